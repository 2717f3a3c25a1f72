//! A series of specimens (`tagdeflect report --series FOLDER...`): each specimen's values;
//! the specimens excluded with their reason (a report that is not valid, or an exclusion the
//! lab gives); over the specimens used, per quantity the mean, the standard deviation and the
//! coefficient of variation; for EN 14651 the characteristic values (EN 1990 Annex D) and the
//! fib Model Code 2010 class ([`crate::series_stats`]); the curves overlaid. `series.json`,
//! `series.csv`, `series.html` (self-contained), `series_curves.svg`.

use std::fmt::Write;
use std::path::{Path, PathBuf};

use plotters::prelude::*;

use crate::error::ReportError;
use crate::plots::{err, PlotError};
use crate::report::Report;
use crate::series_stats::{characteristic, fib_class, stats, Characteristic, Stat};
use crate::standard::Standard;

pub use crate::series_stats::k_n;

/// The residual strengths whose characteristic values EN 14651 series report.
const EN_KEYS: [&str; 5] = ["fL", "fR1", "fR2", "fR3", "fR4"];

/// Where EN 14651 series' characteristic values come from.
pub const KN_SOURCE: &str = "EN 1990:2002 Annex D (D7.2, Table D1): f_k = f_m − k_n·s, 5 % fractile, variance unknown";
/// Where the class comes from.
pub const FIB_SOURCE: &str = "fib Model Code 2010 §5.6.3: strength class f_R1k (1.0 … 8.0 MPa), letter from f_R3k/f_R1k (a 0.5–0.7, b 0.7–0.9, c 0.9–1.1, d 1.1–1.3, e ≥ 1.3)";

/// The specimens of a series split into those used and those excluded, with the reason.
#[derive(Debug, Clone, PartialEq)]
pub struct Selection {
    /// Indices of the reports used.
    pub used: Vec<usize>,
    /// Indices of the reports excluded and why.
    pub excluded: Vec<(usize, String)>,
}

/// The selection: a specimen the lab excludes (`(id, reason)`: its specimen id or its
/// folder's name) is left out with the lab's reason, a report that is not valid with its
/// reasons; the others are used. An exclusion naming no specimen is an error.
pub fn select(reports: &[Report], lab: &[(String, String)]) -> Result<Selection, String> {
    for (id, _) in lab {
        if !reports.iter().any(|r| names_of(r).contains(id)) {
            let known: Vec<String> = reports.iter().map(specimen_name).collect();
            return Err(format!("--exclude {id}: no specimen of the series has this id (specimens: {known:?})"));
        }
    }
    let mut sel = Selection { used: Vec::new(), excluded: Vec::new() };
    for (i, r) in reports.iter().enumerate() {
        if let Some((_, why)) = lab.iter().find(|(id, _)| names_of(r).contains(id)) {
            sel.excluded.push((i, format!("excluded by the lab: {why}")));
        } else if !r.validity.valid {
            sel.excluded.push((i, format!("not a valid test: {}", r.validity.reasons.join(" "))));
        } else {
            sel.used.push(i);
        }
    }
    Ok(sel)
}

/// The names a specimen answers to in `--exclude`: its id and its folder's name.
fn names_of(r: &Report) -> Vec<String> {
    let mut v = vec![specimen_name(r)];
    if let Some(d) = r.feed_path.parent().and_then(|d| d.file_name()) {
        v.push(d.to_string_lossy().into_owned());
    }
    v
}

/// The series' figures over the specimens used.
struct Figures {
    stats: Vec<Stat>,
    characteristic: Vec<Characteristic>,
    class: Option<String>,
}

fn figures(reports: &[Report], sel: &Selection) -> Figures {
    let used: Vec<&Report> = sel.used.iter().map(|&i| &reports[i]).collect();
    let st = stats(reports.first(), &used);
    let en = reports.first().is_some_and(|r| r.standard == Standard::En14651);
    let characteristic = if en { characteristic(&st, &EN_KEYS) } else { Vec::new() };
    let ck = |k: &str| characteristic.iter().find(|c| c.key == k).and_then(|c| c.value);
    let class = match (ck("fR1"), ck("fR3")) {
        (Some(a), Some(b)) => fib_class(a, b),
        _ => None,
    };
    Figures { stats: st, characteristic, class }
}

fn esc(s: &str) -> String {
    s.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;").replace('"', "&quot;")
}

