//! The report's "Control output" section (docs/control.md "A test under control"): a test
//! run with `[output.analog]` carries `control.json` in its folder (written at its stop), and
//! the report prints it — the signal and its scaling, the share of frame sets with the valid
//! line high, the longest invalid stretch and why, the exposure → write latency measured live,
//! and the temporal estimate's gain and phase lag at 0.1, 0.5 and 2 Hz and step response
//! (computed at the stop with the run's `[measure]` at the test's frame rate), with the
//! pipeline's lag at the measured median latency added. A test without control outputs has
//! no `control.json` and no section.

use std::fmt::Write;
use std::path::Path;

use tagdeflect_core::control_summary::{ControlSummary, Dynamics, OutputSummary, CONTROL_FILE};

use crate::html::{esc, time_utc};
use crate::report::Report;

/// `dir/control.json`: `None` when absent, `Err` naming the file when it cannot be read.
pub(crate) fn read(dir: &Path) -> Option<Result<ControlSummary, String>> {
    let path = dir.join(CONTROL_FILE);
    let text = match std::fs::read_to_string(&path) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return None,
        Err(e) => return Some(Err(format!("{}: {e}", path.display()))),
        Ok(t) => t,
    };
    Some(serde_json::from_str(&text).map_err(|e| format!("{}: {e}", path.display())))
}

/// `report.json`'s `control`: the file's figures with each output's valid share, or the
/// reason it could not be read.
pub(crate) fn json(report: &Report) -> Option<serde_json::Value> {
    Some(match report.control.as_ref()? {
        Err(why) => serde_json::json!({ "error": why }),
        Ok(c) => {
            let mut v = serde_json::to_value(c).expect("control summary serialises");
            for (o, out) in c.outputs.iter().zip(v["outputs"].as_array_mut().into_iter().flatten()) {
                out["valid_share"] = serde_json::json!(o.valid_share());
            }
            v
        }
    })
}

/// The section (nothing without `control.json`).
pub(crate) fn html(h: &mut String, report: &Report) {
    let Some(control) = &report.control else { return };
    h.push_str("<h2>Control output</h2>");
    let c = match control {
        Ok(c) => c,
        Err(why) => {
            let _ = write!(h, "<p class=\"warn\">The test ran under control, but its figures cannot be read: {}</p>", esc(why));
            return;
        }
    };
    for o in &c.outputs {
        output(h, o);
    }
    // The pipeline's lag: the analog output's latency when there is one (it includes the
    // device's round trip), else the registers'.
    let analog = c.outputs.iter().filter(|o| o.kind == "analog");
    let p50 = analog.chain(c.outputs.iter()).find_map(|o| o.latency.as_ref()).map(|l| l.p50_ms);
    if let Some(d) = &c.dynamics {
        dynamics(h, d, p50);
    }
}

fn row(h: &mut String, what: &str, value: &str) {
    let _ = write!(h, "<tr><td>{}</td><td>{}</td></tr>", esc(what), esc(value));
}

/// One output's table.
fn output(h: &mut String, o: &OutputSummary) {
    let kind = if o.kind == "analog" { "Analog output ([output.analog])" } else { "Control registers ([output.control])" };
    let _ = write!(h, "<h3>{}</h3><table class=\"control\">", esc(kind));
    row(h, "Signal", &format!("{} → {}", o.gauge, o.target));
    if let Some(s) = &o.scaling {
        let safe = s.safe_v.map_or("holds its last value".to_string(), |v| format!("goes to {v:.3} V"));
        let scaling = format!(
            "{:.4} V/mm from {:.3} V, clamped to {:.2}–{:.2} V; while invalid and at stop the output {safe}",
            s.volts_per_mm, s.offset_v, s.range_v[0], s.range_v[1]
        );
        row(h, "Scaling", &scaling);
    }
    row(h, "Valid while", &format!("σ ≤ {} mm and fresh (stale after {} frame set(s) without the value)", o.max_sigma_mm, o.stale_sets));
    let share = o.valid_share().map_or("–".into(), |s| format!("{:.1} %", s * 100.0));
    row(h, "Valid line high", &format!("{share} of the test's frame sets ({} of {})", o.valid_sets, o.frame_sets));
    let longest = o.longest_invalid.as_ref().map_or("none".into(), |l| {
        format!("{:.0} ms ({} frame set(s)) from {}: {}", l.duration_ms, l.frame_sets, time_utc(l.from_t_ns), l.cause)
    });
    row(h, "Invalid stretches", &format!("{}; the longest {longest}", o.invalid_stretches));
    let latency = o.latency.as_ref().map_or("no value written".into(), |l| {
        format!("p50 {:.1} ms, p99 {:.1} ms, max {:.1} ms over {} values", l.p50_ms, l.p99_ms, l.max_ms, l.values)
    });
    let what = if o.kind == "analog" { "Exposure → write acknowledged (live)" } else { "Exposure → register (live)" };
    row(h, what, &latency);
    if o.kind == "analog" {
        row(h, "Values written / superseded / device outages", &format!("{} / {} / {}", o.values_written, o.superseded, o.outages));
    }
    h.push_str("</table>");
}

/// The estimate's dynamics, with the pipeline's lag at the median latency added.
fn dynamics(h: &mut String, d: &Dynamics, p50_ms: Option<f64>) {
    h.push_str("<h3>Dynamics of the signal</h3><table class=\"control\"><tr><th class=\"num\">Frequency [Hz]</th><th class=\"num\">Gain</th><th class=\"num\">Phase lag of the estimate [°]</th><th class=\"num\">With the pipeline's latency [°]</th></tr>");
    for s in &d.sines {
        let total = p50_ms.map_or("–".into(), |l| format!("{:.1}", s.phase_lag_deg + 360.0 * s.freq_hz * l * 1e-3));
        let _ = write!(
            h,
            "<tr><td class=\"num\">{}</td><td class=\"num\">{:.3}</td><td class=\"num\">{:.1}</td><td class=\"num\">{total}</td></tr>",
            s.freq_hz, s.gain, s.phase_lag_deg
        );
    }
    let st = &d.step;
    let _ = write!(
        h,
        "</table><p>Step of {:.0} µm: 10 % after {:.0} ms, 90 % after {:.0} ms, overshoot {:.1} %.</p><p class=\"sub\">{}; the pipeline's lag is 360° × f × the median exposure → write latency above.</p>",
        st.step_mm * 1e3,
        st.to_10_percent_ms,
        st.to_90_percent_ms,
        st.overshoot_percent,
        esc(&d.how)
    );
}
