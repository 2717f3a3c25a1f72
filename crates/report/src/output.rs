//! The outputs of a report: every file written into its folder (`curve.csv`, the plots as
//! SVG and PNG, `report.json`, `report.html`), each through a temporary sibling and a rename.

use std::path::{Path, PathBuf};

use crate::error::ReportError;
use crate::feed_reader::Feed;
use crate::report::Report;
use crate::standard::Standard;
use crate::{csv_out, html, plots};

/// Writes a file through a temporary sibling and a rename: a reader never sees half a file,
/// and an older file of the same name stays whole until the new one is complete.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), ReportError> {
    let io = |e: std::io::Error| ReportError::Io { path: path.to_path_buf(), message: e.to_string() };
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(io)?;
    }
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let tmp = path.with_file_name(format!(".{name}.tmp"));
    std::fs::write(&tmp, bytes).map_err(io)?;
    std::fs::rename(&tmp, path).map_err(io)
}

/// Writes a file as [`write_atomic`] does, its bytes written by `fill` straight into the
/// temporary sibling (a long feed's `curve.csv` is never held whole in memory).
fn write_atomic_streamed(path: &Path, fill: impl FnOnce(&mut dyn std::io::Write) -> Result<(), String>) -> Result<(), ReportError> {
    use std::io::Write;
    let io = |message: String| ReportError::Io { path: path.to_path_buf(), message };
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let tmp = path.with_file_name(format!(".{name}.tmp"));
    let mut w = std::io::BufWriter::with_capacity(1 << 16, std::fs::File::create(&tmp).map_err(|e| io(e.to_string()))?);
    let written = fill(&mut w).and_then(|()| w.flush().map_err(|e| e.to_string()));
    drop(w);
    if let Err(e) = written {
        let _ = std::fs::remove_file(&tmp);
        return Err(io(e));
    }
    std::fs::rename(&tmp, path).map_err(|e| io(e.to_string()))
}

/// Writes every output of a report into `dir`; returns the files written.
pub fn write(report: &Report, feed: &Feed, dir: &Path) -> Result<Vec<PathBuf>, ReportError> {
    std::fs::create_dir_all(dir)
        .map_err(|e| ReportError::Io { path: dir.to_path_buf(), message: format!("cannot create the folder: {e}") })?;
    let csv = dir.join("curve.csv");
    write_atomic_streamed(&csv, |w| csv_out::write_curve_csv(feed, w).map_err(|e| e.to_string()))?;
    let mut files = vec![csv];
    let mut put = |name: &str, bytes: &[u8]| -> Result<(), ReportError> {
        let p = dir.join(name);
        write_atomic(&p, bytes)?;
        files.push(p);
        Ok(())
    };
    let plots = plots::draw_all(report, feed)?;
    for p in &plots {
        put(&format!("{}.svg", p.name), p.svg.as_bytes())?;
        put(&format!("{}.png", p.name), &p.png)?;
    }
    let inputs = input_hashes(report, dir)?;
    put("report.html", html::render(report, &plots, &inputs).as_bytes())?;
    if report.options.pdf {
        match print_pdf(&dir.join("report.html"), &dir.join("report.pdf")) {
            Ok(true) => files.push(dir.join("report.pdf")),
            Ok(false) => tracing::info!("no Chromium found: report.pdf not printed (print report.html from a browser)"),
            Err(e) => tracing::warn!("report.pdf could not be printed: {e}"),
        }
    }
    // report.json last, with the SHA-256 of every other output (`report verify`).
    let mut outputs = serde_json::Map::new();
    for f in &files {
        let sha = sha256_file(f).map_err(|e| ReportError::Io { path: f.clone(), message: format!("cannot hash the output: {e}") })?;
        outputs.insert(f.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default(), serde_json::json!(sha));
    }
    let mut json = to_json(report, &inputs);
    json["outputs"] = serde_json::Value::Object(outputs);
    let p = dir.join("report.json");
    write_atomic(&p, serde_json::to_string_pretty(&json).expect("report serialises").as_bytes())?;
    files.push(p);
    Ok(files)
}