/// The name of a specimen in the series: its id, else its feed's folder or file name.
pub fn specimen_name(r: &Report) -> String {
    if let Some(s) = &r.lab.specimen {
        return s.clone();
    }
    let p = &r.feed_path;
    let stem = p.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
    match (stem.as_str(), p.parent().and_then(|d| d.file_name())) {
        ("feed", Some(d)) => d.to_string_lossy().into_owned(),
        _ => stem,
    }
}

/// The folder a specimen's report goes into under `--out`: its [`specimen_name`] made a safe
/// file name, as `test.json`'s `specimen` is not trusted (`../../x`, `/abs/path`). Every
/// character but letters, digits, `_`, `-` and `.` becomes `_`, a leading `.` too (so `..` and
/// hidden names cannot be made), at most 64 characters; an empty name is `specimen`.
pub fn folder_name(r: &Report) -> String {
    safe_file_name(&specimen_name(r))
}

/// `name` as one safe path component (see [`folder_name`]).
pub fn safe_file_name(name: &str) -> String {
    let ok = |c: char| c.is_alphanumeric() || matches!(c, '_' | '-' | '.');
    let mut out: String = name.trim().chars().take(64).map(|c| if ok(c) { c } else { '_' }).collect();
    let dots = out.chars().take_while(|&c| c == '.').count();
    out.replace_range(..dots, &"_".repeat(dots));
    if out.is_empty() {
        out = "specimen".into();
    }
    out
}

fn num(v: f64, d: usize) -> String {
    if v.is_finite() {
        format!("{v:.d$}")
    } else {
        "—".into()
    }
}

/// A number for JSON: `null` when not finite.
fn jnum(v: f64) -> serde_json::Value {
    if v.is_finite() {
        serde_json::json!(v)
    } else {
        serde_json::Value::Null
    }
}

/// `series.json`.
fn series_json(reports: &[Report], names: &[String], sel: &Selection, f: &Figures) -> serde_json::Value {
    use serde_json::json;
    let specimens: Vec<serde_json::Value> = reports
        .iter()
        .zip(names)
        .enumerate()
        .map(|(i, (r, n))| {
            let mut m = serde_json::Map::new();
            m.insert("specimen".into(), json!(n));
            m.insert("feed".into(), json!(r.feed_path.display().to_string()));
            m.insert("valid".into(), json!(r.validity.valid));
            m.insert("invalid_reasons".into(), json!(r.validity.reasons));
            m.insert("used".into(), json!(sel.used.contains(&i)));
            for e in &r.entries {
                if let Ok(q) = &e.result {
                    m.insert(e.key.into(), serde_json::to_value(q.rounded()).expect("quantity"));
                }
            }
            serde_json::Value::Object(m)
        })
        .collect();
    let stats_json: serde_json::Map<String, serde_json::Value> = f
        .stats
        .iter()
        .map(|s| (s.key.to_string(), json!({"n": s.n, "mean": jnum(s.mean), "sd": jnum(s.sd), "cov_pct": jnum(s.cov_pct), "unit": s.unit})))
        .collect();
    let standard = reports.first().map_or(Standard::AstmC1609, |r| r.standard);
    let mut doc = json!({
        "standard": standard.id(), "standard_title": standard.title(), "specimens": specimens,
        "excluded": sel.excluded.iter().map(|(i, why)| json!({"specimen": names[*i], "reason": why})).collect::<Vec<_>>(),
        "n_total": reports.len(), "n_used": sel.used.len(),
        "statistics": stats_json, "all_valid": reports.iter().all(|r| r.validity.valid),
    });
    if standard == Standard::En14651 {
        let ch: serde_json::Map<String, serde_json::Value> = f
            .characteristic
            .iter()
            .map(|c| {
                let v = match c.value {
                    Some(v) => json!({"value": v, "n": c.n, "k_n": c.k_n, "unit": "MPa"}),
                    None => json!({"value": null, "n": c.n, "not_determined": format!("n = {} < 3: EN 1990 Table D1 gives no k_n", c.n)}),
                };
                (format!("{}k", c.key), v)
            })
            .collect();
        doc["characteristic"] = serde_json::Value::Object(ch);
        doc["characteristic_source"] = json!(KN_SOURCE);
        doc["fib_class"] = json!({"class": f.class, "source": FIB_SOURCE});
    }
    doc
}

/// A CSV field, quoted when it must be.
fn csv_field(s: &str) -> String {
    if s.contains([',', '"', '\n']) {
        format!("\"{}\"", s.replace('"', "\"\""))
    } else {
        s.to_string()
    }
}

