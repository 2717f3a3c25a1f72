//! Is the feed a complete test of the standard? `report.json` `valid` and `invalid_reasons`,
//! and the banner at the top of the HTML. Every reason is a sentence a technician
//! understands (what was found, where, and what the standard asks for).
//!
//! The rules:
//! * ASTM C1609 / C1856: a first peak (a maximum the load falls from) before L/150 — or, when
//!   the lab states a hardening response (`[report] response = "hardening"`), anywhere (the
//!   first zero slope of a deflection-hardening curve can lie beyond L/150; said in
//!   `validity_unchecked`); the net deflection carried to L/150. EN 14651: a load measured
//!   with the CMOD in 0–0.05 mm (F_L undetermined by a gauge too noisy to tell where the CMOD
//!   passes 0.05 mm is unchecked, not a reason); the CMOD carried to 3.5 mm.
//! * Loading monotonic: the smoothed deflection (CMOD) never goes back by more than 5 σ.
//! * The rate of deflection (CMOD) within the standard's window, per phase (least-squares
//!   slope over the phase). C1609: up to L/900 0.025–0.075 mm/min (depth ≤ 125 mm) or
//!   0.035–0.10 mm/min (larger beams), after it 0.05–0.20 or 0.05–0.30 mm/min. EN 14651:
//!   0.05 ± 0.01 mm/min up to CMOD 0.1 mm, 0.2 ± 0.04 mm/min after it. Each rule's source (document and clause) is listed by
//!   `method_statement`; C1856 refers its flexural test to C1609, whose rates are applied.
//!   A rate outside its window by less than 2 σ of the fitted rate (a gauge as noisy as the
//!   phase is long) is unchecked, not a reason (docs/report.md, "F_L on the EN day").
//! * No gap longer than `max_gap_s` between feed lines or UTM samples, no UTM outage.
//! * The load starts near zero: within max(3 σ, 5 % of the peak load).

use crate::config::BeamConfig;
use crate::curve::Curve;
use crate::feed_reader::Feed;
use crate::standard::Standard;
use crate::{c1609, en14651};

/// Least points for a rate to be measured over a phase.
const MIN_RATE_POINTS: usize = 5;

/// The verdict.
#[derive(Debug, Clone, PartialEq)]
pub struct Validity {
    /// True only when no rule failed.
    pub valid: bool,
    /// Why not, one sentence each.
    pub reasons: Vec<String>,
    /// Rules that could not be checked on this test.
    pub unchecked: Vec<String>,
    /// Measured rates: `(phase, mm/min, window)`.
    pub rates: Vec<(String, f64, (f64, f64))>,
}

/// A standard's windows for the rate of its controlled quantity (net deflection; CMOD for EN
/// 14651), below and above `split_mm` of it (see the module doc); the live page colours the
/// rate by them.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct RateWindows {
    /// Where the second window begins (L/900; CMOD 0.1 mm), mm.
    pub split_mm: f64,
    /// Up to `split_mm`: `[low, high]`, mm/min.
    pub below_mm_per_min: (f64, f64),
    /// Beyond it.
    pub above_mm_per_min: (f64, f64),
}

/// The windows of `standard` for `beam`.
pub fn rate_windows(standard: Standard, beam: &BeamConfig) -> RateWindows {
    let (split_mm, [below, above]) = match standard {
        Standard::AstmC1609 | Standard::AstmC1856 => {
            let w = if beam.depth_mm <= 125.0 { [(0.025, 0.075), (0.05, 0.20)] } else { [(0.035, 0.10), (0.05, 0.30)] };
            (beam.span_mm / 900.0, w)
        }
        Standard::En14651 => (0.1, [(0.04, 0.06), (0.16, 0.24)]),
    };
    RateWindows { split_mm, below_mm_per_min: below, above_mm_per_min: above }
}

/// What the check needs.
pub(crate) struct Input<'a> {
    pub standard: Standard,
    /// The response the lab stated (`[report] response`).
    pub response: crate::Response,
    pub beam: &'a BeamConfig,
    /// The frame-rate curve (x as measured, smoothed).
    pub feed_curve: &'a Curve,
    /// The curve the load-based values come from.
    pub load_curve: &'a Curve,
    pub feed: &'a Feed,
    pub x_name: &'a str,
    pub max_gap_s: f64,
    /// Gaps of the UTM stream longer than `max_gap_s`, s from the feed's start.
    pub utm_gaps: Vec<(f64, f64)>,
    pub utm_outages_s: f64,
    /// The test's method: its phases' windows and its end replace the built-in ones.
    pub method: Option<&'a tagdeflect_core::method::Method>,
}

