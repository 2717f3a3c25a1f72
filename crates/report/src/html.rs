//! `report.html`: one self-contained page (inline CSS, plots inline as SVG, no scripts, no
//! external resources) laid out for the screen and for A4 print.

use std::fmt::Write;

use crate::output::InputHash;
use crate::plots::Plot;
use crate::qc::Qc;
use crate::quantity::Quantity;
use crate::report::{Entry, Report};
use crate::standard::Standard;

pub(crate) fn esc(s: &str) -> String {
    s.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;").replace('"', "&quot;")
}

/// Decimals that show σ with two significant digits (value and σ alike).
pub fn decimals(q: &Quantity) -> usize {
    q.decimals()
}

/// Text inside a CSS string literal.
fn css_string(s: &str) -> String {
    s.chars().filter(|c| !c.is_control() && *c != '<' && *c != '>').map(|c| if c == '"' || c == '\\' { ' ' } else { c }).collect()
}

pub(crate) fn time_utc(t_ns: i64) -> String {
    chrono::DateTime::from_timestamp_nanos(t_ns).format("%Y-%m-%d %H:%M:%S%.3f UTC").to_string()
}

/// `{"field": "clock_offset_ms", "value": {"value": v, "sigma": s}}` as `v ± s ms (field)`.
fn clock_text(v: &serde_json::Value) -> String {
    let field = v["field"].as_str().unwrap_or("");
    let unit = if field.ends_with("_ms") { " ms" } else { "" };
    match (&v["value"]["value"], &v["value"]["sigma"], &v["value"]) {
        (serde_json::Value::Number(x), serde_json::Value::Number(s), _) => {
            format!("{:.1} ± {:.1}{unit} ({field})", x.as_f64().unwrap_or(f64::NAN), s.as_f64().unwrap_or(f64::NAN))
        }
        (_, _, serde_json::Value::Number(x)) => format!("{x}{unit} ({field})"),
        (_, _, other) => format!("{other} ({field})"),
    }
}