/// `path` relative to `base` (both made absolute; `..` where they part), as `report verify`
/// finds an input from the report folder's parent.
fn relative_to(path: &Path, base: &Path) -> PathBuf {
    let (Ok(p), Ok(b)) = (std::path::absolute(path), std::path::absolute(base)) else { return path.to_path_buf() };
    let (pc, bc): (Vec<_>, Vec<_>) = (p.components().collect(), b.components().collect());
    let common = pc.iter().zip(&bc).take_while(|(a, b)| a == b).count();
    let mut out = PathBuf::new();
    for _ in common..bc.len() {
        out.push("..");
    }
    for c in &pc[common..] {
        out.push(c);
    }
    out
}

/// The Chromium to print with: `$TAGDEFLECT_CHROMIUM`, else `chromium` / `chromium-browser`
/// on the PATH.
fn chromium() -> Option<PathBuf> {
    if let Some(p) = std::env::var_os("TAGDEFLECT_CHROMIUM") {
        return Some(PathBuf::from(p));
    }
    let path = std::env::var_os("PATH")?;
    std::env::split_paths(&path).flat_map(|d| ["chromium", "chromium-browser"].map(|n| d.join(n))).find(|p| p.is_file())
}

/// Prints `html` to `pdf` with headless Chromium (A4, the page's own header and footer with
/// page numbers); `Ok(false)` when there is no Chromium. The browser is killed after 120 s.
pub fn print_pdf(html: &Path, pdf: &Path) -> Result<bool, PdfError> {
    let Some(bin) = chromium() else { return Ok(false) };
    let profile = std::env::temp_dir().join(format!(
        "tagdeflect-pdf-{}-{}",
        std::process::id(),
        chrono::Utc::now().timestamp_nanos_opt().unwrap_or(0)
    ));
    let tmp = pdf.with_file_name(".report.pdf.tmp");
    let url = format!("file://{}", std::path::absolute(html).map_err(PdfError::Io)?.display());
    let mut child = std::process::Command::new(&bin)
        .args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--no-pdf-header-footer",
        ])
        .arg(format!("--user-data-dir={}", profile.display()))
        .arg(format!("--print-to-pdf={}", tmp.display()))
        .arg(url)
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .map_err(|source| PdfError::Spawn { bin: bin.clone(), source })?;
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(120);
    let status = loop {
        match child.try_wait() {
            Ok(Some(s)) => break Ok(s),
            Ok(None) if std::time::Instant::now() < deadline => std::thread::sleep(std::time::Duration::from_millis(50)),
            Ok(None) => {
                let _ = child.kill();
                let _ = child.wait();
                break Err(PdfError::Timeout);
            }
            Err(e) => break Err(PdfError::Io(e)),
        }
    };
    let _ = std::fs::remove_dir_all(&profile);
    let status = status?;
    if !status.success() || !tmp.is_file() {
        let _ = std::fs::remove_file(&tmp);
        return Err(PdfError::NoPdf { bin, status });
    }
    std::fs::rename(&tmp, pdf).map_err(PdfError::Io)?;
    Ok(true)
}

