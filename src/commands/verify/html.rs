//! `verification.html`: the certificate as a page to read and print (A4).

use std::fmt::Write;

use tagdeflect_verify::stability::Stability;

use super::Certificate;

/// Text made safe for HTML.
fn esc(s: &str) -> String {
    s.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;").replace('"', "&quot;")
}

/// mm as µm with two decimals, or a dash.
fn um(v: Option<f64>) -> String {
    v.map_or_else(|| "—".into(), |v| format!("{:.2}", v * 1e3))
}

const STYLE: &str = "body{font-family:sans-serif;max-width:48em;margin:2em auto;font-size:11pt}\
table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #999;padding:2px 6px;text-align:right}\
th:first-child,td:first-child{text-align:left}\
table.files{width:100%;table-layout:fixed}table.files td{text-align:left;word-break:break-all}table.files col.sha{width:58%}\
table.files code{font-size:8.5pt}.pass{color:#060}.fail{color:#a00}@page{size:A4;margin:15mm}";

/// The page of `c`.
pub fn page(c: &Certificate) -> String {
    let v = &c.verification;
    let mut h = String::new();
    let _ = write!(
        h,
        "<!DOCTYPE html><html><head><meta charset=\"utf-8\"><title>Verification {}</title><style>{STYLE}</style></head><body>",
        esc(&c.issued_utc)
    );
    let _ = write!(h, "<h1>Verification of a tagdeflect rig</h1>");
    let verdict = match &v.iso9513.class {
        Some(class) => format!(
            "<p class=\"pass\"><b>ISO 9513 class {}</b>; expanded uncertainty U (k = 2) = <b>{:.2} µm</b> over {:.3}–{:.3} mm</p>",
            esc(class),
            v.uncertainty.expanded_mm * 1e3,
            v.uncertainty.range_mm[0],
            v.uncertainty.range_mm[1]
        ),
        None => "<p class=\"fail\"><b>No ISO 9513 class reached</b></p>".into(),
    };
    h.push_str(&verdict);
    let _ =
        write!(h, "<p>Verified quantity: <b>{}</b>; known displacements from <code>{}</code>.</p>", esc(&c.quantity), esc(&c.reference));
    h.push_str("<ul>");
    for r in &v.verdict.reasons {
        let _ = write!(h, "<li>{}</li>", esc(r));
    }
    h.push_str("</ul>");
    who(&mut h, c);
    procedure(&mut h);
    inputs(&mut h, c);
    rig(&mut h, c);
    stability(&mut h, c);
    steps(&mut h, c);
    classes(&mut h, c);
    budget(&mut h, c);
    h.push_str("</body></html>\n");
    h
}

fn who(h: &mut String, c: &Certificate) {
    let e = &c.equipment;
    let opt = |v: &Option<String>| v.as_deref().map_or_else(|| "(not given)".into(), esc);
    let _ = write!(
        h,
        "<h2>Who and with what</h2><table><tr><td>issued</td><td>{}</td></tr><tr><td>operator</td><td>{}</td></tr>\
         <tr><td>reference equipment</td><td>{}</td></tr><tr><td>its calibration</td><td>{}</td></tr>\
         <tr><td>its uncertainty U (k = 2)</td><td>{:.2} µm</td></tr><tr><td>recording</td><td>{} ({} frame sets)</td></tr>\
         <tr><td>tagdeflect</td><td>{}</td></tr></table>",
        esc(&c.issued_utc),
        opt(&c.operator),
        opt(&e.description),
        opt(&e.calibrated),
        e.reference_u_um,
        esc(&c.recording),
        c.frame_sets,
        c.version
    );
}

fn inputs(h: &mut String, c: &Certificate) {
    h.push_str("<h2>Inputs</h2><table class=\"files\"><col><col class=\"sha\"><tr><th>file</th><th>SHA-256</th></tr>");
    for (path, sha) in &c.inputs {
        let _ = write!(h, "<tr><td>{}</td><td><code>{}</code></td></tr>", esc(path), esc(sha));
    }
    h.push_str("</table>");
}

