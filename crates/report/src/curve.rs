//! The load–deflection (or load–CMOD) curve and the numerical steps every standard uses:
//! smoothing over time, the first crossing of a deflection, interpolation with its σ, the
//! area under the curve with its σ, and the first peak.
//!
//! **Smoothing.** Deflection (or CMOD) `x` is smoothed over time by a moving local-linear
//! least-squares fit of `m` points (`smooth_points`, odd; 1 = none): `x̃ᵢ = Σⱼ wᵢⱼ xⱼ`. A
//! straight ramp passes unchanged; the σ of `x̃ᵢ` is propagated from the feed's σ,
//! `σ²(x̃ᵢ) = Σⱼ wᵢⱼ² σⱼ² + σ_ref²`, where `σ_ref` (the uncertainty of the zero reference,
//! common to every point) is not reduced by smoothing.
//!
//! **Where the curve bends, the window shrinks.** A straight line fitted across a kink (the
//! start of loading after rest, a deflection jump at a crack) is biased: on a simulated C1609
//! test of 28 frame sets the 5-point fit put the start of loading 33 µm late and lost 1.3 J
//! (2.6 %) of T150. Each point's window is therefore chosen by the intersection-of-
//! confidence-intervals rule (Goldenshluger & Nemirovski 1997; Katkovnik 1999): the fits of
//! 1, 3, 5, … up to `m` points are made in turn, each with its interval `x̃ ± Γσ(x̃)` (Γ = 2,
//! σ from the feed's σ), and the widest window whose interval still meets all narrower ones'
//! is used. On a straight or gently curved stretch that is `m` (a difference of 2.9 σ between
//! the 1- and 5-point fits is needed to shrink, about 0.1 % of points on noise alone); at a
//! kink the bias shows and the window falls to 3 or 1, where the fit is unbiased. With σ = 0
//! (a truth curve) only exactly collinear points are smoothed.
//!
//! Within a window the line is fitted by weighted least squares, each point weighted by
//! 1/σ² of its own σ: a frame set that lacked a camera (its σ large) pulls the smoothed
//! curve little, while with equal σ the fit is the plain one.
//!
//! The load is not smoothed for values;
//! its σ per reading is `√(noise² + resolution²/12)`, the noise estimated robustly from the
//! data (below).
//!
//! **Noise estimate.** For each interior point the deviation from the straight line through
//! its two neighbours (in time), normalised to unit variance for white noise; σ̂ = 1.4826 ·
//! median absolute deviation. Ramps cancel; sharp corners are outliers the median ignores.

use crate::load_spikes::{robust_noise, LoadSpikes};

/// A curve in time order: load against `x` (net deflection or CMOD), with σ.
#[derive(Debug, Clone, PartialEq)]
pub struct Curve {
    /// Times, ns since the Unix epoch.
    pub t_ns: Vec<i64>,
    /// Seconds since the first point.
    pub t_s: Vec<f64>,
    /// Load, kN.
    pub load: Vec<f64>,
    /// `x` as read, mm.
    pub x: Vec<f64>,
    /// σ of each `x` reading (random part), mm.
    pub sx: Vec<f64>,
    /// σ of the zero reference, common to all points, mm.
    pub x_ref_sigma: f64,
    /// `x` smoothed over time, mm.
    pub xs: Vec<f64>,
    /// σ of `xs` (including `x_ref_sigma`), mm.
    pub sxs: Vec<f64>,
    /// σ of one load reading, kN.
    pub load_sigma: f64,
    /// Robust scatter of the load about a local line, kN.
    pub load_noise: f64,
    /// Robust scatter of `x` about a local line, mm.
    pub x_noise: f64,
    /// Smoothing window, points (the largest; see the module docs for where it shrinks).
    pub smooth_points: usize,
    /// Points whose smoothing window was shrunk below `smooth_points` because the wider
    /// fit's bias showed (a kink: the start of loading, a crack's jump).
    pub smooth_reduced: usize,
    /// Points over which the errors of `xs` are correlated (the smoothing window, in this
    /// curve's points): the random part of an area's σ is scaled by its square root.
    pub x_corr_points: f64,
    /// Sampling period of the load, s (median step of `t_s`).
    pub load_period_s: f64,
    /// True when the load comes from the UTM's own samples (`utm.jsonl`), false when it is the
    /// feed's load sampled at the frame rate.
    pub load_from_utm: bool,
    /// Load readings left out as glitches (`(t_ns, load_kN)`): a jump no machine makes within
    /// one sample and back ([`crate::load_spikes`]).
    pub load_outliers: Vec<(i64, f64)>,
}

