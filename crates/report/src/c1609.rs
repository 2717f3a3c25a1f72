//! ASTM C1609/C1609M quantities from a load–net-deflection curve (third-point loading).
//!
//! Stress from a load: `f = P·L/(b·d²)` (the modulus-of-rupture formula of C1609's
//! calculation section); with `P` in kN and lengths in mm, `f = 1000·P·L/(b·d²)` MPa.
//!
//! *First peak* (C1609: the first point on the curve where the slope is zero). On a
//! measured, noisy curve a zero of the raw slope means nothing, so: the load is smoothed
//! over time like the deflection; the first peak is the first local maximum of the smoothed
//! load above `floor = 10 %` of the maximum load after which the smoothed load falls by
//! `drop = max(3·σ_load, 0.5 % of the maximum load)` before it exceeds that maximum; P1 is
//! the largest measured load within the smoothing window there. A flat stretch that is
//! followed by a rise without such a fall is not taken as a first peak (the first peak is
//! then found later, at worst at the peak load).

use crate::config::BeamConfig;
use crate::curve::Curve;
use crate::quantity::Quantity;
use crate::report::Entry;

/// Fraction of the maximum load below which maxima are not first peaks (seating, noise).
const FIRST_PEAK_FLOOR: f64 = 0.10;
/// Least fall after a maximum, as a fraction of the maximum load.
const FIRST_PEAK_MIN_DROP: f64 = 0.005;

/// The first peak's index in the curve (see the module documentation), or `None`.
pub(crate) fn first_peak(curve: &Curve) -> Option<usize> {
    let pmax = curve.load.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
    let drop = (3.0 * curve.load_sigma).max(FIRST_PEAK_MIN_DROP * pmax.abs());
    curve.first_peak(drop, FIRST_PEAK_FLOOR * pmax)
}

