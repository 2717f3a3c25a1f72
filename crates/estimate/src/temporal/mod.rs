//! Temporal estimation of each specimen tag's centre over frame sets (`[measure] estimator =
//! "temporal"`, the default; `"per_set"` solves every frame set on its own).
//!
//! Why: a frame set that lacks a camera is solved from what is left, and a tag seen by one
//! camera only is located poorly along that camera's line of sight; its camera-pose error is
//! also that one camera's instead of the average of all. Solved on its own, such a set throws
//! the net deflection by a fraction of a millimetre. A beam under load moves slowly and
//! smoothly (but for the jump of a first crack), so each tag's state is carried from set to
//! set and every set's views update what they observe.
//!
//! Model (per tag, an interacting multiple model of two linear Kalman filters on 6 states):
//! the tag's centre `p` (mm, world) and its rate `ṗ` (mm/s), white-noise acceleration of
//! spectral density `q` ([`TemporalConfig::accel_mm_s2`]² per second) in the *changing*
//! model and [`STEADY_SHARE`] of it in the *steady* one (a tag at rest or at a constant
//! rate: the held beam, a steady ramp). The models switch with a chance of
//! `SWITCH_PER_S` per second; each set's centre weighs them by its likelihood under
//! their predictions, and the output is their moment-matched mixture (mean and covariance,
//! the spread of the means included). Why two: one density must choose between noise at
//! rest and following a change of rate; the changing model alone left 0.53–0.61× of the
//! raw noise at rest on rendered scenes, the mixture 0.30–0.46× once settled
//! (docs/control.md), while a change of rate is followed as by the changing model alone. Each frame set's multi-view
//! (or single-view) solve is the measurement `z = p + v`:
//!
//! * `v`'s covariance is the solve's pixel-noise covariance while the tag is seen by as many
//!   cameras as usual (the held camera poses' errors are then common to every set and cancel
//!   from displacements), and its full covariance, camera poses included, when fewer cameras
//!   see it (a partial set: the camera-pose part is no longer the same, and a monocular
//!   view's line-of-sight uncertainty is large), so such a set moves the state only along
//!   what its views observe well.
//! * Adaptive process noise (each model its own): the normalised innovation squared (NIS)
//!   of full sets is averaged; while it stays above its expectation the process noise is
//!   scaled up (a rate change the model did not expect is followed within a few sets), and
//!   it relaxes back.
//! * A jump (a first crack, a bump of the specimen): a full set's innovation beyond the
//!   χ² gate widens the predicted position covariance by the innovation itself, so the state
//!   moves to the measurement at once without throwing the rate. A partial set's innovation
//!   beyond the gate is down-weighted instead (its depth is the suspect).
//! * The noise the filter is told and the noise a set has: the stated pixel-noise
//!   covariance comes from the corner residuals, and on a coarse render most of that residual
//!   is the same in every set (a bias that cancels from displacements): on a 480×360, 5-fps
//!   recording it stated σ_z ≈ 94 µm for a tag whose set-to-set noise was 4.9 µm, and a
//!   sudden ramp from rest (25, then 100 µm a set) scored NIS 0.06–11.7, under both tests, so
//!   the estimate fell behind by up to 0.3 mm (docs/report.md). Each tag therefore learns the
//!   ratio of its set-to-set noise to the stated one from its centres' second differences
//!   ([`noise_scale`]: over 10 s, robust to a change of rate, taken at 1.5× its value, never
//!   above 1). That ratio is used for three things only: a full set's surprise and jump
//!   tests (its NIS divided by the ratio: prediction and noise scaled together, since a
//!   filter's gains do not change when both are, its covariance does); the widening that
//!   follows a detected change (the innovation, in the set's real units); and the weighting
//!   of full sets for 1 s (`FOLLOW_S`) after a detected change (the stated
//!   covariance times the ratio, so the rate is learned from what the sets really say). When
//!   that second ends the state's covariance is put back into the stated units (divided by
//!   the ratio) and sets are weighed by the stated covariance again: at rest the weighting,
//!   hence the smoothing, is the stated one as before. Why not scale the stated covariance
//!   always: that is a filter whose process noise is 1/ratio times larger, and it lost the
//!   smoothing at rest (net deflection RMS over the rest sets 5.4 → 7.2 µm on that recording)
//!   and the steady model's hold of a tag at rest. Told the noise as it is, the ratio stays 1
//!   and the filter is the one it was.
//!
//! σ: the posterior covariance of `p` (pixel noise; the caller adds the camera-pose part for
//! the feed's absolute `sigma_mm`). A fixed-interval Rauch–Tung–Striebel smoother over a
//! stored run ([`smooth`]) gives the replay's and the report's best estimate; it runs on the
//! mixture's moments (each step's combined prediction and posterior), the usual
//! approximation of smoothing an interacting multiple model by one Gaussian.