/// Errors building a curve.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CurveError {
    /// Fewer than two usable points.
    #[error("the curve has {0} point(s) with both load and {1}: at least 2 are needed")]
    TooShort(usize, &'static str),
    /// Input of different lengths or not finite.
    #[error("curve input: {0}")]
    Input(String),
}

impl Curve {
    /// Builds a curve from points in time order. `sx[i] = None` means the feed gave no σ
    /// for that point: the robust scatter of `x` is used instead.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        t_ns: Vec<i64>,
        load: Vec<f64>,
        x: Vec<f64>,
        sx: Vec<Option<f64>>,
        x_ref_sigma: f64,
        smooth_points: usize,
        load_resolution: f64,
        what: &'static str,
    ) -> Result<Curve, CurveError> {
        let n = t_ns.len();
        if load.len() != n || x.len() != n || sx.len() != n {
            return Err(CurveError::Input("columns of different lengths".into()));
        }
        if n < 2 {
            return Err(CurveError::TooShort(n, what));
        }
        if load.iter().chain(&x).any(|v| !v.is_finite()) {
            return Err(CurveError::Input("a load or x value is not finite".into()));
        }
        let spikes = LoadSpikes::find(&load);
        let load_outliers = spikes.readings(&t_ns, &load);
        let (t_ns, load, x, sx) = (spikes.without(t_ns), spikes.without(load), spikes.without(x), spikes.without(sx));
        let n = t_ns.len();
        if n < 2 {
            return Err(CurveError::TooShort(n, what));
        }
        let t0 = t_ns[0];
        let t_s: Vec<f64> = t_ns.iter().map(|&t| (t - t0) as f64 * 1e-9).collect();
        let x_noise = robust_noise(&t_s, &x);
        let load_noise = robust_noise(&t_s, &load);
        let sx: Vec<f64> = sx.into_iter().map(|s| s.filter(|v| v.is_finite() && *v >= 0.0).unwrap_or(x_noise)).collect();
        let m = smooth_points.max(1);
        let mut xs = Vec::with_capacity(n);
        let mut sxs = Vec::with_capacity(n);
        let mut smooth_reduced = 0;
        for i in 0..n {
            let (v, var, used) = smooth_at(&t_s, &x, &sx, i, m);
            xs.push(v);
            sxs.push((var + x_ref_sigma * x_ref_sigma).sqrt());
            smooth_reduced += usize::from(used < m.min(n));
        }
        let load_sigma = (load_noise * load_noise + load_resolution * load_resolution / 12.0).sqrt();
        let load_period_s = median_step(&t_s);
        Ok(Curve {
            t_ns,
            t_s,
            load,
            x,
            sx,
            x_ref_sigma,
            xs,
            sxs,
            load_sigma,
            load_noise,
            x_noise,
            smooth_points: m,
            smooth_reduced,
            x_corr_points: m as f64,
            load_period_s,
            load_from_utm: false,
            load_outliers,
        })
    }

    /// The curve on the UTM's own samples: one point per sample (UTM clock minus `offset_ns`
    /// = camera clock) inside this curve's time span, with this curve's smoothed `x` and its σ
    /// interpolated linearly at the sample's time. A sample between two points further apart
    /// than `max_gap_s` gets no point (nothing is invented across a gap). The σ of the time
    /// alignment `sigma_t_s` adds `|dx/dt|·σ_t` to every point's σ.
    pub fn on_utm(
        &self,
        utm: &[tagdeflect_core::utm_sample::UtmSample],
        offset_ns: i64,
        sigma_t_s: f64,
        load_resolution: f64,
        max_gap_s: f64,
    ) -> Result<Curve, CurveError> {
        let n = self.len();
        let (first, last) = (self.t_ns[0], self.t_ns[n - 1]);
        let max_gap_ns = (max_gap_s * 1e9).min(i64::MAX as f64) as i64;
        let (mut t_ns, mut load, mut x, mut sx, mut sxs) = (vec![], vec![], vec![], vec![], vec![]);
        let ref2 = self.x_ref_sigma * self.x_ref_sigma;
        for s in utm {
            let tc = s.t_ns.saturating_sub(offset_ns);
            if tc < first || tc > last {
                continue;
            }
            let i = self.t_ns.partition_point(|&t| t < tc);
            let (v, sig, rate) = if self.t_ns[i] == tc || i == 0 {
                let rate = if i + 1 < n { (self.xs[i + 1] - self.xs[i]) / (self.t_s[i + 1] - self.t_s[i]).max(1e-12) } else { 0.0 };
                (self.xs[i], self.sxs[i], rate)
            } else {
                let (a, b) = (i - 1, i);
                if self.t_ns[b] - self.t_ns[a] > max_gap_ns {
                    continue;
                }
                let w = (tc - self.t_ns[a]) as f64 / (self.t_ns[b] - self.t_ns[a]) as f64;
                let dt = self.t_s[b] - self.t_s[a];
                (
                    self.xs[a] + w * (self.xs[b] - self.xs[a]),
                    self.sxs[a] + w * (self.sxs[b] - self.sxs[a]),
                    (self.xs[b] - self.xs[a]) / dt.max(1e-12),
                )
            };
            let st = rate.abs() * sigma_t_s;
            t_ns.push(tc);
            load.push(s.load_kn);
            x.push(v);
            sx.push(((sig * sig - ref2).max(0.0) + st * st).sqrt());
            sxs.push((sig * sig + st * st).sqrt());
        }
        let spikes = LoadSpikes::find(&load);
        let load_outliers = spikes.readings(&t_ns, &load);
        let (t_ns, load, x, sx, sxs) =
            (spikes.without(t_ns), spikes.without(load), spikes.without(x), spikes.without(sx), spikes.without(sxs));
        if t_ns.len() < 2 {
            return Err(CurveError::TooShort(t_ns.len(), "UTM samples within the feed's time"));
        }
        let t0 = t_ns[0];
        let t_s: Vec<f64> = t_ns.iter().map(|&t| (t - t0) as f64 * 1e-9).collect();
        let load_noise = robust_noise(&t_s, &load);
        let load_sigma = (load_noise * load_noise + load_resolution * load_resolution / 12.0).sqrt();
        let load_period_s = median_step(&t_s);
        let per_feed_point = (self.load_period_s / load_period_s.max(1e-12)).max(1.0);
        Ok(Curve {
            xs: x.clone(),
            t_ns,
            t_s,
            load,
            x,
            sx,
            x_ref_sigma: self.x_ref_sigma,
            sxs,
            load_sigma,
            load_noise,
            x_noise: self.x_noise,
            smooth_points: self.smooth_points,
            smooth_reduced: self.smooth_reduced,
            x_corr_points: self.x_corr_points * per_feed_point,
            load_period_s,
            load_from_utm: true,
            load_outliers,
        })
    }

    /// σ of a peak read from samples: the true peak lies between the sample taken and the
    /// next, missed by up to the rise over one sampling period `r`; the RMS of such a
    /// one-sided error is `r/√3`. `r` is the mean rise per sample over the (up to)
    /// `max(smooth_points, 5)` samples before the peak, so that one noisy reading does not
    /// make it.
    pub(crate) fn peak_sampling_sigma(&self, j: usize) -> f64 {
        let m = self.smooth_points.max(5).min(j);
        if m == 0 {
            return 0.0;
        }
        ((self.load[j] - self.load[j - m]) / m as f64).max(0.0) / 3f64.sqrt()
    }

    /// Number of points.
    pub(crate) fn len(&self) -> usize {
        self.load.len()
    }

    /// Index of the largest load (the first one if several are equal).
    pub(crate) fn peak_index(&self) -> usize {
        let mut k = 0;
        for (i, &p) in self.load.iter().enumerate() {
            if p > self.load[k] {
                k = i;
            }
        }
        k
    }

    /// The load smoothed like `x` (local-linear fit over time): used to find the first peak.
    fn smoothed_load(&self) -> Vec<f64> {
        let n = self.len();
        (0..n)
            .map(|i| {
                let (lo, hi) = window(i, n, self.smooth_points);
                let w = fit_weights(&self.t_s[lo..hi], self.t_s[i]);
                w.iter().zip(&self.load[lo..hi]).map(|(w, v)| w * v).sum()
            })
            .collect()
    }

    /// The first point where smoothed `x` reaches `target`: `(i, f)` with the crossing
    /// between points `i - 1` and `i` at fraction `f` (`(0, 0.0)` when the first point is
    /// there). `None` when `x` never gets there, or when the curve starts beyond it (the
    /// crossing was not measured).
    pub(crate) fn crossing(&self, target: f64) -> Option<(usize, f64)> {
        if self.xs[0] == target {
            return Some((0, 0.0));
        }
        if self.xs[0] > target {
            return None;
        }
        (1..self.len()).find(|&i| self.xs[i] >= target).map(|i| {
            let (a, b) = (self.xs[i - 1], self.xs[i]);
            (i, if b > a { ((target - a) / (b - a)).clamp(0.0, 1.0) } else { 1.0 })
        })
    }

    /// Why `target` (called `what`) has no crossing: the curve starts beyond it, or never
    /// gets there.
    pub(crate) fn not_reached(&self, what: &str, target: f64) -> String {
        let max = self.xs.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
        if self.xs[0] > target {
            format!("the curve starts at {:.3} mm, beyond {what}: that point was not measured", self.xs[0])
        } else {
            format!("the curve never reached {what} (largest: {max:.3} mm)")
        }
    }

    /// A column's value at a crossing, interpolated linearly.
    fn at(v: &[f64], (i, f): (usize, f64)) -> f64 {
        if i == 0 {
            v[0]
        } else {
            v[i - 1] + f * (v[i] - v[i - 1])
        }
    }

    /// Local slope dP/dx (kN/mm) around point `i`: least squares of load on smoothed `x`
    /// over a window of `max(smooth_points, 5)` points.
    fn local_slope(&self, i: usize) -> f64 {
        let n = self.len();
        let (lo, hi) = window(i.min(n - 1), n, self.smooth_points.max(5));
        let xs = &self.xs[lo..hi];
        let ps = &self.load[lo..hi];
        let k = xs.len() as f64;
        let mx = xs.iter().sum::<f64>() / k;
        let mp = ps.iter().sum::<f64>() / k;
        let sxx: f64 = xs.iter().map(|x| (x - mx) * (x - mx)).sum();
        let sxp: f64 = xs.iter().zip(ps).map(|(x, p)| (x - mx) * (p - mp)).sum();
        if sxx > 1e-18 {
            sxp / sxx
        } else {
            0.0
        }
    }

    /// The load where smoothed `x` first reaches `target`, with its σ, and the crossing.
    /// Interpolating between the bracketing points `i-1`, `i` at fraction `f`, first-order
    /// propagation gives `σ² = s²·((1−f)²σ²(x̃ᵢ₋₁) + f²σ²(x̃ᵢ)) + ((1−f)² + f²)·σ_load²`, with
    /// `s` the slope dP/dx there: the secant of the two points when they are more than 3σ
    /// apart in `x` (sparse points: the interpolation's own slope), else the local
    /// least-squares slope (dense, noisy points, where a secant would be noise).
    pub(crate) fn load_at(&self, target: f64) -> Option<(f64, f64, (usize, f64))> {
        let c = self.crossing(target)?;
        let p = Self::at(&self.load, c);
        let (i, f) = c;
        if i == 0 {
            let s = self.local_slope(0) * self.sxs[0];
            return Some((p, (s * s + self.load_sigma.powi(2)).sqrt(), c));
        }
        let (s0, s1) = (self.sxs[i - 1], self.sxs[i]);
        let dx = self.xs[i] - self.xs[i - 1];
        let slope = if dx > 3.0 * s0.max(s1) { (self.load[i] - self.load[i - 1]) / dx } else { self.local_slope(i) };
        // Neighbouring points of a smoothed (or interpolated) x are correlated: their σ combine
        // linearly.
        let var_x = ((1.0 - f) * s0 + f * s1).powi(2);
        let var_p = ((1.0 - f).powi(2) + f * f) * self.load_sigma.powi(2);
        Some((p, (slope * slope * var_x + var_p).sqrt(), c))
    }

    /// Area under load against smoothed `x` from the first point to where `x` first reaches
    /// `target` (trapezoids; kN·mm = J), with its σ from every point's σ of `x̃` and load
    /// (treated as independent) and the zero reference:
    /// `σ² = Σ (∂T/∂x̃ⱼ σ(x̃ⱼ))² + Σ (∂T/∂Pⱼ σ_P)² + ((P_end − P_0) σ_ref)²`.
    pub(crate) fn area_to(&self, target: f64) -> Option<(f64, f64)> {
        let (p_end, sp_end, c) = self.load_at(target)?;
        let (i, _) = c;
        // Points 0..i (exclusive of i), then the interpolated end at x = target.
        let mut xs: Vec<f64> = self.xs[..i].to_vec();
        let mut ps: Vec<f64> = self.load[..i].to_vec();
        let mut sx: Vec<f64> = self.sxs[..i].iter().map(|s| (s * s - self.x_ref_sigma.powi(2)).max(0.0).sqrt()).collect();
        let mut sp: Vec<f64> = vec![self.load_sigma; i];
        xs.push(target);
        ps.push(p_end);
        sx.push(0.0); // the end is at x = target by definition; its uncertainty is in sp_end
        sp.push(sp_end);
        let n = xs.len();
        if n < 2 {
            return Some((0.0, 0.0));
        }
        let mut area = 0.0;
        for j in 0..n - 1 {
            area += 0.5 * (ps[j] + ps[j + 1]) * (xs[j + 1] - xs[j]);
        }
        let mut var = 0.0;
        let mut var_x = 0.0;
        for j in 0..n {
            let d_dx = match j {
                0 => -0.5 * (ps[0] + ps[1]),
                j if j == n - 1 => 0.5 * (ps[n - 2] + ps[n - 1]),
                j => 0.5 * (ps[j - 1] - ps[j + 1]),
            };
            let d_dp = match j {
                0 => 0.5 * (xs[1] - xs[0]),
                j if j == n - 1 => 0.5 * (xs[n - 1] - xs[n - 2]),
                j => 0.5 * (xs[j + 1] - xs[j - 1]),
            };
            var_x += (d_dx * sx[j]).powi(2);
            var += (d_dp * sp[j]).powi(2);
        }
        // The errors of x̃ are correlated over `x_corr_points` points.
        var += var_x * self.x_corr_points.max(1.0);
        var += ((p_end - ps[0]) * self.x_ref_sigma).powi(2);
        Some((area, var.sqrt()))
    }

    /// The first peak: the first local maximum of the smoothed load after which the load
    /// falls by at least `drop` before it ever exceeds that maximum (the point where the
    /// slope of the curve becomes zero, robust to noise), among maxima above `floor`. The
    /// index returned is that of the largest *measured* load within the smoothing window
    /// around the smoothed maximum. `None` when the load never falls so.
    pub(crate) fn first_peak(&self, drop: f64, floor: f64) -> Option<usize> {
        let ps = self.smoothed_load();
        let mut best = f64::NEG_INFINITY;
        let mut k = 0;
        for (i, &p) in ps.iter().enumerate() {
            if p > best {
                best = p;
                k = i;
            } else if best >= floor && p <= best - drop {
                let (lo, hi) = window(k, self.len(), self.smooth_points);
                let j = (lo..hi).fold(lo, |a, b| if self.load[b] > self.load[a] { b } else { a });
                return Some(j);
            }
        }
        None
    }
}

