//! Clock check: the offset between the UTM's clock and the cameras' clock, found by
//! aligning the measured net deflection with the UTM's stroke over the loading ramp.
//!
//! Model: `δ(tᵢ) = a + b s(tᵢ + τ)` over the loading ramp before the first peak — the net
//! deflection measured at camera time `tᵢ` against the stroke the UTM stamped at `tᵢ + τ`
//! (while the beam is elastic the load is proportional to the deflection, so the stroke —
//! deflection under the loads + compliance × load — is linear in it).
//! The offset `τ` = UTM time − camera time of one instant (positive: the UTM clock is
//! ahead; subtract it from UTM stamps to put them on the cameras' clock). It is identified by
//! the changes of rate of the test (the start of the ramp from rest, pop-ins, holds): over a
//! ramp of constant rate a shift looks like an offset of the stroke. Least squares: a scan of
//! `τ` over `±max_offset_ms` (mean squared residual of the points the stroke covers), then
//! golden-section refinement on a fixed set of points; σ from the Gauss–Newton covariance
//! `s² (JᵀJ)⁻¹` with `J = [1, s, ∂δ̂/∂τ]` and `s²` the residual variance (the
//! deflection's noise; the stroke is taken as exact), inflated by `(1 + ρ)/(1 − ρ)` for a
//! positive lag-1 autocorrelation `ρ` of the residuals (a relation that does not quite fit
//! leaves runs of residuals, which are not independent). Points: the loading ramp, from the
//! first line until the load falls below 97 % of its maximum so far (the first peak: after
//! it, cracking makes the relation non-linear) and up to the largest deflection.
//!
//! [`ClockCheck`] is the live, incremental estimator (every `every_lines` lines once enough
//! points are in); [`estimate_from_feed`] the batch function over a whole feed.

use serde::{Deserialize, Serialize};

use tagdeflect_core::feed::{FeedLine, ValueSigma};
use tagdeflect_core::utm_sample::UtmHistory;

/// `[clock_check]` (extension): the live clock check.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ClockCheckConfig {
    /// Estimate (and report in the feed) every this many lines.
    pub every_lines: u32,
    /// Warn when the offset exceeds this, ms (and is significant: more than 3 σ).
    pub warn_ms: f64,
    /// Offsets searched: ±this, ms.
    pub max_offset_ms: f64,
    /// Lines with a net deflection needed before the first estimate.
    pub min_points: u32,
}

impl Default for ClockCheckConfig {
    fn default() -> Self {
        Self { every_lines: 10, warn_ms: 20.0, max_offset_ms: 1000.0, min_points: 20 }
    }
}

impl ClockCheckConfig {
    /// Checks the values; keys relative to `[clock_check]`.
    pub fn validate(&self) -> Result<(), tagdeflect_core::Problem> {
        use tagdeflect_core::Problem;
        if self.every_lines == 0 {
            return Err(Problem::new("every_lines", "must be ≥ 1"));
        }
        if !(self.warn_ms.is_finite() && self.warn_ms > 0.0) {
            return Err(Problem::new("warn_ms", format!("must be a positive number of ms, got {}", self.warn_ms)));
        }
        if !(self.max_offset_ms.is_finite() && self.max_offset_ms > 0.0 && self.max_offset_ms <= 60_000.0) {
            return Err(Problem::new("max_offset_ms", format!("must be in (0, 60000] ms, got {}", self.max_offset_ms)));
        }
        if self.min_points < 8 {
            return Err(Problem::new("min_points", "must be ≥ 8"));
        }
        Ok(())
    }
}

/// An estimated clock offset.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ClockOffset {
    /// UTM time − camera time of one instant, ms.
    pub offset_ms: f64,
    /// 1-σ uncertainty, ms.
    pub sigma_ms: f64,
    /// Points used.
    pub points: usize,
    /// RMS residual of the deflection against the fitted stroke relation, mm.
    pub rms_mm: f64,
}

impl ClockOffset {
    /// As the feed carries it.
    pub fn to_feed(&self) -> ValueSigma {
        ValueSigma { value: (self.offset_ms * 100.0).round() / 100.0, sigma: ((self.sigma_ms * 100.0).round() / 100.0).max(0.01) }
    }
}