/// Why Chromium did not print the PDF.
#[derive(Debug, thiserror::Error)]
pub enum PdfError {
    /// Making the HTML's path absolute, waiting for the browser or moving the PDF failed.
    #[error(transparent)]
    Io(std::io::Error),
    /// The browser could not be started.
    #[error("{}: {source}", bin.display())]
    Spawn {
        /// The browser.
        bin: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// The browser ran past its deadline and was killed.
    #[error("Chromium did not finish within 120 s")]
    Timeout,
    /// The browser ended without writing the PDF.
    #[error("{} exited with {status} without a PDF", bin.display())]
    NoPdf {
        /// The browser.
        bin: PathBuf,
        /// How it ended.
        status: std::process::ExitStatus,
    },
}

/// One input of a report with its SHA-256.
#[derive(Debug, Clone, PartialEq)]
pub struct InputHash {
    /// What it is (`feed`, `utm`, `config`, `calibration`).
    pub role: String,
    /// Its path relative to the report folder's parent (where `report verify` looks).
    pub name: PathBuf,
    /// Its path, absolute when it could be made so.
    pub path: PathBuf,
    /// SHA-256 of its first `bytes` bytes, lower-case hex.
    pub sha256: String,
    /// Its length when it was hashed: a feed still being written grows after, and `report
    /// verify` checks this prefix (docs/report.md).
    pub bytes: u64,
}

/// SHA-256 of a file, lower-case hex.
pub fn sha256_file(path: &Path) -> Result<String, std::io::Error> {
    sha256_prefix(path, None).map(|(sha, _)| sha)
}

/// SHA-256 (lower-case hex) of the first `limit` bytes of a file (all of it for `None`: its
/// length when opened), and the number of bytes hashed (fewer than `limit` when it is shorter).
pub fn sha256_prefix(path: &Path, limit: Option<u64>) -> Result<(String, u64), std::io::Error> {
    use sha2::Digest;
    use std::io::Read;
    let f = std::fs::File::open(path)?;
    let limit = match limit {
        Some(l) => l,
        None => f.metadata()?.len(),
    };
    let mut f = f.take(limit);
    let mut h = sha2::Sha256::new();
    let mut buf = vec![0u8; 1 << 16];
    let mut bytes = 0u64;
    loop {
        let n = f.read(&mut buf)?;
        if n == 0 {
            break;
        }
        h.update(&buf[..n]);
        bytes += n as u64;
    }
    Ok((h.finalize().iter().map(|b| format!("{b:02x}")).collect(), bytes))
}

/// Every input of the report hashed (feed, UTM stream, then the caller's: config, calibration files).
fn input_hashes(report: &Report, dir: &Path) -> Result<Vec<InputHash>, ReportError> {
    let base = dir.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    let mut list: Vec<(String, PathBuf)> = vec![("feed".into(), report.feed_path.clone())];
    if let Some(u) = &report.utm_path {
        list.push(("utm".into(), u.clone()));
    }
    list.extend(report.inputs.iter().cloned());
    list.into_iter()
        .map(|(role, path)| {
            let (sha256, bytes) = sha256_prefix(&path, None)
                .map_err(|e| ReportError::Io { path: path.clone(), message: format!("cannot hash the input: {e}") })?;
            let name = relative_to(&path, base);
            let path = std::path::absolute(&path).unwrap_or(path);
            Ok(InputHash { role, name, path, sha256, bytes })
        })
        .collect()
}

/// `report.json`: every quantity as `{"value", "sigma", "unit"}` under the SPEC keys, plus
/// `standard`, `specimen`, `qc`, and how each value was found.
fn to_json(report: &Report, inputs: &[InputHash]) -> serde_json::Value {
    use serde_json::{json, Map, Value};
    let mut root = Map::new();
    root.insert("standard".into(), json!(report.standard.id()));
    root.insert("standard_title".into(), json!(report.standard.title()));
    if let Some(e) = &report.lab.edition {
        root.insert("standard_edition".into(), json!(e));
    }
    root.insert("response".into(), json!(report.options.response.id()));
    root.insert("valid".into(), json!(report.validity.valid));
    root.insert("invalid_reasons".into(), json!(report.validity.reasons));
    root.insert("validity_unchecked".into(), json!(report.validity.unchecked));
    root.insert(
        "rates".into(),
        Value::Array(
            report
                .validity
                .rates
                .iter()
                .map(|(p, r, (lo, hi))| json!({"phase": p, "mm_per_min": r, "window_mm_per_min": [lo, hi]}))
                .collect(),
        ),
    );
    let b = &report.beam;
    let mut spec = json!({
        "width_mm": b.width_mm, "depth_mm": b.depth_mm, "span_mm": b.span_mm,
        "source": report.beam_source,
        "loading": match report.standard { Standard::En14651 => "three-point, notched at midspan", _ => "four-point, loads at the third points" },
    });
    if let Some(n) = b.notch_mm {
        spec["notch_mm"] = json!(n);
        spec["h_sp_mm"] = json!(b.ligament_mm());
    }
    for (k, v) in [
        ("width_tol_mm", b.width_tol_mm),
        ("depth_tol_mm", b.depth_tol_mm),
        ("span_tol_mm", b.span_tol_mm),
        ("notch_tol_mm", b.notch_tol_mm),
    ] {
        if let Some(v) = v {
            spec[k] = json!(v);
        }
    }
    let lab = &report.lab;
    for (k, v) in [
        ("id", &lab.specimen),
        ("operator", &lab.operator),
        ("cast_date", &lab.cast_date),
        ("test_date", &lab.test_date),
        ("machine", &lab.machine),
        ("fracture", &lab.fracture),
        ("laboratory", &lab.laboratory),
    ] {
        if let Some(v) = v {
            spec[k] = json!(v);
        }
    }
    if let Some(a) = lab.age_days() {
        spec["age_days"] = json!(a);
    }
    test_keys(report, &mut root, &mut spec);
    root.insert("specimen".into(), spec);
    root.insert(
        "inputs".into(),
        json!({
            "files": inputs.iter().map(|i| json!({"role": i.role, "name": i.name.display().to_string(), "path": i.path.display().to_string(), "sha256": i.sha256, "bytes": i.bytes})).collect::<Vec<_>>(),
            "software": {"name": "tagdeflect", "version": env!("CARGO_PKG_VERSION")},
        }),
    );
    root.insert("load_source".into(), json!(report.load_source));
    let mut undetermined = Map::new();
    let mut defs = Map::new();
    for e in &report.entries {
        match &e.result {
            Ok(q) => {
                root.insert(e.key.into(), serde_json::to_value(q.rounded()).expect("quantity"));
            }
            Err(why) => {
                undetermined.insert(e.key.into(), json!(why));
            }
        }
        defs.insert(e.key.into(), json!({"name": e.name, "method": e.method, "clause": e.clause}));
    }
    root.insert("undetermined".into(), Value::Object(undetermined));
    root.insert("definitions".into(), Value::Object(defs));
    let c = &report.curve;
    root.insert(
        "curve".into(),
        json!({
            "x": report.x_name, "x_source": report.x_source, "points": c.len(),
            "smooth_points": c.smooth_points,
            "smooth_points_reduced_at": c.smooth_reduced,
            "load_sigma_kN": c.load_sigma, "load_noise_kN": c.load_noise,
            "load_from_utm": c.load_from_utm, "load_period_s": c.load_period_s,
            "load_resolution_kN": report.options.load_resolution_kn.unwrap_or(0.0),
            "x_scatter_mm": c.x_noise, "x_reference_sigma_mm": c.x_ref_sigma,
            "max_x_mm": c.xs.iter().cloned().fold(f64::NEG_INFINITY, f64::max),
        }),
    );
    root.insert("notes".into(), json!(report.notes));
    let method = report.test.as_ref().and_then(|t| t.method.as_ref());
    root.insert("method_statement".into(), json!(crate::method_statement::statement(method, report.standard)));
    let rules: Vec<_> = crate::method_statement::rules_in_force(report.options.method.as_ref(), report.standard)
        .into_iter()
        .map(|(rule, source)| json!({"rule": rule, "source": source}))
        .collect();
    root.insert("rules".into(), json!(rules));
    root.insert("feed".into(), json!(report.feed_path.display().to_string()));
    if let Some((k, n)) = report_run(report) {
        root.insert("run".into(), json!({"index": k, "of": n}));
    }
    root.insert("qc".into(), serde_json::to_value(&report.qc).expect("qc"));
    if let Some(c) = crate::control_section::json(report) {
        root.insert("control".into(), c);
    }
    Value::Object(root)
}

/// What a test folder's record adds (SPEC "Report"): `operator`, `method`, `events`, the
/// operator's `test_notes`, `crack` and the `verification` in force; in `specimen` where each dimension came from
/// (`dimension_sources`) and the specimen's row (`info`).
fn test_keys(report: &Report, root: &mut serde_json::Map<String, serde_json::Value>, spec: &mut serde_json::Value) {
    use serde_json::json;
    if let Some(op) = &report.lab.operator {
        root.insert("operator".into(), json!(op));
    }
    if !report.dimension_sources.is_empty() {
        spec["dimension_sources"] = json!(report.dimension_sources);
    }
    let Some(t) = &report.test else { return };
    if let Some(info) = &t.specimen_info {
        spec["info"] = serde_json::to_value(info).expect("specimen info");
    }
    if let Some(m) = &t.method {
        root.insert("method".into(), serde_json::to_value(m).expect("method"));
    }
    root.insert("events".into(), crate::event_loads::OnCurve::of(report).events_json(&t.events));
    if let Some(n) = &t.meta.notes {
        root.insert("test_notes".into(), json!(n));
    }
    if let Some(c) = &t.crack {
        root.insert("crack".into(), serde_json::to_value(c).expect("crack"));
    }
    if let Some(v) = &t.verification {
        root.insert("verification".into(), serde_json::to_value(v).expect("verification"));
    }
}

fn report_run(report: &Report) -> Option<(usize, usize)> {
    report.run
}