mod mode;
pub mod noise_scale;

use mode::{combine, Mode};
use nalgebra::{Matrix3, Matrix6, Vector3, Vector6};
use noise_scale::NoiseScale;

/// Which estimator turns frame sets into positions (`[measure] estimator`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
///
/// The default is `Temporal` (since 2026-12-03): with partial sets referred to the full sets
/// (`estimate::partial`) and the rate's changes followed at once, it is as accurate as the
/// per-set solve on full sets of simulated scenes (hard scene: displacement RMS 0.0146 against
/// 0.0157 mm; moderate noise: net deflection 2.9 against 3.5 µm; at the start of loading it
/// lags by a few µm for a few sets: 5.0 against 4.6 µm on a slow ramp) and 6× better on sets
/// that lack cameras (docs/control.md).
pub enum Estimator {
    /// Each tag's state carried over frame sets (this module).
    #[default]
    Temporal,
    /// Every frame set solved on its own (monocular views fused with the recent
    /// multi-view history, `solve::motion`).
    PerSet,
}

/// Options of the temporal estimator.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TemporalConfig {
    /// Expected size (1 σ) of the unmodelled change of a tag's rate while it changes, mm/s
    /// per √s (the changing model's white-noise acceleration density is its square; the
    /// steady model's [`STEADY_SHARE`] of it).
    pub accel_mm_s2: f64,
    /// Most the adaptive scale may raise the process noise's density.
    pub max_adapt: f64,
}

impl Default for TemporalConfig {
    fn default() -> Self {
        Self { accel_mm_s2: DEFAULT_ACCEL_MM_S2, max_adapt: 1e4 }
    }
}

/// Default `[measure] temporal_accel_mm_s2`.
pub const DEFAULT_ACCEL_MM_S2: f64 = 0.02;

/// Squared Mahalanobis distance (3 d.o.f.) beyond which an innovation is a jump (full set)
/// or suspect (partial set): χ²₃ at 99.9 %.
const GATE: f64 = 16.3;
/// A full set's NIS / 3 above this (NIS > 12: 0.7 % by chance) raises the process noise
/// at once (see [`TagFilter::update`]).
const SURPRISE: f64 = 4.0;
/// Weight of the newest full set in the running NIS average.
const NIS_WEIGHT: f64 = 0.25;
/// A tag not updated for this long starts afresh, ns.
const RESTART_NS: i64 = 5_000_000_000;
/// Share of the configured process-noise density the steady model assumes (a tag at rest or
/// moving at a constant rate: the held beam, a steady ramp).
pub const STEADY_SHARE: f64 = 0.01;
/// Chance per second that a tag switches between steady and changing motion (each way).
const SWITCH_PER_S: f64 = 0.5;
/// The models' probabilities when a filter starts: steady, changing.
const START_MU: [f64; 2] = [0.5, 0.5];
/// Sets over which the usual number of views of a tag is remembered.
const VIEWS_MEMORY: u32 = 50;

type M6 = Matrix6<f64>;
type V6 = Vector6<f64>;

