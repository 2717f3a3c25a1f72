//! The outputs of a report: every file written into its folder (`curve.csv`, the plots as
//! SVG and PNG, `report.json`, `report.html`), each through a temporary sibling and a rename.

use std::path::{Path, PathBuf};

use crate::{csv_out, html, plots, Feed, Report, ReportError, Standard};

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

/// Writes every output of a report into `dir`; returns the files written.
pub fn write(report: &Report, feed: &Feed, dir: &Path) -> Result<Vec<PathBuf>, ReportError> {
    std::fs::create_dir_all(dir)
        .map_err(|e| ReportError::Io { path: dir.to_path_buf(), message: format!("cannot create the folder: {e}") })?;
    let mut files = Vec::new();
    let mut put = |name: &str, bytes: &[u8]| -> Result<(), ReportError> {
        let p = dir.join(name);
        write_atomic(&p, bytes)?;
        files.push(p);
        Ok(())
    };
    let mut csv_bytes = Vec::new();
    csv_out::write_curve_csv(feed, &mut csv_bytes).map_err(|e| ReportError::Io { path: dir.join("curve.csv"), message: e.to_string() })?;
    put("curve.csv", &csv_bytes)?;
    let plots = plots::draw_all(report, feed)?;
    for p in &plots {
        put(&format!("{}.svg", p.name), p.svg.as_bytes())?;
        put(&format!("{}.png", p.name), &p.png)?;
    }
    let json = serde_json::to_string_pretty(&to_json(report)).expect("report serialises");
    put("report.json", json.as_bytes())?;
    put("report.html", html::render(report, &plots).as_bytes())?;
    Ok(files)
}

/// `report.json`: every quantity as `{"value", "sigma", "unit"}` under the SPEC keys, plus
/// `standard`, `specimen`, `qc`, and how each value was found.
fn to_json(report: &Report) -> serde_json::Value {
    use serde_json::{json, Map, Value};
    let mut root = Map::new();
    root.insert("standard".into(), json!(report.standard.id()));
    root.insert("standard_title".into(), json!(report.standard.title()));
    let b = &report.beam;
    let mut spec = json!({
        "width_mm": b.width_mm, "depth_mm": b.depth_mm, "span_mm": b.span_mm,
        "source": "config [specimen.beam]",
        "loading": match report.standard { Standard::En14651 => "three-point, notched at midspan", _ => "four-point, loads at the third points" },
    });
    if let Some(n) = b.notch_mm {
        spec["notch_mm"] = json!(n);
        spec["h_sp_mm"] = json!(b.ligament_mm());
    }
    root.insert("specimen".into(), spec);
    let mut undetermined = Map::new();
    let mut defs = Map::new();
    for e in &report.entries {
        match &e.result {
            Ok(q) => {
                root.insert(e.key.into(), serde_json::to_value(q).expect("quantity"));
            }
            Err(why) => {
                undetermined.insert(e.key.into(), json!(why));
            }
        }
        defs.insert(e.key.into(), json!({"name": e.name, "method": e.method, "clause": e.clause, "checked_against_text": false}));
    }
    root.insert("undetermined".into(), Value::Object(undetermined));
    root.insert("definitions".into(), Value::Object(defs));
    let c = &report.curve;
    root.insert(
        "curve".into(),
        json!({
            "x": report.x_name, "x_source": report.x_source, "points": c.len(),
            "smooth_points": c.smooth_points,
            "load_sigma_kN": c.load_sigma, "load_noise_kN": c.load_noise,
            "load_resolution_kN": report.options.load_resolution_kn.unwrap_or(0.0),
            "x_scatter_mm": c.x_noise, "x_reference_sigma_mm": c.x_ref_sigma,
            "max_x_mm": c.xs.iter().cloned().fold(f64::NEG_INFINITY, f64::max),
        }),
    );
    root.insert("notes".into(), json!(report.notes));
    root.insert("feed".into(), json!(report.feed_path.display().to_string()));
    root.insert("qc".into(), serde_json::to_value(&report.qc).expect("qc"));
    Value::Object(root)
}