/// The points of the loading ramp: up to the largest deflection, unless the deflection has
/// not fallen back by 5 % of its range since.
fn ramp(points: &[(i64, f64)]) -> &[(i64, f64)] {
    let Some((imax, _)) = points.iter().enumerate().max_by(|a, b| a.1 .1.total_cmp(&b.1 .1)) else { return points };
    let lo = points.iter().map(|p| p.1).fold(f64::INFINITY, f64::min);
    let range = points[imax].1 - lo;
    let fell = points[imax..].iter().any(|p| p.1 < points[imax].1 - 0.05 * range);
    if fell {
        &points[..=imax]
    } else {
        points
    }
}

/// The deflection as a piecewise-linear function of the stroke (hat functions on knots at
/// quantiles of the stroke): flexible enough for the machine's compliance × a load that is
/// not proportional to deflection, too stiff to follow a shift of time at a change of rate.
struct Relation {
    knots: Vec<f64>,
    coef: nalgebra::DVector<f64>,
    ssr: f64,
}

/// Knots at quantiles of the strokes (`count` at most; closer ones merged).
fn knots_for(pairs: &[(f64, f64)], count: usize) -> Vec<f64> {
    let mut s: Vec<f64> = pairs.iter().map(|p| p.0).collect();
    s.sort_by(f64::total_cmp);
    let (lo, hi) = (s[0], s[s.len() - 1]);
    let min_gap = (hi - lo) / 50.0;
    let mut knots: Vec<f64> = Vec::new();
    for k in 0..count {
        let q = s[((s.len() - 1) * k) / (count - 1).max(1)];
        if knots.last().is_none_or(|l| q - l > min_gap) {
            knots.push(q);
        }
    }
    if knots.len() >= 2 {
        *knots.last_mut().unwrap() = hi;
    }
    knots
}

/// Hat-function weights of stroke `s` (clamped to the knots' span).
fn hats(knots: &[f64], s: f64) -> [(usize, f64); 2] {
    let n = knots.len();
    if s <= knots[0] {
        return [(0, 1.0), (0, 0.0)];
    }
    if s >= knots[n - 1] {
        return [(n - 1, 1.0), (n - 1, 0.0)];
    }
    let i = knots.partition_point(|k| *k <= s) - 1;
    let w = (s - knots[i]) / (knots[i + 1] - knots[i]);
    [(i, 1.0 - w), (i + 1, w)]
}

impl Relation {
    fn fit(pairs: &[(f64, f64)], knots: &[f64]) -> Option<Relation> {
        let k = knots.len();
        if k < 2 || pairs.len() < k + 2 {
            return None;
        }
        let mut a = nalgebra::DMatrix::<f64>::zeros(k, k);
        let mut r = nalgebra::DVector::<f64>::zeros(k);
        for &(s, d) in pairs {
            let h = hats(knots, s);
            for &(i, wi) in &h {
                r[i] += wi * d;
                for &(j, wj) in &h {
                    a[(i, j)] += wi * wj;
                }
            }
        }
        let coef = a.try_inverse()? * r;
        let mut rel = Relation { knots: knots.to_vec(), coef, ssr: 0.0 };
        rel.ssr = pairs.iter().map(|&(s, d)| (d - rel.at(s)).powi(2)).sum();
        Some(rel)
    }

    fn at(&self, s: f64) -> f64 {
        hats(&self.knots, s).iter().map(|&(i, w)| w * self.coef[i]).sum()
    }

    /// Slope dδ/ds of the segment holding `s` (0 outside the knots' span).
    fn slope(&self, s: f64) -> f64 {
        let n = self.knots.len();
        if s <= self.knots[0] || s >= self.knots[n - 1] {
            return 0.0;
        }
        let i = self.knots.partition_point(|k| *k <= s) - 1;
        (self.coef[i + 1] - self.coef[i]) / (self.knots[i + 1] - self.knots[i])
    }
}

/// Number of knots for `n` points.
///
/// Two: the relation is a straight line. Over the elastic ramp before the first peak the
/// load is proportional to the deflection, so the stroke (deflection under the loads +
/// compliance × load) is linear in it; a more flexible relation would also absorb a shift
/// of time next to the start of the ramp (a steeper first segment), which is where the
/// offset is measured.
fn knot_count(_n: usize) -> usize {
    2
}