/// The C1609 quantities: P1, δ1, f1, Pp, δp, fp, P600, P150, f600, f150, T150, R_T,150.
pub fn compute(curve: &Curve, beam: &BeamConfig) -> Vec<Entry> {
    let (b, d, l) = (beam.width_mm, beam.depth_mm, beam.span_mm);
    let (ub, ud, ul, _) = beam.sigmas_mm();
    let stress = |p: f64| 1000.0 * p * l / (b * d * d);
    // Relative variance of L/(b·d²) from the dimensions' tolerances.
    let geo_rel2 = (ul / l).powi(2) + (ub / b).powi(2) + (2.0 * ud / d).powi(2);
    let f_of = |q: &Result<Quantity, String>| -> Result<Quantity, String> {
        q.as_ref()
            .map(|q| {
                let f = stress(q.value);
                Quantity::new(f, (stress(q.sigma).powi(2) + f * f * geo_rel2).sqrt(), "MPa")
            })
            .map_err(|e| e.clone())
    };
    let mut out = Vec::new();
    let stress_method = "f = P·L/(b·d²); σ from the load's σ and the dimensions' tolerances (uniform: σ = tol/√3), \
                         (σ_f/f)² = (σ_P/P)² + (σ_L/L)² + (σ_b/b)² + (2σ_d/d)²";
    let peak_sigma = |j: usize| (curve.load_sigma.powi(2) + curve.peak_sampling_sigma(j).powi(2)).sqrt();

    // First peak.
    let fp_idx = first_peak(curve);
    let no_peak = "the load never fell after a maximum by the drop threshold: no first peak on this curve".to_string();
    let p1 = fp_idx.map(|j| Quantity::new(curve.load[j], peak_sigma(j), "kN")).ok_or(no_peak.clone());
    let d1 = fp_idx.map(|j| Quantity::new(curve.xs[j], curve.sxs[j], "mm")).ok_or(no_peak);
    let f1 = f_of(&p1);
    out.push(Entry {
        key: "P1",
        symbol: "P₁",
        name: "first-peak load",
        result: p1.clone(),
        method: "first local maximum of the smoothed load that is followed by a fall of max(3·σ_load, 0.5 % of the maximum load) \
                 before being exceeded, among maxima above 10 % of the maximum load; the largest measured load within the \
                 smoothing window there. σ² = σ² of one load reading + (r/√3)², r the rise over one load sampling period \
                 into the peak (the true peak lies between that sample and the next)"
            .into(),
        clause: "C1609 §3 Terminology (first-peak load: first point where the slope is zero)",
    });
    out.push(Entry {
        key: "delta1",
        symbol: "δ₁",
        name: "first-peak deflection",
        result: d1,
        method: "net deflection (smoothed) at the first-peak point; σ propagated from the feed".into(),
        clause: "C1609 §3 Terminology (first-peak deflection)",
    });
    out.push(Entry {
        key: "f1",
        symbol: "f₁",
        name: "first-peak strength",
        result: f1.clone(),
        method: stress_method.into(),
        clause: "C1609 §3 Terminology (first-peak strength); §9 Calculation, Eq. 1",
    });

    // Peak.
    let k = curve.peak_index();
    let pp = Ok(Quantity::new(curve.load[k], peak_sigma(k), "kN"));
    out.push(Entry {
        key: "Pp",
        symbol: "P_P",
        name: "peak load",
        result: pp.clone(),
        method: "largest measured load of the test; σ as P1's (one reading and the sampling of the peak)".into(),
        clause: "C1609 §3 Terminology (peak load)",
    });
    out.push(Entry {
        key: "deltap",
        symbol: "δ_P",
        name: "net deflection at peak load",
        result: Ok(Quantity::new(curve.xs[k], curve.sxs[k], "mm")),
        method: "net deflection (smoothed) at the peak load".into(),
        clause: "C1609 §3 Terminology (peak deflection)",
    });
    out.push(Entry {
        key: "fp",
        symbol: "f_P",
        name: "peak strength",
        result: f_of(&pp),
        method: stress_method.into(),
        clause: "C1609 §3 Terminology (peak strength); §9 Calculation, Eq. 1",
    });

    // Residual loads.
    let residual = |div: f64| -> Result<Quantity, String> {
        let target = l / div;
        curve
            .load_at(target)
            .map(|(p, s, _)| Quantity::new(p, s, "kN"))
            .ok_or_else(|| curve.not_reached(&format!("L/{div} = {target:.3} mm"), target))
    };
    let p600 = residual(600.0);
    let p150 = residual(150.0);
    let residual_method = |div: &str| {
        format!(
            "load where the smoothed net deflection first reaches {div}, interpolated linearly; σ from the σ of the two bracketing deflections through the slope there, and the load σ"
        )
    };
    out.push(Entry {
        key: "P600",
        symbol: "P_600",
        name: "residual load at L/600",
        result: p600.clone(),
        method: residual_method("L/600"),
        clause: "C1609 §3 Terminology (residual load P_600^D)",
    });
    out.push(Entry {
        key: "P150",
        symbol: "P_150",
        name: "residual load at L/150",
        result: p150.clone(),
        method: residual_method("L/150"),
        clause: "C1609 §3 Terminology (residual load P_150^D)",
    });
    out.push(Entry {
        key: "f600",
        symbol: "f_600",
        name: "residual strength at L/600",
        result: f_of(&p600),
        method: stress_method.into(),
        clause: "C1609 §3 Terminology (residual strength f_600^D); §9 Calculation, Eq. 1",
    });
    out.push(Entry {
        key: "f150",
        symbol: "f_150",
        name: "residual strength at L/150",
        result: f_of(&p150),
        method: stress_method.into(),
        clause: "C1609 §3 Terminology (residual strength f_150^D); §9 Calculation, Eq. 1",
    });

    // Toughness and the strength ratio.
    let t150 = curve
        .area_to(l / 150.0)
        .map(|(a, s)| Quantity::new(a, s, "J"))
        .ok_or_else(|| curve.not_reached(&format!("L/150 = {:.3} mm", l / 150.0), l / 150.0));
    out.push(Entry {
        key: "T150",
        symbol: "T_150",
        name: "toughness (area to L/150)",
        result: t150.clone(),
        method: "area under load against smoothed net deflection from the first point to L/150 (trapezoids; kN·mm = J); σ from every \
                 point's σ of deflection and load and the zero reference"
            .into(),
        clause: "C1609 §3 Terminology (toughness T_150^D)",
    });
    // R_T,150 = 150·T150/(f1·b·d²)·100 % = 100·T150/(P1·L/150): b and d cancel.
    let rt = match (&t150, &f1, &p1) {
        (Ok(t), Ok(f), Ok(p)) if f.value > 0.0 && p.value > 0.0 => {
            let v = 150.0 * t.value * 1000.0 / (f.value * b * d * d) * 100.0;
            let rel = ((t.sigma / t.value.abs().max(1e-300)).powi(2) + (p.sigma / p.value).powi(2) + (ul / l).powi(2)).sqrt();
            Ok(Quantity::new(v, v.abs() * rel, "%"))
        }
        (Err(e), _, _) => Err(e.clone()),
        (_, Err(e), _) => Err(format!("needs f1: {e}")),
        _ => Err("f1 is not positive".into()),
    };
    out.push(Entry {
        key: "RT150",
        symbol: "R_T,150",
        name: "equivalent flexural strength ratio",
        result: rt,
        method: "R_T,150 = 150·T150/(f1·b·d²)·100 % (= 100·T150/(P1·L/150): b and d cancel); relative σ from T150, P1 and L combined"
            .into(),
        clause: "C1609 §9 Calculation, Eq. 2 (equivalent flexural strength ratio)",
    });
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Deflection-hardening: elastic to the first crack at 30 kN (0.05 mm), a fall to 27 kN
    /// (0.1 mm), a rise to the peak of 40 kN at 1.5 mm, then down to 32 kN at 3.2 mm.
    fn hardening(x: f64) -> f64 {
        if x <= 0.05 {
            600.0 * x
        } else if x <= 0.1 {
            30.0 - 3.0 * (x - 0.05) / 0.05
        } else if x <= 1.5 {
            27.0 + 13.0 * (x - 0.1) / 1.4
        } else {
            40.0 - 8.0 * (x - 1.5) / 1.7
        }
    }

    fn value(entries: &[Entry], key: &str) -> f64 {
        let e = entries.iter().find(|e| e.key == key).unwrap_or_else(|| panic!("no {key}"));
        e.result.as_ref().unwrap_or_else(|why| panic!("{key}: {why}")).value
    }

    /// The first-peak quantities come from the first peak, not from the test's maximum: on a
    /// curve whose maximum (40 kN at 1.5 mm) comes long after its first peak (30 kN at
    /// 0.05 mm), P1, δ1, f1 and R_T,150 are the first peak's and only P_P and f_P the maximum's.
    #[test]
    fn f1_is_the_first_peak_s_strength_when_the_maximum_comes_later() {
        let n = 1601; // 0 to 3.2 mm in 2 µm steps, 10 points a second
        let x: Vec<f64> = (0..n).map(|i| 0.002 * i as f64).collect();
        let load: Vec<f64> = x.iter().map(|&x| hardening(x)).collect();
        let t_ns: Vec<i64> = (0..n as i64).map(|i| i * 100_000_000).collect();
        let curve = Curve::new(t_ns, load, x, vec![Some(0.001); n], 0.001, 5, 0.01, "deflection").unwrap();
        let beam = BeamConfig { width_mm: 150.0, depth_mm: 150.0, span_mm: 450.0, ..Default::default() };
        let e = compute(&curve, &beam);
        let stress = |p: f64| 1000.0 * p * 450.0 / (150.0 * 150.0 * 150.0);
        let (p1, pp) = (value(&e, "P1"), value(&e, "Pp"));
        assert!((p1 - 30.0).abs() < 0.05, "P1 {p1} kN, the first peak is 30 kN");
        assert!((value(&e, "delta1") - 0.05).abs() < 0.005, "δ1 {} mm, the first peak is at 0.05 mm", value(&e, "delta1"));
        assert!((pp - 40.0).abs() < 0.05, "P_P {pp} kN, the maximum is 40 kN");
        let f1 = value(&e, "f1");
        assert!((f1 - stress(p1)).abs() < 1e-9 * f1, "f1 {f1} MPa is not P1·L/(b·d²) = {} MPa (P_P's: {})", stress(p1), stress(pp));
        assert!((f1 - 4.0).abs() < 0.01, "f1 {f1} MPa, the first peak's strength is 4.0 MPa");
        assert!((value(&e, "fp") - stress(pp)).abs() < 1e-9 * stress(pp), "f_P {} MPa", value(&e, "fp"));
        // R_T,150 = 100·T150/(P1·L/150), with the first peak's load.
        let rt = value(&e, "RT150");
        let expected = 100.0 * value(&e, "T150") / (p1 * 450.0 / 150.0);
        assert!((rt - expected).abs() < 1e-9 * expected, "R_T,150 {rt} %, from P1 {expected} %");
    }
}