/// `series.csv`: one row per specimen (used or excluded with the reason), then the mean,
/// the standard deviation and the CoV over the specimens used, and the characteristic values.
fn series_csv(reports: &[Report], names: &[String], sel: &Selection, f: &Figures) -> String {
    let mut c = String::from("specimen,used,excluded_reason");
    for s in &f.stats {
        let _ = write!(c, ",{} [{}],{} sigma [{}]", s.key, s.unit, s.key, s.unit);
    }
    c.push('\n');
    for (i, (r, n)) in reports.iter().zip(names).enumerate() {
        let why = sel.excluded.iter().find(|(k, _)| *k == i).map_or("", |(_, w)| w.as_str());
        let _ = write!(c, "{},{},{}", csv_field(n), if sel.used.contains(&i) { "yes" } else { "no" }, csv_field(why));
        for s in &f.stats {
            match r.entries.iter().find(|e| e.key == s.key).and_then(|e| e.result.as_ref().ok()) {
                Some(q) => {
                    let _ = write!(c, ",{},{}", q.value, q.sigma);
                }
                None => c.push_str(",,"),
            }
        }
        c.push('\n');
    }
    let rows: [(&str, fn(&Stat) -> f64); 3] = [("mean", |s| s.mean), ("sd", |s| s.sd), ("cov_pct", |s| s.cov_pct)];
    for (label, get) in rows {
        let _ = write!(c, "{label},,n used = {}", sel.used.len());
        for s in &f.stats {
            let v = get(s);
            let _ = write!(c, ",{},", if v.is_finite() { v.to_string() } else { String::new() });
        }
        c.push('\n');
    }
    for ch in &f.characteristic {
        let _ = writeln!(
            c,
            "{}k,,{},{}",
            ch.key,
            csv_field(&format!("k_n = {}", ch.k_n.map_or("—".into(), |k| k.to_string()))),
            ch.value.map_or("not determined (n < 3)".into(), |v| v.to_string())
        );
    }
    c
}

/// Writes `series.json`, `series.csv`, `series.html` and the overlaid curves into `dir`;
/// `lab_excluded`: the lab's exclusions `(id, reason)`.
pub fn write(reports: &[Report], lab_excluded: &[(String, String)], dir: &Path) -> Result<Vec<PathBuf>, ReportError> {
    std::fs::create_dir_all(dir)
        .map_err(|e| ReportError::Io { path: dir.to_path_buf(), message: format!("cannot create the folder: {e}") })?;
    let sel = select(reports, lab_excluded).map_err(|message| ReportError::Data { path: dir.to_path_buf(), message })?;
    let f = figures(reports, &sel);
    let names: Vec<String> = reports.iter().map(specimen_name).collect();
    let mut files = Vec::new();
    let mut put = |name: &str, bytes: &[u8]| -> Result<(), ReportError> {
        let p = dir.join(name);
        crate::write_atomic(&p, bytes)?;
        files.push(p);
        Ok(())
    };
    put("series.json", serde_json::to_string_pretty(&series_json(reports, &names, &sel, &f)).expect("json").as_bytes())?;
    put("series.csv", series_csv(reports, &names, &sel, &f).as_bytes())?;
    crate::plots::ensure_font()?;
    let svg = overlay_svg(reports, &names).map_err(|e| ReportError::Plot { name: "series_curves".into(), message: e.to_string() })?;
    put("series_curves.svg", svg.as_bytes())?;
    put("series.html", series_html(reports, &names, &sel, &f, &svg).as_bytes())?;
    Ok(files)
}