const STYLE: &str = r#"
:root { --ink: #1b1f24; --muted: #5b6470; --rule: #d5dae0; --accent: #14469f; --warn: #a0521b; }
* { box-sizing: border-box; }
body { font-family: "DejaVu Sans", "Liberation Sans", Arial, sans-serif; color: var(--ink); margin: 0 auto; max-width: 1000px; padding: 24px 28px; line-height: 1.4; font-size: 14px; }
h1 { font-size: 24px; margin: 0 0 4px; }
h2 { font-size: 18px; margin: 28px 0 8px; padding-bottom: 3px; border-bottom: 2px solid var(--accent); color: var(--accent); }
h3 { font-size: 15px; margin: 16px 0 6px; }
.sub { color: var(--muted); margin: 2px 0; }
table { border-collapse: collapse; width: 100%; margin: 6px 0 10px; }
th, td { text-align: left; padding: 4px 8px; border-bottom: 1px solid var(--rule); vertical-align: top; }
th { background: #f1f4f8; font-weight: 600; }
td.num { text-align: right; font-variant-numeric: tabular-nums; white-space: nowrap; }
td.key { font-family: "DejaVu Sans Mono", monospace; font-size: 12px; color: var(--muted); }
td.clause { font-size: 12px; color: var(--muted); }
tr.undetermined td { color: var(--warn); }
.note { background: #f7f4ea; border-left: 4px solid #d2b24c; padding: 6px 10px; margin: 8px 0; font-size: 13px; }
.warn { color: var(--warn); }
figure { margin: 10px 0 18px; }
figure svg { width: 100%; height: auto; display: block; border: 1px solid var(--rule); }
figcaption { color: var(--muted); font-size: 12px; margin-top: 4px; }
ul { margin: 4px 0 8px 18px; padding: 0; }
footer { margin-top: 30px; color: var(--muted); font-size: 12px; border-top: 1px solid var(--rule); padding-top: 6px; }
.banner { border: 2px solid; padding: 8px 12px; margin: 12px 0; font-size: 14px; }
.banner.bad { border-color: #b3261e; background: #fdecea; color: #7a1a14; }
.banner.good { border-color: #2e7d32; background: #edf7ee; color: #1b4d1f; }
.banner ul { margin: 4px 0 0 18px; }
table.id td { width: 25%; }
tr.informative td { color: var(--muted); }
@page { size: A4; margin: 18mm 14mm 16mm 14mm;
  @top-left { content: var(--page-head, ""); font: 9px "DejaVu Sans", sans-serif; color: #5b6470; }
  @top-right { content: "tagdeflect flexural test report"; font: 9px "DejaVu Sans", sans-serif; color: #5b6470; }
  @bottom-left { content: "Page " counter(page) " of " counter(pages); font: 9px "DejaVu Sans", sans-serif; color: #5b6470; }
  @bottom-right { content: "Signed: ____________________"; font: 9px "DejaVu Sans", sans-serif; color: #5b6470; }
}
@media print {
  body { max-width: none; padding: 0; font-size: 11px; }
  h2 { break-after: avoid; }
  table, figure, .note { break-inside: avoid; }
  figure svg { border: none; }
  a { color: inherit; text-decoration: none; }
}
"#;

/// The HTML page of a report: its sections in order, each written by its own function.
pub fn render(report: &Report, plots: &[Plot], inputs: &[InputHash]) -> String {
    let mut h = String::with_capacity(64 * 1024);
    let std_short = standard_short(report.standard);
    head(&mut h, report, std_short);
    header(&mut h, report, std_short);
    validity_banner(&mut h, report, std_short);
    let in_force = report.test.as_ref().and_then(|t| t.method.as_ref());
    let _ = write!(h, "<p class=\"method-statement\"><b>{}</b></p>", esc(&crate::method_statement::statement(in_force, report.standard)));
    identification(&mut h, report, std_short);
    test_record(&mut h, report);
    results(&mut h, report);
    specimen(&mut h, report);
    curves(&mut h, plots);
    method(&mut h, report);
    crate::control_section::html(&mut h, report);
    quality_control(&mut h, report);
    inputs_table(&mut h, inputs);
    footer(&mut h);
    h
}

/// The standard's short name in the page's titles.
fn standard_short(standard: Standard) -> &'static str {
    match standard {
        Standard::AstmC1609 => "ASTM C1609",
        Standard::AstmC1856 => "ASTM C1856 (flexure per ASTM C1609)",
        Standard::En14651 => "EN 14651",
    }
}

/// `<head>`: the title, the style and the printed page's running head.
fn head(h: &mut String, report: &Report, std_short: &str) {
    let lab = &report.lab;
    let head_text =
        format!("{} — specimen {} — {}", std_short, lab.specimen.as_deref().unwrap_or("(no id)"), lab.test_date.as_deref().unwrap_or(""));
    let _ = write!(
        h,
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\
         <title>Flexural test report — {}</title><style>{STYLE}\n@page {{ @top-left {{ content: \"{}\"; }} }}</style></head><body>\n",
        esc(std_short),
        css_string(&head_text)
    );
}

/// The page's header: the standard, the feed and its time span.
fn header(h: &mut String, report: &Report, std_short: &str) {
    let qc = &report.qc;
    let _ = write!(
        h,
        "<header><h1>Flexural test report — {}</h1><p class=\"sub\">{}{}</p><p class=\"sub\">Feed <code>{}</code>: {} lines, {} to {} ({:.1} s). Measured without contact by tagdeflect {}.</p></header>",
        esc(std_short),
        esc(report.standard.title()),
        report.lab.edition.as_ref().map_or(String::new(), |e| format!(" — edition {}", esc(e))),
        esc(&report.feed_path.display().to_string()),
        qc.lines,
        time_utc(qc.first_t_ns),
        time_utc(qc.last_t_ns),
        qc.duration_s,
        env!("CARGO_PKG_VERSION")
    );
}

/// The validity banner, first: valid, or why not.
fn validity_banner(h: &mut String, report: &Report, std_short: &str) {
    let v = &report.validity;
    if v.valid {
        let _ = write!(h, "<div class=\"banner good\"><b>Valid test of {}</b>: every rule checked holds.</div>", esc(std_short));
        return;
    }
    let _ = write!(
        h,
        "<div class=\"banner bad\"><b>Not a valid test of {}</b> — the values below are for information only, not for a test report:<ul>",
        esc(std_short)
    );
    for r in &v.reasons {
        let _ = write!(h, "<li>{}</li>", esc(r));
    }
    h.push_str("</ul></div>");
}

/// The identification table: specimen, dates, machine, standard, laboratory.
fn identification(h: &mut String, report: &Report, std_short: &str) {
    let lab = &report.lab;
    let opt = |o: &Option<String>| o.as_deref().map_or("—".to_string(), esc);
    let standard_note = lab.edition.as_ref().map_or(String::new(), |e| format!(" ({})", esc(e)))
        + if report.options.response == crate::Response::Hardening { "; deflection-hardening response stated" } else { "" };
    let _ = write!(
        h,
        "<table class=\"id\"><tr><th>Specimen</th><td>{}</td><th>Operator</th><td>{}</td></tr>\
         <tr><th>Cast</th><td>{}</td><th>Tested</th><td>{}</td></tr>\
         <tr><th>Age</th><td>{}</td><th>Machine</th><td>{}</td></tr>\
         <tr><th>Standard</th><td>{}{}</td><th>Fracture</th><td>{}</td></tr>\
         <tr><th>Laboratory</th><td>{}</td><th>Load from</th><td>{}</td></tr></table>",
        opt(&lab.specimen),
        opt(&lab.operator),
        opt(&lab.cast_date),
        opt(&lab.test_date),
        lab.age_days().map_or("—".into(), |a| format!("{a} days")),
        opt(&lab.machine),
        esc(std_short),
        standard_note,
        opt(&lab.fracture),
        opt(&lab.laboratory),
        if report.curve.load_from_utm { "UTM samples (own rate)" } else { "feed (frame rate)" }
    );
}

/// The test's record: the operator's notes and the events (start, marks, zeros, crack,
/// stop) with their times from the start; marks and cracks are also drawn on the curve.
fn test_record(h: &mut String, report: &Report) {
    let Some(t) = &report.test else { return };
    h.push_str("<h2>Test record</h2>");
    if let Some(v) = &t.verification {
        let class = if v.stale.is_empty() { "" } else { " class=\"warn\"" };
        let _ = write!(h, "<p{class}><b>Verification:</b> {}</p>", esc(&v.describe()));
    }
    if let Some(n) = t.meta.notes.as_deref().filter(|n| !n.trim().is_empty()) {
        let _ = write!(h, "<p><b>Notes:</b> {}</p>", esc(n));
    }
    if t.events.is_empty() {
        return;
    }
    let t0 = t.events.iter().find(|e| e.kind == "start").map_or(t.events[0].t_ns, |e| e.t_ns);
    h.push_str(
        "<table class=\"events\"><tr><th>Event</th><th>Time (UTC)</th><th class=\"num\">From the start [s]</th>\
         <th class=\"num\">Load [kN]</th><th>By</th><th>Note</th></tr>",
    );
    for e in &t.events {
        let load = crate::event_loads::OnCurve::of(report).event_load(e).map_or(String::new(), |p| format!("{p:.3}"));
        let _ = write!(
            h,
            "<tr><td>{}</td><td>{}</td><td class=\"num\">{:.1}</td><td class=\"num\">{load}</td><td>{}</td><td>{}</td></tr>",
            esc(&e.kind),
            time_utc(e.t_ns),
            (e.t_ns - t0) as f64 * 1e-9,
            e.user.as_deref().map_or(String::new(), esc),
            e.note.as_deref().map_or(String::new(), esc)
        );
    }
    h.push_str("</table>");
}

/// The results table: every entry with its σ, or why it was not determined.
fn results(h: &mut String, report: &Report) {
    h.push_str("<h2>Results</h2><table><tr><th>Quantity</th><th>Symbol</th><th class=\"num\">Value</th><th class=\"num\">± σ</th><th>Unit</th><th>Key</th><th>Definition</th></tr>");
    for e in &report.entries {
        result_row(h, e, report.validity.valid);
    }
    let _ = write!(
        h,
        "</table><p class=\"sub\">Values rounded to two significant digits of their σ. σ: one standard uncertainty from the feed's σ of the {}, the time alignment of the UTM, the load's scatter and resolution, the sampling of peaks and the dimensions' tolerances (see Method). Loads: {}.</p>",
        esc(&report.x_axis),
        esc(&report.load_source)
    );
}

/// One row of the results table (informative when the test is not valid).
fn result_row(h: &mut String, e: &Entry, valid: bool) {
    match &e.result {
        Ok(q) => {
            let d = decimals(q);
            let q = &q.rounded();
            let _ = write!(
                h,
                "<tr{}><td>{}</td><td>{}</td><td class=\"num\">{:.d$}</td><td class=\"num\">{:.d$}</td><td>{}</td><td class=\"key\">{}</td><td class=\"clause\">{}</td></tr>",
                if valid { "" } else { " class=\"informative\"" },
                esc(e.name),
                esc(e.symbol),
                q.value,
                q.sigma,
                esc(&q.unit),
                e.key,
                esc(e.clause)
            );
        }
        Err(why) => {
            let _ = write!(
                h,
                "<tr class=\"undetermined\"><td>{}</td><td>{}</td><td colspan=\"3\">not determined: {}</td><td class=\"key\">{}</td><td class=\"clause\">{}</td></tr>",
                esc(e.name),
                esc(e.symbol),
                esc(why),
                e.key,
                esc(e.clause)
            );
        }
    }
}

/// The specimen's dimensions, then the report's notes.
fn specimen(h: &mut String, report: &Report) {
    let b = &report.beam;
    h.push_str("<h2>Specimen</h2><table><tr><th>Dimension</th><th>Symbol</th><th class=\"num\">Value</th><th>From</th></tr>");
    let src = |k: &str| report.dimension_sources.get(k).cloned().unwrap_or_else(|| "config".into());
    let mut row = |name: &str, sym: &str, v: f64, tol: Option<f64>, from: String| {
        let t = tol.map_or(String::new(), |t| format!(" ± {t}"));
        let _ = write!(h, "<tr><td>{name}</td><td>{sym}</td><td class=\"num\">{v}{t} mm</td><td>{}</td></tr>", esc(&from));
    };
    row("width", "b", b.width_mm, b.width_tol_mm, src("width_mm"));
    row("depth", if report.standard == Standard::En14651 { "h" } else { "d" }, b.depth_mm, b.depth_tol_mm, src("depth_mm"));
    row("span", if report.standard == Standard::En14651 { "l" } else { "L" }, b.span_mm, b.span_tol_mm, src("span_mm"));
    if let Some(n) = b.notch_mm {
        row("notch depth", "a₀", n, b.notch_tol_mm, src("notch_mm"));
        row("height above the notch tip", "h_sp", b.ligament_mm(), None, "depth − notch".into());
    }
    h.push_str("</table>");
    specimen_row(h, report);
    for n in &report.notes {
        let _ = write!(h, "<p class=\"note\">{}</p>", esc(n));
    }
}

/// The specimen's row of the lab's table (`test.json`'s `specimen_info`): mix, fibre and
/// dosage, client, project, and each dimension's readings whose mean the test measured —
/// those the test's method names in `report_fields` (every one without a method or a list).
fn specimen_row(h: &mut String, report: &Report) {
    let Some(i) = report.test.as_ref().and_then(|t| t.specimen_info.as_ref()) else { return };
    let shows = |field: &str| report.options.method.as_ref().map_or(true, |m| m.shows_field(field));
    let mut parts: Vec<String> = Vec::new();
    let named = [("mix", "Mix", &i.mix), ("fibre", "Fibre", &i.fibre), ("client", "Client", &i.client), ("project", "Project", &i.project)];
    for (field, name, v) in named {
        if let Some(v) = v.as_ref().filter(|_| shows(field)) {
            parts.push(format!("<b>{name}:</b> {}", esc(v)));
        }
    }
    if let Some(d) = i.dosage_kg_m3.filter(|_| shows("dosage_kg_m3")) {
        parts.push(format!("<b>Dosage:</b> {d} kg/m³"));
    }
    for (dim, r) in i.readings.iter().filter(|(_, r)| r.len() > 1 && shows("readings")) {
        let list: Vec<String> = r.iter().map(|v| v.to_string()).collect();
        parts.push(format!("<b>{}:</b> {} (their mean measured)", esc(dim), list.join(", ")));
    }
    if !parts.is_empty() {
        let _ = write!(h, "<p class=\"specimen-row\">{}</p>", parts.join("; "));
    }
}

/// The plots, inline SVG.
fn curves(h: &mut String, plots: &[Plot]) {
    h.push_str("<h2>Curves</h2>");
    for p in plots {
        let svg = p.svg.trim_start_matches(|c| c != '<');
        let svg = svg.strip_prefix("<?xml version=\"1.0\" encoding=\"UTF-8\"?>").unwrap_or(svg);
        let _ = write!(
            h,
            "<figure>{}<figcaption>{} (also <code>{}.png</code>, <code>{}.svg</code>)</figcaption></figure>",
            svg,
            esc(&p.title),
            p.name,
            p.name
        );
    }
}

/// The method: how the curve, its σ and the values are determined, then every entry's method.
fn method(h: &mut String, report: &Report) {
    h.push_str("<h2>Method</h2><ul>");
    method_curve(h, report);
    let _ = write!(h, "<li><b>Loads:</b> {}.</li>", esc(&report.load_source));
    for (phase, r, (lo, hi)) in &report.validity.rates {
        let _ = write!(h, "<li><b>Rate {}:</b> {:.3} mm/min (the window: {lo} to {hi} mm/min).</li>", esc(phase), r);
    }
    for u in &report.validity.unchecked {
        let _ = write!(h, "<li><b>Not checked:</b> {}</li>", esc(u));
    }
    h.push_str("</ul><table><tr><th>Key</th><th>How it is determined</th></tr>");
    for e in &report.entries {
        let _ = write!(h, "<tr><td class=\"key\">{}</td><td>{}</td></tr>", e.key, esc(&e.method));
    }
    h.push_str("</table><h3>Rules and their sources</h3><table class=\"rules\"><tr><th>Rule</th><th>Source</th></tr>");
    for (rule, source) in crate::method_statement::rules_in_force(report.options.method.as_ref(), report.standard) {
        let _ = write!(h, "<tr><td>{}</td><td>{}</td></tr>", esc(&rule), esc(&source));
    }
    h.push_str("</table>");
}

/// The method's items on the curve: its points, smoothing, load σ, interpolation, first peak.
fn method_curve(h: &mut String, report: &Report) {
    let c = &report.curve;
    let _ = write!(
        h,
        "<li><b>Curve:</b> load against {}, {} points in time order. {}: {}.</li>",
        esc(&report.x_name),
        c.len(),
        esc(&report.x_axis),
        esc(&report.x_source)
    );
    let _ = write!(
        h,
        "<li><b>Smoothing:</b> the {} is smoothed over time by a moving local-linear least-squares fit of up to {} points (a straight ramp passes unchanged); the window shrinks where the wider fit's bias shows, at a kink such as the start of loading ({} points here); its σ is propagated through the fit's weights, the σ of the zero reference ({:.4} mm) added in full. The load is not smoothed.</li>",
        esc(&report.x_axis),
        c.smooth_points,
        c.smooth_reduced,
        c.x_ref_sigma
    );
    let _ = write!(
        h,
        "<li><b>Load σ:</b> {:.4} kN per reading = √(scatter² + resolution²/12), scatter {:.4} kN (robust: 1.4826·MAD of each point's deviation from the line through its neighbours), resolution {} kN.</li>",
        c.load_sigma, c.load_noise, report.options.load_resolution_kn.unwrap_or(0.0)
    );
    h.push_str("<li><b>Values at a deflection/CMOD:</b> the first point where the smoothed curve reaches it, loads interpolated linearly between the two bracketing points; σ² = s²·((1−f)²σ²(x̃ᵢ₋₁) + f²σ²(x̃ᵢ)) + ((1−f)² + f²)·σ_load², f the fraction between them, s the slope there (their secant when they are more than 3σ apart, else the local least-squares slope over the smoothing window).</li>");
    if report.standard != Standard::En14651 {
        h.push_str("<li><b>First peak:</b> C1609 defines it as the first point where the slope of the curve is zero. Here: the first local maximum of the load (smoothed like the deflection) above 10 % of the maximum load after which the smoothed load falls by max(3·σ_load, 0.5 % of the maximum load) before exceeding it; P1 is the largest measured load within the smoothing window there. A flat stretch without such a fall is not taken as the first peak.</li>");
    }
}

/// The quality control section: warnings, the checks, then the tables of outages, cameras,
/// drift and coverage.
fn quality_control(h: &mut String, report: &Report) {
    let qc = &report.qc;
    h.push_str("<h2>Quality control</h2>");
    if qc.warnings.is_empty() {
        h.push_str("<p>No warnings.</p>");
    } else {
        h.push_str("<ul>");
        for w in &qc.warnings {
            let _ = write!(h, "<li class=\"warn\">{}</li>", esc(w));
        }
        h.push_str("</ul>");
    }
    qc_checks(h, report);
    utm_outages(h, qc);
    cameras(h, qc);
    drift_and_stale(h, qc);
    tag_coverage(h, qc);
}

/// The table of the QC's checks.
fn qc_checks(h: &mut String, report: &Report) {
    let qc = &report.qc;
    h.push_str("<table><tr><th>Check</th><th class=\"num\">Value</th></tr>");
    let mut kv = |k: &str, v: String| {
        let _ = write!(h, "<tr><td>{}</td><td class=\"num\">{}</td></tr>", esc(k), esc(&v));
    };
    kv("feed lines", qc.lines.to_string());
    kv("curve points (load and deflection/CMOD)", qc.curve_points.to_string());
    kv("frame sets without a line (gaps in seq)", qc.frame_sets_without_line.to_string());
    kv("gaps in time between lines", qc.time_gaps.len().to_string());
    kv("lines without load", qc.lines_without_load.to_string());
    kv(&format!("lines with load but without {}", report.x_axis), qc.lines_with_load_without_x.to_string());
    kv("frame sets dropped (live pipeline)", qc.dropped_sets.map_or("not reported".into(), |d| d.to_string()));
    kv("lines with the UTM down", qc.utm_down_lines.to_string());
    kv("UTM outages", qc.utm_outages.len().to_string());
    kv(&format!("{} scatter (robust)", report.x_axis), format!("{:.4} mm", qc.x_scatter_mm));
    kv(&format!("{} σ from the feed (median)", report.x_axis), format!("{:.4} mm", qc.x_feed_sigma_median_mm));
    kv("load scatter (robust)", format!("{:.4} kN", qc.load_noise_kn));
    kv("clock offset (as the feed reports it)", qc.clock_offset.as_ref().map_or("not in the feed".into(), clock_text));
    h.push_str("</table>");
}

/// The UTM's outages, when there were any.
fn utm_outages(h: &mut String, qc: &Qc) {
    if qc.utm_outages.is_empty() {
        return;
    }
    h.push_str("<h3>UTM outages</h3><table><tr><th>from</th><th>to</th><th class=\"num\">duration</th></tr>");
    for o in &qc.utm_outages {
        let _ = write!(
            h,
            "<tr><td>{}</td><td>{}</td><td class=\"num\">{:.2} s</td></tr>",
            time_utc(o.from_t_ns),
            time_utc(o.to_t_ns),
            o.duration_s
        );
    }
    h.push_str("</table>");
}

/// The cameras' bumps and missing frames and poses, when the feed names cameras.
fn cameras(h: &mut String, qc: &Qc) {
    if qc.cameras.is_empty() {
        return;
    }
    h.push_str("<h3>Cameras</h3><table><tr><th>camera</th><th class=\"num\">bumps</th><th class=\"num\">lines without frame</th><th class=\"num\">lines without pose</th></tr>");
    for c in &qc.cameras {
        let _ = write!(
            h,
            "<tr><td>{}</td><td class=\"num\">{}</td><td class=\"num\">{}</td><td class=\"num\">{}</td></tr>",
            esc(&c.camera),
            c.bumps,
            c.lines_without_frame,
            c.lines_unposed
        );
    }
    h.push_str("</table>");
}

/// The drift and stale-pose fields, when the feed has any.
fn drift_and_stale(h: &mut String, qc: &Qc) {
    if qc.drift_and_stale.is_empty() {
        return;
    }
    h.push_str("<h3>Drift and stale poses</h3><table><tr><th>field</th><th class=\"num\">lines</th><th class=\"num\">largest</th></tr>");
    for f in &qc.drift_and_stale {
        let _ = write!(
            h,
            "<tr><td>{}</td><td class=\"num\">{}</td><td class=\"num\">{}</td></tr>",
            esc(&f.field),
            f.lines,
            f.max_abs.map_or(String::new(), |m| format!("{m:.4}"))
        );
    }
    h.push_str("</table>");
}

/// Coverage per tag.
fn tag_coverage(h: &mut String, qc: &Qc) {
    h.push_str("<h3>Coverage per tag</h3><table><tr><th>tag</th><th>role</th><th class=\"num\">lines</th><th class=\"num\">coverage</th><th class=\"num\">mean views</th><th class=\"num\">median σ (up)</th></tr>");
    for t in &qc.tags {
        let _ = write!(
            h,
            "<tr><td>{}</td><td>{}</td><td class=\"num\">{}</td><td class=\"num\">{:.1} %</td><td class=\"num\">{:.2}</td><td class=\"num\">{}</td></tr>",
            t.id,
            t.role.unwrap_or(""),
            t.lines,
            t.coverage_pct,
            t.mean_views,
            t.median_sigma_up_mm.map_or(String::new(), |s| format!("{s:.4} mm"))
        );
    }
    h.push_str("</table>");
}

/// The inputs with their SHA-256.
fn inputs_table(h: &mut String, inputs: &[InputHash]) {
    h.push_str("<h2>Inputs</h2><table><tr><th>role</th><th>file</th><th>SHA-256</th></tr>");
    for i in inputs {
        let _ = write!(
            h,
            "<tr><td>{}</td><td><code>{}</code></td><td class=\"key\">{}</td></tr>",
            esc(&i.role),
            esc(&i.path.display().to_string()),
            i.sha256
        );
    }
    h.push_str("</table>");
}

/// The footer: the files beside the page, the version and the time of writing.
fn footer(h: &mut String) {
    let _ = write!(
        h,
        "<footer>Files beside this page: <code>report.json</code> (every value with σ and unit), <code>curve.csv</code> (the feed as a table), the plots as PNG and SVG. Generated by tagdeflect {} on {}.</footer></body></html>",
        env!("CARGO_PKG_VERSION"),
        chrono::Utc::now().format("%Y-%m-%d %H:%M UTC")
    );
}