/// Follows the load along a test: true while the test is still on its loading ramp before
/// the first peak (the load has not fallen below 97 % of its maximum so far).
#[derive(Debug, Clone, Copy, Default)]
struct PrePeak {
    max: f64,
    /// Time of the line with the largest load so far.
    t_max: i64,
    ended: bool,
}

impl PrePeak {
    fn on_ramp(&mut self, t_ns: i64, load_kn: Option<f64>) -> bool {
        if let Some(l) = load_kn {
            if l > self.max {
                self.max = l;
                self.t_max = t_ns;
            } else if self.max > 0.0 && l < 0.97 * self.max && self.max - l > 1e-3 {
                self.ended = true;
            }
        }
        !self.ended
    }
}

/// Once the ramp has ended, the points to keep: before the line of the largest load less
/// `margin_ns` (the loads of the lines are read on the UTM's clock, so the peak's line may
/// already be past the crack in camera time by the offset).
fn before_peak(points: &mut Vec<(i64, f64)>, t_max: i64, margin_ns: i64) {
    points.retain(|p| p.0 < t_max - margin_ns);
}

/// The lines of the loading ramp before the first peak (by their load), time-sorted, and
/// the time of the largest load when the ramp ended.
fn pre_peak(lines: &[FeedLine]) -> (Vec<&FeedLine>, Option<i64>) {
    let mut sorted: Vec<&FeedLine> = lines.iter().collect();
    sorted.sort_by_key(|l| l.t_ns);
    let mut ramp = PrePeak::default();
    let kept: Vec<&FeedLine> = sorted.into_iter().take_while(|l| ramp.on_ramp(l.t_ns, l.load_kn)).collect();
    (kept, ramp.ended.then_some(ramp.t_max))
}

/// [`estimate`] on the pre-peak points: a first pass without the peak's line, a second
/// with the points within the first estimate's offset (+ 3σ) of the peak left out too.
fn estimate_pre_peak(
    mut points: Vec<(i64, f64)>,
    t_max: Option<i64>,
    stroke: impl Fn(i64) -> Option<f64>,
    max_offset_ms: f64,
) -> Option<ClockOffset> {
    points.sort_by_key(|p| p.0);
    let Some(t_max) = t_max else { return estimate(&points, stroke, max_offset_ms) };
    before_peak(&mut points, t_max, 0);
    let first = estimate(&points, &stroke, max_offset_ms)?;
    before_peak(&mut points, t_max, ((first.offset_ms.abs() + 3.0 * first.sigma_ms) * 1e6) as i64);
    estimate(&points, &stroke, max_offset_ms).or(Some(first))
}

/// Sum of squared residuals of the relation fitted to `pairs` (knots from the pairs).
fn fit_ssr(pairs: &[(f64, f64)]) -> Option<f64> {
    Relation::fit(pairs, &knots_for(pairs, knot_count(pairs.len()))).map(|r| r.ssr)
}

/// Estimates the clock offset from `(camera t_ns, net deflection mm)` points and the UTM
/// stroke as a function of UTM time (`None` where unknown), searching ±`max_offset_ms`.
/// `None` when the points do not determine it (too few, no motion, no change of rate).
pub fn estimate(points: &[(i64, f64)], stroke: impl Fn(i64) -> Option<f64>, max_offset_ms: f64) -> Option<ClockOffset> {
    estimate_within(points, stroke, -max_offset_ms, max_offset_ms)
}