/// `series.html`.
fn series_html(reports: &[Report], names: &[String], sel: &Selection, f: &Figures, svg: &str) -> String {
    let standard = reports.first().map_or(Standard::AstmC1609, |r| r.standard);
    let mut h = String::new();
    let _ = write!(
        h,
        "<!DOCTYPE html><html lang=\"en\"><head><meta charset=\"utf-8\"><title>Series — {}</title><style>body{{font-family:\"DejaVu Sans\",sans-serif;max-width:1100px;margin:0 auto;padding:20px;font-size:13px}}table{{border-collapse:collapse;width:100%}}th,td{{border-bottom:1px solid #ccd;padding:3px 6px;text-align:right}}th:first-child,td:first-child{{text-align:left}}tr.stat td{{font-weight:600;background:#f1f4f8}}.bad{{color:#b3261e}}svg{{width:100%;height:auto}}</style></head><body><h1>Series of {} specimens — {}</h1><p>{} used, {} excluded.</p>",
        esc(standard.id()),
        reports.len(),
        esc(standard.title()),
        sel.used.len(),
        sel.excluded.len()
    );
    h.push_str("<table><tr><th>specimen</th><th>used</th>");
    for s in &f.stats {
        let _ = write!(h, "<th>{} [{}]</th>", s.key, esc(&s.unit));
    }
    h.push_str("</tr>");
    for (i, (r, n)) in reports.iter().zip(names).enumerate() {
        let used = sel.used.contains(&i);
        let _ =
            write!(h, "<tr><td>{}</td><td class=\"{}\">{}</td>", esc(n), if used { "" } else { "bad" }, if used { "yes" } else { "no" });
        for s in &f.stats {
            let cell = r.entries.iter().find(|e| e.key == s.key).and_then(|e| e.result.as_ref().ok()).map_or("—".to_string(), |q| {
                let d = q.decimals();
                let q = q.rounded();
                format!("{:.d$} ± {:.d$}", q.value, q.sigma)
            });
            let _ = write!(h, "<td>{cell}</td>");
        }
        h.push_str("</tr>");
    }
    for (label, k) in [("mean", 0), ("standard deviation", 1), ("CoV [%]", 2)] {
        let _ = write!(h, "<tr class=\"stat\"><td>{label} (n = {})</td><td></td>", sel.used.len());
        for s in &f.stats {
            let _ = write!(h, "<td>{}</td>", num([s.mean, s.sd, s.cov_pct][k], if k == 2 { 1 } else { 3 }));
        }
        h.push_str("</tr>");
    }
    h.push_str("</table>");
    if !sel.excluded.is_empty() {
        h.push_str("<h2>Excluded</h2><ul>");
        for (i, why) in &sel.excluded {
            let _ = write!(h, "<li><b>{}</b>: {}</li>", esc(&names[*i]), esc(why));
        }
        h.push_str("</ul>");
    }
    if standard == Standard::En14651 {
        h.push_str("<h2>Characteristic values</h2><table><tr><th>quantity</th><th>n</th><th>k_n</th><th>value [MPa]</th></tr>");
        for c in &f.characteristic {
            let v = c.value.map_or("not determined (n &lt; 3)".to_string(), |v| format!("{v:.2}"));
            let _ = write!(
                h,
                "<tr><td>{}k</td><td>{}</td><td>{}</td><td>{v}</td></tr>",
                c.key,
                c.n,
                c.k_n.map_or("—".into(), |k| k.to_string())
            );
        }
        let _ = write!(
            h,
            "</table><p>{}.</p><p><b>fib Model Code 2010 class:</b> {} — {}.</p>",
            esc(KN_SOURCE),
            f.class.as_deref().map_or("not determined".to_string(), esc),
            esc(FIB_SOURCE)
        );
    }
    h.push_str("<h2>Curves</h2>");
    h.push_str(svg.trim_start_matches(|c| c != '<').trim_start_matches("<?xml version=\"1.0\" encoding=\"UTF-8\"?>"));
    h.push_str("<p>Each specimen's own report is in its sub-folder.</p></body></html>");
    h
}

fn overlay_svg(reports: &[Report], names: &[String]) -> Result<String, PlotError> {
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, (960, 560)).into_drawing_area();
        root.fill(&WHITE).map_err(err)?;
        let xmax = reports.iter().flat_map(|r| r.curve.xs.iter().cloned()).filter(|v| v.is_finite()).fold(0.0f64, f64::max).max(1e-3);
        let pmax = reports.iter().flat_map(|r| r.curve.load.iter().cloned()).filter(|v| v.is_finite()).fold(0.0f64, f64::max).max(1e-3);
        let x_axis = reports.first().map_or("x".to_string(), |r| r.x_axis.clone());
        let mut chart = ChartBuilder::on(&root)
            .margin(14)
            .x_label_area_size(44)
            .y_label_area_size(60)
            .build_cartesian_2d(0.0..xmax * 1.05, 0.0..pmax * 1.1)
            .map_err(err)?;
        chart.configure_mesh().x_desc(format!("{x_axis} [mm]")).y_desc("load [kN]").draw().map_err(err)?;
        for (k, (r, n)) in reports.iter().zip(names).enumerate() {
            let color = Palette99::pick(k).to_rgba();
            let step = (r.curve.len() / 2000).max(1);
            let pts: Vec<(f64, f64)> = r.curve.xs.iter().zip(&r.curve.load).step_by(step).map(|(&x, &p)| (x, p)).collect();
            chart
                .draw_series(LineSeries::new(pts, color.stroke_width(2)))
                .map_err(err)?
                .label(n.clone())
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], color.stroke_width(2)));
        }
        chart.configure_series_labels().background_style(WHITE.mix(0.85)).border_style(BLACK).draw().map_err(err)?;
        root.present().map_err(err)?;
    }
    Ok(svg)
}