/// Median step of increasing times, s (0 with fewer than 2).
fn median_step(t: &[f64]) -> f64 {
    if t.len() < 2 {
        return 0.0;
    }
    let mut d: Vec<f64> = t.windows(2).map(|w| w[1] - w[0]).collect();
    median(&mut d)
}

/// Multiplier of σ in the intervals of the window choice (module docs).
const ICI_GAMMA: f64 = 2.0;

/// The smoothed `x` at point `i` and its variance (random part), with the window chosen by
/// the intersection-of-confidence-intervals rule up to `m_max` points (module docs); also
/// the window used.
fn smooth_at(t: &[f64], x: &[f64], sx: &[f64], i: usize, m_max: usize) -> (f64, f64, usize) {
    let n = x.len();
    let (mut lower, mut upper) = (f64::NEG_INFINITY, f64::INFINITY);
    let mut best = (x[i], sx[i] * sx[i], 1);
    let mut m = 1;
    while m <= m_max.min(n) {
        let (lo, hi) = window(i, n, m);
        let w = fit_weights_sigma(&t[lo..hi], &sx[lo..hi], t[i]);
        let v: f64 = w.iter().zip(&x[lo..hi]).map(|(w, v)| w * v).sum();
        let var: f64 = w.iter().zip(&sx[lo..hi]).map(|(w, s)| w * w * s * s).sum();
        let half = ICI_GAMMA * var.sqrt();
        lower = lower.max(v - half);
        upper = upper.min(v + half);
        // 1 pm of slack: collinear points with σ = 0 differ by rounding only.
        if lower > upper + 1e-9 {
            break;
        }
        best = (v, var, m);
        m += 2;
    }
    best
}