/// [`estimate`] searching offsets in `[lo_ms, hi_ms]` only (the live check, once determined,
/// searches near its last estimate).
pub(crate) fn estimate_within(points: &[(i64, f64)], stroke: impl Fn(i64) -> Option<f64>, lo_ms: f64, hi_ms: f64) -> Option<ClockOffset> {
    let pts = ramp(points);
    if pts.len() < 8 {
        return None;
    }
    let ms = 1e6;
    let pairs_at = |tau_ms: f64, subset: &[(i64, f64)]| -> Vec<(f64, f64)> {
        let shift = (tau_ms * ms).round() as i64;
        subset.iter().filter_map(|&(t, d)| stroke(t + shift).map(|s| (s, d))).collect()
    };
    // Coarse scan: mean squared residual of the covered points (at least 60 % of them).
    let steps = 400;
    let step = ((hi_ms - lo_ms) / steps as f64).max(0.5);
    let mut best: Option<(f64, f64)> = None;
    let mut tau = lo_ms;
    while tau <= hi_ms + 1e-9 {
        let pairs = pairs_at(tau, pts);
        if pairs.len() * 10 >= pts.len() * 6 && pairs.len() >= 8 {
            if let Some(ssr) = fit_ssr(&pairs) {
                let msr = ssr / pairs.len() as f64;
                if best.is_none_or(|b| msr < b.1) {
                    best = Some((tau, msr));
                }
            }
        }
        tau += step;
    }
    let (coarse, _) = best?;
    // Fixed set: points covered over the whole refinement bracket.
    let (lo, hi) = (coarse - 2.0 * step, coarse + 2.0 * step);
    let fixed: Vec<(i64, f64)> =
        pts.iter().copied().filter(|&(t, _)| stroke(t + (lo * ms) as i64).is_some() && stroke(t + (hi * ms) as i64).is_some()).collect();
    if fixed.len() < 8 {
        return None;
    }
    // Knots fixed for the refinement (from the coarse optimum).
    let knots = knots_for(&pairs_at(coarse, &fixed), knot_count(fixed.len()));
    let cost = |tau: f64| Relation::fit(&pairs_at(tau, &fixed), &knots).map_or(f64::INFINITY, |f| f.ssr);
    let (mut a, mut b) = (lo, hi);
    let g = 0.5 * (5f64.sqrt() - 1.0);
    let (mut c, mut d) = (b - g * (b - a), a + g * (b - a));
    let (mut fc, mut fd) = (cost(c), cost(d));
    while b - a > 0.01 {
        if fc < fd {
            b = d;
            d = c;
            fd = fc;
            c = b - g * (b - a);
            fc = cost(c);
        } else {
            a = c;
            c = d;
            fc = fd;
            d = a + g * (b - a);
            fd = cost(d);
        }
    }
    let tau = 0.5 * (a + b);
    let pairs = pairs_at(tau, &fixed);
    let rel = Relation::fit(&pairs, &knots)?;
    let ssr = rel.ssr;
    let n = pairs.len();
    let k = knots.len();
    let s2 = ssr / (n as f64 - k as f64 - 1.0).max(1.0);
    // Gauss–Newton covariance with the stroke's local slope (per ms) from ±5 ms.
    let mut jtj = nalgebra::DMatrix::<f64>::zeros(k + 1, k + 1);
    let shift = (tau * ms).round() as i64;
    for &(t, _) in &fixed {
        let (Some(s), Some(sp), Some(sm)) = (stroke(t + shift), stroke(t + shift + 5_000_000), stroke(t + shift - 5_000_000)) else {
            continue;
        };
        let mut j = nalgebra::DVector::<f64>::zeros(k + 1);
        for (i, w) in hats(&knots, s) {
            j[i] += w;
        }
        j[k] = rel.slope(s) * (sp - sm) / 10.0;
        jtj += &j * j.transpose();
    }
    let cov = jtj.try_inverse()?;
    // Residuals that follow each other in time (the relation does not quite fit) carry less
    // information than independent noise: the variance is inflated by (1 + ρ) / (1 − ρ),
    // ρ = their lag-1 autocorrelation (when positive).
    let residuals: Vec<f64> = fixed.iter().filter_map(|&(t, d)| stroke(t + shift).map(|s| d - rel.at(s))).collect();
    let (num, den) = residuals.windows(2).fold((0.0, 0.0), |(n, d), w| (n + w[0] * w[1], d + w[0] * w[0]));
    let rho = if den > 0.0 { (num / den).clamp(0.0, 0.9) } else { 0.0 };
    let sigma = (s2 * cov[(k, k)] * (1.0 + rho) / (1.0 - rho)).sqrt();
    let range = fixed.iter().map(|p| p.1).fold(f64::NEG_INFINITY, f64::max) - fixed.iter().map(|p| p.1).fold(f64::INFINITY, f64::min);
    let rms = (ssr / n as f64).sqrt();
    if !(sigma.is_finite() && sigma > 0.0) || range < 10.0 * rms.max(1e-4) {
        return None;
    }
    Some(ClockOffset { offset_ms: tau, sigma_ms: sigma, points: n, rms_mm: rms })
}