/// A phase whose rate is checked: its name, where it starts and ends (mm of the gauge), its
/// window (mm/min).
struct RatePhase {
    name: String,
    from_mm: f64,
    to_mm: f64,
    window: (f64, f64),
}

/// The phases and the end (mm, its name) the test is checked against: the method's when the
/// test names one, else the standard's built-in windows ([`rate_windows`]).
fn phases_and_end(i: &Input, std_end: f64, end_name: &str, split_name: &str) -> (Vec<RatePhase>, f64, String) {
    let Some(m) = i.method else {
        let rw = rate_windows(i.standard, i.beam);
        let split = rw.split_mm;
        let phases = vec![
            RatePhase { name: format!("up to {split_name}"), from_mm: 0.1 * split, to_mm: split, window: rw.below_mm_per_min },
            RatePhase { name: format!("from {split_name} to {end_name}"), from_mm: split, to_mm: std_end, window: rw.above_mm_per_min },
        ];
        return (phases, std_end, end_name.to_string());
    };
    let span = i.beam.span_mm;
    let (end, end_name) = match (m.end.at_mm, m.end.at_span_over) {
        (_, Some(n)) => (span / n, format!("L/{n} = {:.2} mm", span / n)),
        (Some(v), None) => (v, format!("{} = {v} mm", if m.end.gauge == "cmod" { "CMOD" } else { "net deflection" })),
        (None, None) => (std_end, end_name.to_string()),
    };
    let mut phases = Vec::new();
    let mut from: Option<f64> = None;
    for p in m.phases_for(Some(i.beam.depth_mm)) {
        let to = p.until_mm.or(p.until_span_over.map(|n| span / n)).unwrap_or(end);
        let start = from.unwrap_or(0.1 * to);
        let window = (p.rate_mm_per_min[0], p.rate_mm_per_min[1]);
        phases.push(RatePhase { name: format!("in phase \"{}\" of method {}", p.name, m.name), from_mm: start, to_mm: to, window });
        from = Some(to);
    }
    (phases, end, end_name)
}

fn t_of(feed: &Feed, t_ns: i64) -> f64 {
    (t_ns - feed.columns.t_ns[0]) as f64 * 1e-9
}