/// The usual number of cameras that see a tag: the most seen lately (forgotten after
/// [`VIEWS_MEMORY`] sets with fewer, so a camera lost for good stops making every set partial).
#[derive(Debug, Clone, Copy, Default)]
pub struct UsualViews {
    usual: usize,
    since: u32,
}

impl UsualViews {
    /// Counts a set that saw the tag with `views` cameras; true when that is fewer than usual.
    pub fn observe(&mut self, views: usize) -> bool {
        if views >= self.usual {
            self.usual = views;
            self.since = 0;
            return false;
        }
        self.since += 1;
        if self.since > VIEWS_MEMORY {
            self.usual = views;
            self.since = 0;
            return false;
        }
        true
    }
}

/// One filter step as stored for the smoother.
#[derive(Debug, Clone, Copy)]
pub struct Step {
    /// Time of the set, ns.
    pub t_ns: i64,
    /// Predicted state and covariance (before the update).
    pub x_pred: V6,
    /// Predicted covariance.
    pub p_pred: M6,
    /// Filtered state (after the update).
    pub x: V6,
    /// Filtered covariance.
    pub p: M6,
    /// Transition from the previous step to this one.
    pub f: M6,
    /// The filter started afresh here: no transition links it to the step before.
    pub restart: bool,
}

/// What one update did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Update {
    /// Filtered centre, mm.
    pub centre: Vector3<f64>,
    /// Its covariance (pixel noise only), mm².
    pub covariance: Matrix3<f64>,
    /// Filtered rate, mm/s.
    pub rate: Vector3<f64>,
    /// The set saw the tag with fewer cameras than usual.
    pub partial: bool,
    /// The innovation was taken as a jump of the tag.
    pub jump: bool,
}

/// The temporal filter of one tag (see the module docs): an interacting multiple model of
/// two constant-velocity filters, the *steady* one ([`STEADY_SHARE`] of the density) and the
/// *changing* one (the configured density), mixed by how well each predicted the sets.
#[derive(Debug, Clone)]
pub struct TagFilter {
    config: TemporalConfig,
    t_ns: i64,
    /// The steady and the changing model.
    modes: [Mode; 2],
    /// Their probabilities.
    mu: [f64; 2],
    /// The combined state and covariance.
    x: V6,
    p: M6,
    /// The steps so far, when kept for the smoother.
    history: Option<Vec<Step>>,
    /// The latest step (for a fixed-lag smoother outside, `estimate::smooth`).
    last: Step,
    /// The learned set-to-set scale of the full sets' noise.
    noise: NoiseScale,
}

impl TagFilter {
    /// A filter started at a first measurement (`cov`: its pixel-noise covariance).
    pub fn new(config: TemporalConfig, t_ns: i64, centre: Vector3<f64>, cov: &Matrix3<f64>) -> TagFilter {
        let blank =
            Step { t_ns, x_pred: V6::zeros(), p_pred: M6::zeros(), x: V6::zeros(), p: M6::zeros(), f: M6::identity(), restart: true };
        let mode = Mode::new(1.0, V6::zeros(), M6::zeros());
        let mut f = TagFilter {
            config,
            t_ns,
            modes: [mode; 2],
            mu: [0.5; 2],
            x: V6::zeros(),
            p: M6::zeros(),
            history: None,
            last: blank,
            noise: NoiseScale::default(),
        };
        f.start(t_ns, centre, cov);
        f
    }

    /// Keeps every step for [`smooth`].
    pub fn keep_history(mut self) -> Self {
        self.history = Some(vec![self.last]);
        self
    }

    /// The stored steps (when kept).
    pub fn history(&self) -> &[Step] {
        self.history.as_deref().unwrap_or(&[])
    }