/// Piecewise-linear interpolation in a time-sorted series (no extrapolation).
fn interpolate(series: &[(i64, f64)], t: i64) -> Option<f64> {
    let (first, last) = (series.first()?, series.last()?);
    if t < first.0 || t > last.0 {
        return None;
    }
    let i = series.partition_point(|p| p.0 < t);
    let b = series[i];
    if b.0 == t || i == 0 {
        return Some(b.1);
    }
    let a = series[i - 1];
    Some(a.1 + (b.1 - a.1) * (t - a.0) as f64 / (b.0 - a.0) as f64)
}

/// The batch clock check over a whole feed: the lines' net deflection against their
/// stroke (the UTM stroke as interpolated to each line; the series of lines is
/// interpolated again at shifted times). `net` picks the deflection of a line (e.g. the
/// line's `net_deflection_mm`, or a `net_deflection` gauge).
pub fn estimate_from_feed(lines: &[FeedLine], max_offset_ms: f64) -> Option<ClockOffset> {
    let net = |l: &FeedLine| l.net_deflection_mm.or_else(|| l.gauges.values().find(|g| g.unit == "mm").map(|g| g.value));
    let (ramp, t_max) = pre_peak(lines);
    let points: Vec<(i64, f64)> = ramp.into_iter().filter_map(|l| net(l).map(|d| (l.t_ns, d))).collect();
    let mut stroke: Vec<(i64, f64)> = lines.iter().filter_map(|l| l.stroke_mm.map(|s| (l.t_ns, s))).collect();
    stroke.sort_by_key(|p| p.0);
    estimate_pre_peak(points, t_max, |t| interpolate(&stroke, t), max_offset_ms)
}

/// The batch clock check against the UTM's own samples (e.g. a recording's `utm.jsonl`).
pub fn estimate_from_utm(lines: &[FeedLine], utm: &[tagdeflect_core::utm_sample::UtmSample], max_offset_ms: f64) -> Option<ClockOffset> {
    let (ramp, t_max) = pre_peak(lines);
    let points: Vec<(i64, f64)> = ramp.into_iter().filter_map(|l| l.net_deflection_mm.map(|d| (l.t_ns, d))).collect();
    let mut stroke: Vec<(i64, f64)> = utm.iter().filter_map(|s| s.stroke_mm.map(|v| (s.t_ns, v))).collect();
    stroke.sort_by_key(|p| p.0);
    estimate_pre_peak(points, t_max, |t| interpolate(&stroke, t), max_offset_ms)
}

/// The live clock check: collects `(t, net deflection)` and estimates against the
/// measurement's UTM history every `every_lines` lines.
#[derive(Debug, Clone)]
pub struct ClockCheck {
    config: ClockCheckConfig,
    points: Vec<(i64, f64)>,
    lines: u64,
    last: Option<ClockOffset>,
    warned_at: Option<f64>,
    ramp: PrePeak,
}

/// Points kept by the live estimator (older ones are thinned out beyond this).
const MAX_POINTS: usize = 4000;

impl ClockCheck {
    /// A clock check with `config`.
    pub fn new(config: ClockCheckConfig) -> ClockCheck {
        ClockCheck { config, points: Vec::new(), lines: 0, last: None, warned_at: None, ramp: PrePeak::default() }
    }

    /// The latest estimate.
    pub fn latest(&self) -> Option<ClockOffset> {
        self.last
    }