/// Indices `lo..hi` of a window of `m` points centred on `i` (shifted inside `0..n`).
fn window(i: usize, n: usize, m: usize) -> (usize, usize) {
    let m = m.clamp(1, n.max(1));
    let lo = i.saturating_sub(m / 2).min(n - m);
    (lo, lo + m)
}

/// Weights `w` with `Σ w_j y_j` = the least-squares line through `(t_j, y_j)` evaluated at `at`.
fn fit_weights(t: &[f64], at: f64) -> Vec<f64> {
    let n = t.len() as f64;
    let mean = t.iter().sum::<f64>() / n;
    let s: f64 = t.iter().map(|v| (v - mean) * (v - mean)).sum();
    t.iter().map(|v| if s > 0.0 { 1.0 / n + (at - mean) * (v - mean) / s } else { 1.0 / n }).collect()
}

/// [`fit_weights`] of the line fitted by weighted least squares, each point weighted by
/// 1/σ² (a partial frame set, its σ large, moves the smoothed curve little). Equal σ give
/// the plain fit's weights; each σ counts at least half the window's median (a σ of 0 pins
/// nothing), a window of σ 0 (a truth curve) gets equal weights.
fn fit_weights_sigma(t: &[f64], s: &[f64], at: f64) -> Vec<f64> {
    let mut sorted = s.to_vec();
    let mid = median(&mut sorted);
    if mid <= 0.0 || !mid.is_finite() {
        return fit_weights(t, at);
    }
    // A point's σ counts at least half the window's median: a reference line's σ of 0 (or a
    // σ far below its neighbours') must not pin the line to it.
    let w: Vec<f64> = s.iter().map(|v| 1.0 / v.max(0.5 * mid).powi(2)).collect();
    let sw: f64 = w.iter().sum();
    // One time only (one point): its weight is 1 — the rounding of a weighted mean must not
    // make a slope of it.
    let span = t.iter().cloned().fold(f64::NEG_INFINITY, f64::max) - t.iter().cloned().fold(f64::INFINITY, f64::min);
    if span <= 0.0 {
        return w.iter().map(|w| w / sw).collect();
    }
    let tm = w.iter().zip(t).map(|(w, t)| w * t).sum::<f64>() / sw;
    let stt: f64 = w.iter().zip(t).map(|(w, t)| w * (t - tm) * (t - tm)).sum();
    w.iter().zip(t).map(|(w, t)| if stt > 0.0 { w / sw + (at - tm) * w * (t - tm) / stt } else { w / sw }).collect()
}