    fn start(&mut self, t_ns: i64, centre: Vector3<f64>, cov: &Matrix3<f64>) {
        self.t_ns = t_ns;
        self.x = V6::zeros();
        self.x.fixed_rows_mut::<3>(0).copy_from(&centre);
        self.p = M6::zeros();
        self.p.fixed_view_mut::<3, 3>(0, 0).copy_from(cov);
        // The rate is unknown at start: a few mm/s (a beam in a test moves far less).
        self.p.fixed_view_mut::<3, 3>(3, 3).copy_from(&(Matrix3::identity() * 1.0));
        self.modes = [Mode::new(STEADY_SHARE, self.x, self.p), Mode::new(1.0, self.x, self.p)];
        self.mu = START_MU;
        self.noise.reset();
        self.last = Step { t_ns, x_pred: self.x, p_pred: self.p, x: self.x, p: self.p, f: M6::identity(), restart: true };
        if let Some(h) = self.history.as_mut() {
            h.push(self.last);
        }
    }

    /// The latest step: the one the last [`update`](Self::update) (or the start) made.
    pub fn last_step(&self) -> &Step {
        &self.last
    }

    /// The state's time, ns.
    pub fn t_ns(&self) -> i64 {
        self.t_ns
    }

    /// Filtered centre (mm) and rate (mm/s) now.
    pub fn centre(&self) -> Vector3<f64> {
        self.x.fixed_rows::<3>(0).into_owned()
    }

    /// Filtered rate, mm/s.
    pub fn rate(&self) -> Vector3<f64> {
        self.x.fixed_rows::<3>(3).into_owned()
    }

    /// Covariance of the centre, mm².
    pub fn covariance(&self) -> Matrix3<f64> {
        self.p.fixed_view::<3, 3>(0, 0).into_owned()
    }

    /// Centre and covariance predicted at `t_ns` (for a set that did not see the tag).
    pub fn predict_at(&self, t_ns: i64) -> (Vector3<f64>, Matrix3<f64>) {
        let (f, dt) = self.transition(t_ns);
        let pred = self.modes.map(|m| (f * m.x, f * m.p * f.transpose() + m.process_noise(&self.config, dt)));
        let (x, p) = combine(self.mu.iter().zip(&pred).map(|(w, (x, p))| (*w, x, p)));
        (x.fixed_rows::<3>(0).into_owned(), p.fixed_view::<3, 3>(0, 0).into_owned())
    }

    /// The current adaptive scale of the changing model's process noise (1 = the configured
    /// density).
    pub fn adaptive_scale(&self) -> f64 {
        self.modes[1].adapt
    }

    /// The learned set-to-set scale of the full sets' noise against the stated (a variance
    /// ratio, see [`noise_scale`]).
    pub fn noise_scale(&self) -> f64 {
        self.noise.scale()
    }

    /// The probability that the tag moves steadily (at rest or at a constant rate) rather
    /// than changing its rate.
    pub fn steady_probability(&self) -> f64 {
        self.mu[0]
    }

    /// The transition to `t_ns` and its interval, s.
    fn transition(&self, t_ns: i64) -> (M6, f64) {
        let dt = ((t_ns - self.t_ns) as f64 * 1e-9).max(0.0);
        let mut f = M6::identity();
        f.fixed_view_mut::<3, 3>(0, 3).copy_from(&(Matrix3::identity() * dt));
        (f, dt)
    }

