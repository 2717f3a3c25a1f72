//! A series of specimens (`tagdeflect report --series FEED...`): each specimen's values, and
//! per quantity the mean, the standard deviation and the coefficient of variation, with the
//! curves overlaid — what a testing machine's suite gives for a batch. `series.json`,
//! `series.html` (self-contained), `series_curves.svg` / `.png`.

use std::fmt::Write;
use std::path::{Path, PathBuf};

use plotters::prelude::*;

use crate::error::ReportError;
use crate::plots::{err, PlotError};
use crate::report::Report;

/// Statistics of one quantity over the specimens that have it.
#[derive(Debug, Clone, PartialEq)]
pub struct Stat {
    /// `report.json` key.
    pub key: &'static str,
    /// Unit.
    pub unit: String,
    /// Specimens with a value.
    pub n: usize,
    /// Mean.
    pub mean: f64,
    /// Sample standard deviation (n − 1).
    pub sd: f64,
    /// Coefficient of variation, %.
    pub cov_pct: f64,
}

/// The statistics per quantity, in the standard's order.
pub fn stats(reports: &[Report]) -> Vec<Stat> {
    let Some(first) = reports.first() else { return Vec::new() };
    first
        .entries
        .iter()
        .map(|e| {
            let vals: Vec<f64> = reports
                .iter()
                .filter_map(|r| r.entries.iter().find(|x| x.key == e.key).and_then(|x| x.result.as_ref().ok()).map(|q| q.value))
                .collect();
            let n = vals.len();
            let mean = if n > 0 { vals.iter().sum::<f64>() / n as f64 } else { f64::NAN };
            let sd = if n > 1 { (vals.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1) as f64).sqrt() } else { f64::NAN };
            let unit = e.result.as_ref().map(|q| q.unit.clone()).unwrap_or_default();
            Stat { key: e.key, unit, n, mean, sd, cov_pct: 100.0 * sd / mean.abs() }
        })
        .collect()
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

/// Writes `series.json`, `series.html` and the overlaid curves into `dir`.
pub fn write(reports: &[Report], dir: &Path) -> Result<Vec<PathBuf>, ReportError> {
    use serde_json::json;
    std::fs::create_dir_all(dir)
        .map_err(|e| ReportError::Io { path: dir.to_path_buf(), message: format!("cannot create the folder: {e}") })?;
    let st = stats(reports);
    let names: Vec<String> = reports.iter().map(specimen_name).collect();
    let specimens: Vec<serde_json::Value> = reports
        .iter()
        .zip(&names)
        .map(|(r, n)| {
            let mut m = serde_json::Map::new();
            m.insert("specimen".into(), json!(n));
            m.insert("feed".into(), json!(r.feed_path.display().to_string()));
            m.insert("valid".into(), json!(r.validity.valid));
            m.insert("invalid_reasons".into(), json!(r.validity.reasons));
            for e in &r.entries {
                if let Ok(q) = &e.result {
                    m.insert(e.key.into(), serde_json::to_value(q.rounded()).expect("quantity"));
                }
            }
            serde_json::Value::Object(m)
        })
        .collect();
    let stats_json: serde_json::Map<String, serde_json::Value> = st
        .iter()
        .map(|s| {
            (s.key.to_string(), json!({"n": s.n, "mean": s.mean, "sd": if s.sd.is_finite() { json!(s.sd) } else { json!(null) }, "cov_pct": if s.cov_pct.is_finite() { json!(s.cov_pct) } else { json!(null) }, "unit": s.unit}))
        })
        .collect();
    let standard = reports.first().map_or("", |r| r.standard.id());
    let doc = json!({"standard": standard, "specimens": specimens, "statistics": stats_json, "all_valid": reports.iter().all(|r| r.validity.valid)});
    let mut files = Vec::new();
    let mut put = |name: &str, bytes: &[u8]| -> Result<(), ReportError> {
        let p = dir.join(name);
        crate::write_atomic(&p, bytes)?;
        files.push(p);
        Ok(())
    };
    put("series.json", serde_json::to_string_pretty(&doc).expect("json").as_bytes())?;
    crate::plots::ensure_font()?;
    let svg = overlay_svg(reports, &names).map_err(|e| ReportError::Plot { name: "series_curves".into(), message: e.to_string() })?;
    put("series_curves.svg", svg.as_bytes())?;

    let mut h = String::new();
    let _ = write!(
        h,
        "<!DOCTYPE html><html lang=\"en\"><head><meta charset=\"utf-8\"><title>Series — {}</title><style>body{{font-family:\"DejaVu Sans\",sans-serif;max-width:1100px;margin:0 auto;padding:20px;font-size:13px}}table{{border-collapse:collapse;width:100%}}th,td{{border-bottom:1px solid #ccd;padding:3px 6px;text-align:right}}th:first-child,td:first-child{{text-align:left}}tr.stat td{{font-weight:600;background:#f1f4f8}}.bad{{color:#b3261e}}svg{{width:100%;height:auto}}</style></head><body><h1>Series of {} specimens — {}</h1>",
        esc(standard),
        reports.len(),
        esc(reports.first().map_or("", |r| r.standard.title()))
    );
    h.push_str("<table><tr><th>specimen</th><th>valid</th>");
    for s in &st {
        let _ = write!(h, "<th>{} [{}]</th>", s.key, esc(&s.unit));
    }
    h.push_str("</tr>");
    for (r, n) in reports.iter().zip(&names) {
        let _ = write!(
            h,
            "<tr><td>{}</td><td class=\"{}\">{}</td>",
            esc(n),
            if r.validity.valid { "" } else { "bad" },
            if r.validity.valid { "yes" } else { "no" }
        );
        for s in &st {
            let cell = r.entries.iter().find(|e| e.key == s.key).and_then(|e| e.result.as_ref().ok()).map_or("—".to_string(), |q| {
                let d = q.decimals();
                let q = q.rounded();
                format!("{:.d$} ± {:.d$}", q.value, q.sigma)
            });
            let _ = write!(h, "<td>{cell}</td>");
        }
        h.push_str("</tr>");
    }
    for (label, f) in [("mean", 0), ("standard deviation", 1), ("CoV [%]", 2)] {
        let _ = write!(h, "<tr class=\"stat\"><td>{label}</td><td></td>");
        for s in &st {
            let v = [s.mean, s.sd, s.cov_pct][f];
            let _ = write!(h, "<td>{}</td>", num(v, if f == 2 { 1 } else { 3 }));
        }
        h.push_str("</tr>");
    }
    h.push_str("</table><h2>Curves</h2>");
    h.push_str(svg.trim_start_matches(|c| c != '<').trim_start_matches("<?xml version=\"1.0\" encoding=\"UTF-8\"?>"));
    h.push_str("<p>Each specimen's own report is in its sub-folder.</p></body></html>");
    put("series.html", h.as_bytes())?;
    Ok(files)
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