fn procedure(h: &mut String) {
    h.push_str(
        "<h2>Procedure</h2><p>A target carrying the tags was held at rest, then moved to known displacements \
         by the reference equipment and held at each. The recording was replayed by tagdeflect; the first hold gives the \
         noise, drift and Allan deviation at rest; each hold's mean of the verified quantity (after its first 30 % of \
         readings) is compared with the reference. The class follows ISO 9513's table; the figures of VDI/VDE 2626 (ZS, ZD, D) and the \
         expanded uncertainty (GUM, k = 2) follow docs/verification.md.</p>",
    );
}

fn rig(h: &mut String, c: &Certificate) {
    h.push_str(
        "<h2>Rig</h2><table><tr><th>camera</th><th>size</th><th>fx, fy (px)</th><th>cx, cy (px)</th><th>centre in the world (mm)</th></tr>",
    );
    for cam in &c.rig.cameras {
        let centre =
            c.rig.camera_poses.iter().find(|p| p.camera == cam.name).map_or_else(
                || "not posed".to_string(),
                |p| format!("{:.1}, {:.1}, {:.1}", p.centre_mm[0], p.centre_mm[1], p.centre_mm[2]),
            );
        let _ = write!(
            h,
            "<tr><td>{}</td><td>{}×{}</td><td>{:.1}, {:.1}</td><td>{:.1}, {:.1}</td><td>{centre}</td></tr>",
            esc(&cam.name),
            cam.width,
            cam.height,
            cam.fx,
            cam.fy,
            cam.cx,
            cam.cy
        );
    }
    h.push_str("</table><table class=\"files\"><col><col class=\"sha\"><tr><th>file</th><th>SHA-256</th></tr>");
    for f in c.rig.config.iter().chain(&c.rig.calibration_files) {
        let _ = write!(h, "<tr><td>{}</td><td><code>{}</code></td></tr>", esc(&f.path), &f.sha256);
    }
    let tags: Vec<String> =
        c.rig.tags.iter().map(|t| format!("{}{}", t.id, t.role.map(|r| format!(" ({r:?})").to_lowercase()).unwrap_or_default())).collect();
    let _ = write!(h, "</table><p>Tags: {}.</p>", esc(&tags.join(", ")));
}

fn stability_row(h: &mut String, name: &str, s: &Stability) {
    let allan: Vec<String> =
        s.allan.iter().map(|a| a.adev_mm.map_or_else(|| "not enough data".into(), |v| format!("{:.3}", v * 1e3))).collect();
    let _ = write!(
        h,
        "<tr><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td></tr>",
        esc(name),
        um(s.sd_mm),
        s.drift_mm_per_h.map_or_else(|| "not enough data".into(), |d| format!("{:.3}", d * 1e3)),
        allan.join("</td><td>"),
        s.samples
    );
}

fn stability(h: &mut String, c: &Certificate) {
    let st = &c.verification.static_figures;
    h.push_str("<h2>At rest</h2><table><tr><th>reading</th><th>SD (µm)</th><th>drift (µm/h)</th><th>Allan 1 s (µm)</th><th>10 s</th><th>100 s</th><th>readings</th></tr>");
    stability_row(h, "verified quantity", &st.quantity);
    stability_row(h, "mean displacement", &st.displacement);
    if let Some(n) = &st.net_deflection {
        stability_row(h, "net deflection", n);
    }
    for (id, s) in &st.tags {
        stability_row(h, &format!("tag {id}"), s);
    }
    vdi(h, c);
}