    /// Updates the state with one set's solve of the tag: `centre` with its pixel-noise
    /// covariance `noise_cov` and its full covariance `full_cov` (camera poses included);
    /// `partial` when fewer cameras than usual saw the tag (see [`UsualViews`]).
    ///
    /// Each model is mixed from both by the chance of a switch over the interval, predicts,
    /// and is updated as one filter would be (the jump and the adaptation of the module docs,
    /// each model its own); the models' probabilities follow the likelihood of the set's
    /// centre under their predictions, and the output is their moment-matched mixture.
    pub fn update(&mut self, t_ns: i64, centre: Vector3<f64>, noise_cov: &Matrix3<f64>, full_cov: &Matrix3<f64>, partial: bool) -> Update {
        if t_ns - self.t_ns > RESTART_NS || t_ns < self.t_ns {
            self.start(t_ns, centre, if partial { full_cov } else { noise_cov });
            return self.result(partial, false);
        }
        let (f, dt) = self.transition(t_ns);
        // Mixing: the chance of a switch over the interval.
        let switch = 1.0 - (-SWITCH_PER_S * dt).exp();
        let stay = 1.0 - switch;
        let c = [stay * self.mu[0] + switch * self.mu[1], switch * self.mu[0] + stay * self.mu[1]];
        let mut modes = self.modes;
        for (j, mode) in modes.iter_mut().enumerate() {
            if c[j] <= 0.0 {
                continue;
            }
            let w = |i: usize| if i == j { stay } else { switch } * self.mu[i] / c[j];
            let (x0, p0) = combine((0..2).map(|i| (w(i), &self.modes[i].x, &self.modes[i].p)));
            mode.x = x0;
            mode.p = p0;
        }
        // Per tag and frame set: fixed-size arrays, no allocation.
        let [m0, m1] = &mut modes;
        let scale = self.noise.scale();
        let update = |m: &mut Mode| m.update(&self.config, &f, dt, centre, noise_cov, full_cov, partial, scale);
        let (Some(s0), Some(s1)) = (update(m0), update(m1)) else {
            return self.result(partial, false);
        };
        let steps = [s0, s1];
        let best = steps[0].log_likelihood.max(steps[1].log_likelihood);
        let weights = [0, 1].map(|j| c[j] * (steps[j].log_likelihood - best).exp());
        let total = weights[0] + weights[1];
        if !(total > 0.0 && total.is_finite()) {
            return self.result(partial, false);
        }
        self.mu = [weights[0] / total, weights[1] / total];
        if !partial {
            self.noise.observe(t_ns, centre, noise_cov);
        }
        self.modes = modes;
        let (x, p) = combine(self.mu.iter().zip(&self.modes).map(|(w, m)| (*w, &m.x, &m.p)));
        let (x_pred, p_pred) = combine(c.iter().zip(&steps).map(|(w, s)| (*w, &s.x_pred, &s.p_pred)));
        let jump = steps.iter().any(|s| s.jump);
        self.x = x;
        self.p = p;
        self.t_ns = t_ns;
        self.last = Step { t_ns, x_pred, p_pred, x: self.x, p: self.p, f, restart: false };
        if let Some(hist) = self.history.as_mut() {
            hist.push(self.last);
        }
        self.result(partial, jump)
    }

    fn result(&self, partial: bool, jump: bool) -> Update {
        Update { centre: self.centre(), covariance: self.covariance(), rate: self.rate(), partial, jump }
    }
}

/// Fixed-interval Rauch–Tung–Striebel smoothing of a filter's stored steps: each step's
/// smoothed centre and its covariance (mm, mm²), in step order.
pub fn smooth(steps: &[Step]) -> Vec<(i64, Vector3<f64>, Matrix3<f64>)> {
    let n = steps.len();
    if n == 0 {
        return Vec::new();
    }
    let mut xs: Vec<V6> = steps.iter().map(|s| s.x).collect();
    let mut ps: Vec<M6> = steps.iter().map(|s| s.p).collect();
    for k in (0..n - 1).rev() {
        let next = &steps[k + 1];
        if next.restart {
            continue;
        }
        let Some(pp_inv) = next.p_pred.try_inverse() else { continue };
        let c = steps[k].p * next.f.transpose() * pp_inv;
        xs[k] = steps[k].x + c * (xs[k + 1] - next.x_pred);
        let p = steps[k].p + c * (ps[k + 1] - next.p_pred) * c.transpose();
        ps[k] = (p + p.transpose()) * 0.5;
    }
    steps
        .iter()
        .zip(xs.iter().zip(&ps))
        .map(|(s, (x, p))| (s.t_ns, x.fixed_rows::<3>(0).into_owned(), p.fixed_view::<3, 3>(0, 0).into_owned()))
        .collect()
}

#[cfg(test)]
mod tests;