pub(crate) use tagdeflect_core::stats::median_in_place as median;

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_distr::{Distribution, StandardNormal};

    /// A ramp from rest (10 points at 0, then 0.1 mm per point) with σ = 3 µm noise.
    fn ramp_from_rest(seed: u64, sigma: f64) -> Curve {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let n = 60;
        let t: Vec<i64> = (0..n).map(|i| i as i64 * 100_000_000).collect();
        let truth: Vec<f64> = (0..n).map(|i| 0.1 * (i as f64 - 10.0).max(0.0)).collect();
        let x: Vec<f64> = truth
            .iter()
            .map(|v| {
                v + sigma * {
                    let z: f64 = StandardNormal.sample(&mut rng);
                    z
                }
            })
            .collect();
        Curve::new(t, truth.iter().map(|v| 100.0 * v).collect(), x, vec![Some(sigma); n], 0.0, 5, 0.0, "deflection").unwrap()
    }

    /// A point with a large σ and a large error (a partial frame set) in a straight ramp:
    /// weighted by 1/σ², its neighbours' smoothed values stay near the truth.
    #[test]
    fn a_point_with_a_large_sigma_pulls_the_smoothed_curve_little() {
        let n = 21;
        let t: Vec<i64> = (0..n).map(|i| i as i64 * 100_000_000).collect();
        let truth: Vec<f64> = (0..n).map(|i| 0.01 * i as f64).collect();
        let mut x = truth.clone();
        let mut sx = vec![Some(0.002); n];
        x[10] += 0.05; // 50 µm off, as a one-camera set can be
        sx[10] = Some(0.05);
        let c = Curve::new(t, truth.iter().map(|v| 100.0 * v).collect(), x, sx, 0.0, 5, 0.0, "deflection").unwrap();
        for i in [8, 9, 11, 12] {
            let e = c.xs[i] - truth[i];
            assert!(e.abs() < 0.0005, "point {i}: smoothed {} off by {e} mm", c.xs[i]);
        }
        // Unweighted, the 5-point line through it would put its neighbours 10 µm off.
        let (lo, hi) = window(9, n, 5);
        let plain: f64 = fit_weights(&c.t_s[lo..hi], c.t_s[9]).iter().zip(&c.x[lo..hi]).map(|(w, v)| w * v).sum();
        assert!((plain - truth[9]).abs() > 0.005, "the unweighted fit {plain}");
    }

    /// At the start of loading the fixed 5-point line is 20 µm off (σ 3 µm); the window
    /// chosen per point keeps every point within 3σ of its own σ there, and smooths the
    /// straight stretches with the full window.
    #[test]
    fn the_window_shrinks_at_a_kink_and_not_on_a_straight_ramp() {
        let mut worst = 0.0f64;
        let mut reduced = 0;
        for seed in 0..20 {
            let c = ramp_from_rest(seed, 0.003);
            for (i, (v, s)) in c.xs.iter().zip(&c.sxs).enumerate() {
                let truth = 0.1 * (i as f64 - 10.0).max(0.0);
                worst = worst.max((v - truth).abs() / s);
            }
            reduced += c.smooth_reduced;
            // The fixed window would put the kink's point (index 10) 0.2·0.1 mm = 20 µm high.
            let fixed = {
                let (lo, hi) = window(10, c.len(), 5);
                let w = fit_weights(&c.t_s[lo..hi], c.t_s[10]);
                w.iter().zip(&c.x[lo..hi]).map(|(w, v)| w * v).sum::<f64>()
            };
            assert!(fixed > 0.012, "seed {seed}: the fixed 5-point fit at the kink {fixed} mm (expected about 0.02)");
        }
        eprintln!(
            "ramp from rest, 20 seeds: worst smoothed point {worst:.2} σ from the truth, {reduced} of 1200 points with a reduced window"
        );
        assert!(worst < 3.5, "a smoothed point {worst:.2} σ from the truth");
        // Points near the kink (about 3 of 60) shrink; noise alone shrinks almost none.
        assert!((20..=100).contains(&reduced), "{reduced} points of 1200 with a reduced window");
        // With σ = 0 the exact ramp from rest is left exact.
        let c = ramp_from_rest(0, 0.0);
        for (i, v) in c.xs.iter().enumerate() {
            assert!((v - 0.1 * (i as f64 - 10.0).max(0.0)).abs() < 1e-9, "point {i}: {v}");
        }
    }
}