/// Checks the rules.
pub(crate) fn check(i: &Input) -> Validity {
    let mut reasons = Vec::new();
    let mut unchecked = Vec::new();
    let fc = i.feed_curve;
    let lc = i.load_curve;
    let xmax = fc.xs.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
    let (std_end, std_end_name, split_name): (f64, String, String) = match i.standard {
        Standard::AstmC1609 | Standard::AstmC1856 => {
            let l = i.beam.span_mm;
            (l / 150.0, format!("L/150 = {:.2} mm", l / 150.0), format!("L/900 = {:.3} mm", l / 900.0))
        }
        Standard::En14651 => (3.5, "CMOD = 3.5 mm".into(), "CMOD = 0.1 mm".into()),
    };
    let (phases, end_at, end_at_name) = phases_and_end(i, std_end, &std_end_name, &split_name);
    let (end, end_name) = (std_end, std_end_name);
    if i.standard == Standard::AstmC1856 && i.method.is_none() {
        unchecked.push("ASTM C1856 refers its flexural test to ASTM C1609: C1609's rates were applied.".into());
    }

    // Reached the end of the test.
    if fc.xs[0] > 5.0 * fc.sxs[0] + 0.01 * end {
        reasons
            .push(format!("The {} was already {:.3} mm at the first line: the test was not recorded from its start.", i.x_name, fc.xs[0]));
    }
    if let Some(m) = i.method.filter(|_| fc.crossing(end_at).is_none()) {
        reasons
            .push(format!("The {} reached only {:.3} mm: the test ended early; method {} ends at {end_at_name}.", i.x_name, xmax, m.name));
    } else if fc.crossing(end).is_none() {
        reasons.push(format!(
            "The {} reached only {:.3} mm: {} needs the test carried to {end_name}.",
            i.x_name,
            xmax,
            match i.standard {
                Standard::En14651 => "EN 14651",
                Standard::AstmC1856 => "ASTM C1856 (its flexural test, ASTM C1609)",
                Standard::AstmC1609 => "ASTM C1609",
            }
        ));
    }

    // The first peak / the limit of proportionality.
    match i.standard {
        Standard::AstmC1609 | Standard::AstmC1856 => match c1609::first_peak(lc) {
            None => reasons.push(
                "No first peak: the load never fell after a maximum, so the first crack (the first point where the slope is zero) \
                 was not reached or not recorded."
                    .into(),
            ),
            Some(j) if lc.xs[j] >= end && i.response == crate::Response::Hardening => unchecked.push(format!(
                "A hardening response was stated: the first zero slope of the curve, and so the first peak, lies beyond \
                 {end_name} ({:.2} kN at {:.3} mm; P1 = Pp). Whether the beam cracked before it is not judged from the curve.",
                lc.load[j], lc.xs[j]
            )),
            Some(j) if lc.xs[j] >= end => reasons.push(format!(
                "The first peak ({:.2} kN at a net deflection of {:.3} mm) lies beyond {end_name}: the beam did not crack as a C1609 \
                 specimen does (an uncracked beam, load cycles, or not this test). A deflection-hardening specimen is stated with \
                 `[report] response = \"hardening\"` (or --response hardening).",
                lc.load[j], lc.xs[j]
            )),
            Some(_) => {}
        },
        Standard::En14651 => match en14651::limit_of_proportionality(lc, en14651::LOP_CMOD_MM) {
            Err(en14651::LopError::NotMeasured(why)) => {
                reasons.push(format!("No load was measured with the CMOD between 0 and 0.05 mm ({why}): F_L cannot be determined."))
            }
            Err(en14651::LopError::Unresolved(why)) => unchecked
                .push(format!("F_L could not be determined: {why}. A CMOD gauge of finer resolution (a clip gauge) is needed for it.")),
            Ok(_) => {}
        },
    }

    // Monotonic loading.
    let mut run_max = fc.xs[0];
    let mut worst: Option<(usize, f64, f64)> = None;
    for k in 1..fc.len() {
        run_max = run_max.max(fc.xs[k]);
        let back = run_max - fc.xs[k];
        if back > 5.0 * fc.sxs[k].max(1e-6) && worst.is_none_or(|w| back > w.1) {
            worst = Some((k, back, run_max));
        }
    }
    if let Some((k, back, from)) = worst {
        reasons.push(format!(
            "The {} went back by {back:.3} mm (from {from:.3} mm to {:.3} mm, {:.1} s into the feed): the loading was not monotonic \
             (load cycles or an unloading); the standard loads continuously.",
            i.x_name, fc.xs[k], fc.t_s[k]
        ));
    }

    // Rates.
    let mut rates = Vec::new();
    let asks = if i.method.is_some() { "the method asks" } else { "the standard asks" };
    for RatePhase { name, from_mm: lo, to_mm: hi, window: (wlo, whi) } in phases {
        // The first pass through the phase (a later unloading is another fault).
        let idx: Vec<usize> = match (0..fc.len()).find(|&k| fc.xs[k] >= lo) {
            Some(s) => (s..fc.len()).take_while(|&k| fc.xs[k] <= hi).collect(),
            None => Vec::new(),
        };
        if idx.len() < MIN_RATE_POINTS {
            unchecked.push(format!(
                "The rate {name} could not be checked: {} point(s) of the curve lie there (at least {MIN_RATE_POINTS} are needed).",
                idx.len()
            ));
            continue;
        }
        let ts: Vec<f64> = idx.iter().map(|&k| fc.t_s[k]).collect();
        let xs: Vec<f64> = idx.iter().map(|&k| fc.xs[k]).collect();
        let rate = slope(&ts, &xs) * 60.0;
        rates.push((name.clone(), rate, (wlo, whi)));
        if (wlo..=whi).contains(&rate) {
            continue;
        }
        let sxs: Vec<f64> = idx.iter().map(|&k| fc.sxs[k]).collect();
        let sigma = slope_sigma(&ts, &sxs, fc.smooth_points) * 60.0;
        let off = if rate < wlo { wlo - rate } else { rate - whi };
        if off <= 2.0 * sigma {
            unchecked.push(format!(
                "The rate {name} could not be told from its window: the {} increased at {} ± {} mm/min over {} points, within 2 σ of \
                 {wlo} to {whi} mm/min (the gauge's noise, σ {:.3} mm a point, against the phase's {:.3} mm).",
                i.x_name,
                fmt_rate(rate),
                fmt_rate(sigma),
                idx.len(),
                sxs.iter().sum::<f64>() / sxs.len() as f64,
                hi - lo
            ));
            continue;
        }
        reasons.push(format!("The {} increased at {} mm/min {name}; {asks} for {wlo} to {whi} mm/min.", i.x_name, fmt_rate(rate)));
    }

    // Gaps.
    let feed = i.feed;
    let mut gaps = 0;
    let mut longest = (0.0, 0.0, 0.0);
    for w in feed.columns.t_ns.windows(2) {
        let d = (w[1] - w[0]) as f64 * 1e-9;
        if d > i.max_gap_s {
            gaps += 1;
            if d > longest.0 {
                longest = (d, t_of(feed, w[0]), t_of(feed, w[1]));
            }
        }
    }
    if gaps > 0 {
        reasons.push(format!(
            "The feed has {gaps} gap(s) longer than {} s without a line (the longest {:.1} s, from {:.1} s to {:.1} s into the feed): \
             the curve is not measured there.",
            i.max_gap_s, longest.0, longest.1, longest.2
        ));
    }
    if let Some(&(a, b)) = i.utm_gaps.iter().max_by(|x, y| (x.1 - x.0).total_cmp(&(y.1 - y.0))) {
        reasons.push(format!(
            "The UTM stream has {} gap(s) longer than {} s (the longest {:.1} s, from {a:.1} s to {b:.1} s into the feed): the load is not known there.",
            i.utm_gaps.len(),
            i.max_gap_s,
            b - a
        ));
    }
    if i.utm_outages_s > 0.0 {
        reasons.push(format!("The UTM was unreachable for {:.1} s during the test: the load is not known then.", i.utm_outages_s));
    }

    // The load from zero.
    let pmax = lc.load.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
    let p0 = lc.load[0];
    if p0.abs() > (3.0 * lc.load_sigma).max(0.05 * pmax.abs()) {
        reasons.push(format!(
            "The load was already {p0:.2} kN at the first point ({:.0} % of the peak load): the test was not recorded from its start, \
             or the load cell was not zeroed.",
            100.0 * p0 / pmax
        ));
    }
    Validity { valid: reasons.is_empty(), reasons, unchecked, rates }
}