/// VDI/VDE 2626's table; ZS only where the verified quantity is a rigid target's displacement.
fn vdi(h: &mut String, c: &Certificate) {
    let d = &c.verification.vdi2626;
    h.push_str("</table><h2>VDI/VDE 2626</h2><table>");
    if d.zs_applies {
        let _ = write!(
            h,
            "<tr><td>ZS: net deflection of the rigid target, largest hold mean</td><td>{} µm</td></tr>\
             <tr><td>ZS: SD of the net deflection at rest</td><td>{} µm</td></tr>",
            um(d.zs_net_deflection_mm),
            um(d.zs_net_deflection_sd_mm)
        );
    } else {
        let _ = write!(
            h,
            "<tr><td>ZS: not applicable — the verified quantity ({}) is the target's own deformation (a staged target)</td><td>—</td></tr>",
            esc(&c.quantity)
        );
    }
    let _ = write!(
        h,
        "<tr><td>ZD: SD of the displacement at rest</td><td>{} µm</td></tr>\
         <tr><td>ZD: largest deviation at rest</td><td>{} µm</td></tr><tr><td>D: largest step error</td><td>{} µm</td></tr>\
         <tr><td>D: scale error</td><td>{:.4} %</td></tr></table>",
        um(d.zd_sd_mm),
        um(d.zd_max_mm),
        um(Some(d.d_max_error_mm)),
        d.d_scale_error_pct.unwrap_or(f64::NAN)
    );
}

fn steps(h: &mut String, c: &Certificate) {
    let v = &c.verification;
    h.push_str("<h2>Known displacements</h2><table><tr><th>step</th><th>position (mm)</th><th>approach</th><th>readings</th><th>measured (mm)</th><th>error (µm)</th><th>SD (µm)</th><th>net defl. (µm)</th></tr>");
    for s in &v.steps {
        let _ = write!(
            h,
            "<tr><td>{}</td><td>{:.4}</td><td>{:?}</td><td>{}</td><td>{:.5}</td><td>{:.2}</td><td>{}</td><td>{}</td></tr>",
            s.step,
            s.position_mm,
            s.approach,
            s.lines,
            s.measured_mm,
            s.error_mm * 1e3,
            um(s.sd_mm),
            um(s.net_deflection_mm)
        );
    }
    let k = &v.known;
    let _ = write!(
        h,
        "</table><table><tr><td>bias (mean error)</td><td>{} µm</td></tr><tr><td>linearity (largest deviation from the best line)</td><td>{} µm</td></tr>\
         <tr><td>repeatability (largest SD over repeats)</td><td>{} µm</td></tr><tr><td>hysteresis (increasing − decreasing)</td><td>{} µm</td></tr></table>",
        um(Some(k.bias_mm)),
        um(k.linearity_mm),
        um(k.repeatability_mm),
        um(k.hysteresis_mm)
    );
}

fn classes(h: &mut String, c: &Certificate) {
    let r = &c.verification.iso9513;
    let _ = write!(
        h,
        "<h2>ISO 9513</h2><p>Resolution (2 × SD at rest): {:.3} µm. Table source: {}.</p>",
        r.resolution_mm * 1e3,
        esc(&r.table_source)
    );
    h.push_str("<table><tr><th>class</th><th>bias</th><th>worst step (share of its limit)</th><th>resolution</th></tr>");
    for k in &r.checks {
        let ok = |b: bool| if b { "<span class=\"pass\">within</span>" } else { "<span class=\"fail\">beyond</span>" };
        let _ = write!(
            h,
            "<tr><td>{}</td><td>{}</td><td>step {} ({:.0} %)</td><td>{}</td></tr>",
            k.class,
            ok(k.bias_ok),
            k.worst_bias_step,
            k.worst_bias_ratio * 100.0,
            ok(k.resolution_ok)
        );
    }
    h.push_str("</table>");
}

fn budget(h: &mut String, c: &Certificate) {
    let u = &c.verification.uncertainty;
    h.push_str("<h2>Uncertainty budget</h2><table><tr><th>component</th><th>u (µm)</th></tr>");
    for comp in &u.components {
        let _ = write!(h, "<tr><td>{}</td><td>{:.3}</td></tr>", esc(&comp.name), comp.u_mm * 1e3);
    }
    let _ = write!(
        h,
        "<tr><td>combined</td><td>{:.3}</td></tr><tr><td><b>U (k = 2)</b></td><td><b>{:.2}</b></td></tr></table>",
        u.combined_mm * 1e3,
        u.expanded_mm * 1e3
    );
}
