//! EN 14651 quantities from a load–CMOD curve (notched beam, three-point loading).
//!
//! Stress from a load: `f = 3·F·l/(2·b·h_sp²)` with `h_sp` the height above the notch tip;
//! with `F` in kN and lengths in mm, `f = 1500·F·l/(b·h_sp²)` MPa.
//! Limit of proportionality `F_L`: the largest load in the CMOD interval 0 to 0.05 mm.
//! Residual loads `F_R,j` at CMOD_j = 0.5, 1.5, 2.5, 3.5 mm.

use crate::config::BeamConfig;
use crate::curve::Curve;
pub(crate) use crate::lop::{limit_of_proportionality, LopError};
use crate::quantity::Quantity;
use crate::report::Entry;

/// Upper end of the CMOD interval of the limit of proportionality, mm.
pub(crate) const LOP_CMOD_MM: f64 = 0.05;
/// CMOD of the residual strengths fR1..fR4, mm.
pub(crate) const CMOD_J_MM: [f64; 4] = [0.5, 1.5, 2.5, 3.5];

/// The EN 14651 quantities: F_L, f_L, fR1..fR4.
pub fn compute(curve: &Curve, beam: &BeamConfig) -> Vec<Entry> {
    let (b, l, h) = (beam.width_mm, beam.span_mm, beam.ligament_mm());
    let (ub, ud, ul, un) = beam.sigmas_mm();
    let stress = |f: f64| 1500.0 * f * l / (b * h * h);
    // Relative variance of l/(b·h_sp²), h_sp = depth − notch.
    let geo_rel2 = (ul / l).powi(2) + (ub / b).powi(2) + 4.0 * (ud * ud + un * un) / (h * h);
    let f_of = |p: f64, s: f64| {
        let f = stress(p);
        Quantity::new(f, (stress(s).powi(2) + f * f * geo_rel2).sqrt(), "MPa")
    };
    let mut out = Vec::new();
    let fl = limit_of_proportionality(curve, LOP_CMOD_MM)
        .map(|l| Quantity::new(l.load_kn, l.sigma_kn, "kN"))
        .map_err(|e| e.message().to_string());
    out.push(Entry {
        key: "FL",
        symbol: "F_L",
        name: "load at the limit of proportionality",
        result: fl.clone(),
        method: "largest load up to the time the CMOD passes 0.05 mm (the load interpolated there included); that time from the \
                 CMOD's readings where they are within 2σ of 0.05 mm (between two neighbours, or a line fitted over time across \
                 more), with its σ; σ of F_L = half the change of that largest load over ±1σ of the time, with the σ of one load \
                 reading and of the sampling of a peak (r/√3); undetermined when the gauge cannot tell where the CMOD passes \
                 0.05 mm (docs/report.md, \"F_L where the gauge can tell it\")"
            .into(),
        clause: "EN 14651 §9.1 (limit of proportionality, F_L)",
    });
    out.push(Entry {
        key: "fL",
        symbol: "f_ct,L^f",
        name: "limit of proportionality",
        result: fl.map(|q| f_of(q.value, q.sigma)),
        method: "f = 3·F_L·l/(2·b·h_sp²); σ from the load's σ and the dimensions' tolerances (uniform: σ = tol/√3)".into(),
        clause: "EN 14651 §9.1, Eq. 1",
    });
    const KEYS: [&str; 4] = ["fR1", "fR2", "fR3", "fR4"];
    const SYMS: [&str; 4] = ["f_R,1", "f_R,2", "f_R,3", "f_R,4"];
    const NAMES: [&str; 4] = [
        "residual flexural tensile strength at CMOD 0.5 mm",
        "residual flexural tensile strength at CMOD 1.5 mm",
        "residual flexural tensile strength at CMOD 2.5 mm",
        "residual flexural tensile strength at CMOD 3.5 mm",
    ];
    for (j, &cmod) in CMOD_J_MM.iter().enumerate() {
        let r = curve.load_at(cmod).map(|(p, s, _)| f_of(p, s)).ok_or_else(|| curve.not_reached(&format!("CMOD {cmod} mm"), cmod));
        out.push(Entry {
            key: KEYS[j],
            symbol: SYMS[j],
            name: NAMES[j],
            result: r,
            method: format!(
                "F_R,{} = load where the smoothed CMOD first reaches {cmod} mm, interpolated; f = 3·F·l/(2·b·h_sp²); σ of F from the σ of the two bracketing CMODs through the slope there, and the load σ",
                j + 1
            ),
            clause: "EN 14651 §9.2, Eq. 2 (residual flexural tensile strength)",
        });
    }
    out
}