fn fmt_rate(r: f64) -> String {
    if r.abs() >= 10.0 {
        format!("{r:.0}")
    } else if r.abs() >= 1.0 {
        format!("{r:.1}")
    } else {
        format!("{r:.3}")
    }
}

/// Least-squares slope of `y` on `t`.
fn slope(t: &[f64], y: &[f64]) -> f64 {
    let n = t.len() as f64;
    let mt = t.iter().sum::<f64>() / n;
    let my = y.iter().sum::<f64>() / n;
    let stt: f64 = t.iter().map(|v| (v - mt) * (v - mt)).sum();
    let sty: f64 = t.iter().zip(y).map(|(a, b)| (a - mt) * (b - my)).sum();
    if stt > 0.0 {
        sty / stt
    } else {
        0.0
    }
}

/// σ of [`slope`] from the points' σ `sy`, each point a mean over `smooth_points` neighbours
/// (the smoothed curve's): `√(Σ wᵢ² σᵢ²)` with `wᵢ = (tᵢ − t̄)/Σ(t − t̄)²`, times
/// `√smooth_points` for the neighbours' shared noise (a bound: fully shared within a window).
fn slope_sigma(t: &[f64], sy: &[f64], smooth_points: usize) -> f64 {
    let n = t.len() as f64;
    let mt = t.iter().sum::<f64>() / n;
    let stt: f64 = t.iter().map(|v| (v - mt) * (v - mt)).sum();
    if stt <= 0.0 {
        return f64::INFINITY;
    }
    let var: f64 = t.iter().zip(sy).map(|(a, s)| ((a - mt) / stt * s).powi(2)).sum();
    var.sqrt() * (smooth_points.max(1) as f64).sqrt()
}

#[cfg(test)]
mod tests;