    /// Adds one feed line's net deflection (when it has one, and the test is still on its
    /// loading ramp before the first peak, by `load_kn`); every `every_lines` lines,
    /// re-estimates against `utm` and returns the estimate for the feed (once determined;
    /// after the first peak the last estimate is repeated).
    pub fn update(&mut self, t_ns: i64, net_deflection_mm: Option<f64>, load_kn: Option<f64>, utm: &UtmHistory) -> Option<ValueSigma> {
        self.lines += 1;
        let was_on_ramp = !self.ramp.ended;
        let on_ramp = self.ramp.on_ramp(t_ns, load_kn);
        if was_on_ramp && !on_ramp {
            // The first peak: a last estimate from the points before it, then frozen.
            let stroke = |t: i64| utm.interpolate(t).and_then(|(_, s)| s);
            let points = std::mem::take(&mut self.points);
            if let Some(e) = estimate_pre_peak(points, Some(self.ramp.t_max), stroke, self.config.max_offset_ms) {
                self.last = Some(e);
            }
        }
        if !on_ramp {
            return self.lines.is_multiple_of(self.config.every_lines as u64).then_some(self.last?.to_feed());
        }
        if let Some(d) = net_deflection_mm.filter(|_| on_ramp) {
            self.points.push((t_ns, d));
            if self.points.len() > MAX_POINTS {
                // Thin out every other point of the older half: the ramp's start is kept.
                let half = self.points.len() / 2;
                let mut k = 0;
                self.points.retain(|_| {
                    k += 1;
                    k > half || k % 2 == 1
                });
            }
        }
        if !self.lines.is_multiple_of(self.config.every_lines as u64)
            || self.points.len() < self.config.min_points as usize
            || utm.is_empty()
        {
            return None;
        }
        let stroke = |t: i64| utm.interpolate(t).and_then(|(_, s)| s);
        let max = self.config.max_offset_ms;
        let est = match self.last {
            // Once determined, only near the last estimate (cheap); the whole range again
            // when the estimate runs to the bracket's edge.
            Some(l) => {
                let half = (10.0 * l.sigma_ms).clamp(20.0, max);
                let (lo, hi) = ((l.offset_ms - half).max(-max), (l.offset_ms + half).min(max));
                match estimate_within(&self.points, stroke, lo, hi) {
                    Some(e) if (e.offset_ms - lo).min(hi - e.offset_ms) > 0.1 * half => Some(e),
                    _ => estimate(&self.points, stroke, max),
                }
            }
            None => estimate(&self.points, stroke, max),
        }?;
        self.last = Some(est);
        let big = est.offset_ms.abs() > self.config.warn_ms && est.offset_ms.abs() > 3.0 * est.sigma_ms;
        if big && self.warned_at.is_none_or(|w| (w - est.offset_ms).abs() > self.config.warn_ms) {
            self.warned_at = Some(est.offset_ms);
            tracing::warn!(
                offset_ms = est.offset_ms,
                sigma_ms = est.sigma_ms,
                "the UTM clock is {:.1} ± {:.1} ms {} the cameras' clock: the feed's load and stroke belong to frames {:.1} ms {}",
                est.offset_ms.abs(),
                est.sigma_ms,
                if est.offset_ms > 0.0 { "ahead of" } else { "behind" },
                est.offset_ms.abs(),
                if est.offset_ms > 0.0 { "earlier" } else { "later" },
            );
        }
        Some(est.to_feed())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn recovers_a_shift_of_a_ramp_from_rest() {
        // Deflection: rest, then 2 mm/s; stroke = 1.1 × deflection + 0.3, stamped 37 ms ahead.
        let truth = |t_s: f64| 2.0 * (t_s - 0.5).max(0.0);
        let offset_ms = 37.0;
        let stroke: Vec<(i64, f64)> =
            (0..250).map(|j| j as f64 * 0.02 - 0.5).map(|t| (((t + offset_ms / 1e3) * 1e9) as i64, 1.1 * truth(t) + 0.3)).collect();
        let mut seed = 1u64;
        let mut noise = || {
            seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((seed >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * 0.01
        };
        let points: Vec<(i64, f64)> = (0..40).map(|k| k as f64 * 0.1).map(|t| ((t * 1e9) as i64, truth(t) + noise())).collect();
        let est = estimate(&points, |t| interpolate(&stroke, t), 500.0).expect("determined");
        assert!((est.offset_ms - offset_ms).abs() < 4.0 * est.sigma_ms + 0.5, "{est:?}");
        assert!(est.sigma_ms < 10.0, "{est:?}");
        // No motion: not determined.
        let flat: Vec<(i64, f64)> = (0..40).map(|k| (k * 100_000_000, noise())).collect();
        assert!(estimate(&flat, |t| interpolate(&stroke, t), 500.0).is_none());
    }
}
