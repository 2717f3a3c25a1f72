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
//!
//! σ: the posterior covariance of `p` (pixel noise; the caller adds the camera-pose part for
//! the feed's absolute `sigma_mm`). A fixed-interval Rauch–Tung–Striebel smoother over a
//! stored run ([`smooth`]) gives the replay's and the report's best estimate; it runs on the
//! mixture's moments (each step's combined prediction and posterior), the usual
//! approximation of smoothing an interacting multiple model by one Gaussian.

use nalgebra::{Matrix3, Matrix6, SMatrix, Vector3, Vector6};

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

/// One motion model's filter: the state, its covariance and the model's own adaptation
/// (see [`TagFilter`]: two of them, mixed).
#[derive(Debug, Clone, Copy)]
struct Mode {
    /// Share of the configured process-noise density this model assumes.
    density_share: f64,
    x: V6,
    p: M6,
    /// Adaptive scale of the process noise (≥ 1).
    adapt: f64,
    /// Running mean of the full sets' NIS / 3.
    nis: f64,
    /// The last full update was a jump.
    jumped_last: bool,
}

/// What one mode's update made of a set.
struct ModeStep {
    x_pred: V6,
    p_pred: M6,
    /// Log-likelihood of the set's centre under the mode's prediction (before any widening),
    /// up to a constant common to the modes.
    log_likelihood: f64,
    jump: bool,
}

impl Mode {
    fn new(density_share: f64, x: V6, p: M6) -> Mode {
        Mode { density_share, x, p, adapt: 1.0, nis: 1.0, jumped_last: false }
    }

    /// The process noise over `dt` seconds for a white-noise acceleration of density `q`.
    fn process_noise(&self, config: &TemporalConfig, dt: f64) -> M6 {
        let q = config.accel_mm_s2.powi(2) * self.density_share * self.adapt;
        let i = Matrix3::<f64>::identity();
        let mut qm = M6::zeros();
        qm.fixed_view_mut::<3, 3>(0, 0).copy_from(&(i * (q * dt.powi(3) / 3.0 + 1e-12)));
        qm.fixed_view_mut::<3, 3>(0, 3).copy_from(&(i * (q * dt.powi(2) / 2.0)));
        qm.fixed_view_mut::<3, 3>(3, 0).copy_from(&(i * (q * dt.powi(2) / 2.0)));
        qm.fixed_view_mut::<3, 3>(3, 3).copy_from(&(i * (q * dt)));
        qm
    }

    /// Predicts over `dt` seconds (transition `f`) and updates with one set's centre (see
    /// [`TagFilter::update`]); `None` when the innovation's covariance is singular (nothing
    /// changed then).
    #[allow(clippy::too_many_arguments)]
    fn update(
        &mut self,
        config: &TemporalConfig,
        f: &M6,
        dt: f64,
        centre: Vector3<f64>,
        noise_cov: &Matrix3<f64>,
        full_cov: &Matrix3<f64>,
        partial: bool,
    ) -> Option<ModeStep> {
        let q = self.process_noise(config, dt);
        let x_pred = f * self.x;
        let mut p_pred = f * self.p * f.transpose() + q;
        let mut r = if partial { *full_cov } else { *noise_cov };
        let h = SMatrix::<f64, 3, 6>::identity();
        let d = centre - x_pred.fixed_rows::<3>(0);
        let s = p_pred.fixed_view::<3, 3>(0, 0) + r;
        let s_inv = s.try_inverse()?;
        let nis = d.dot(&(s_inv * d));
        let log_likelihood = -0.5 * (nis + s.determinant().max(f64::MIN_POSITIVE).ln());
        let mut jump = false;
        let dt_rate = dt.max(1e-3);
        if nis > GATE {
            if partial {
                // Suspect depth: down-weight, never lock out.
                r *= nis / GATE;
            } else {
                // A jump: the position may be anywhere along the innovation (a first crack
                // moves the tag at once). A second jump in a row says the rate changed (the
                // start or end of loading, a crack's softening): the rate may then be off by
                // as much as the innovation over the interval. One jump alone leaves the rate
                // as it was, so a step is followed in one set without a rate thrown by noise.
                let widen = d * d.transpose();
                let mut pp = p_pred.fixed_view_mut::<3, 3>(0, 0);
                pp += widen;
                if self.jumped_last {
                    let mut pv = p_pred.fixed_view_mut::<3, 3>(3, 3);
                    pv += widen / (dt_rate * dt_rate);
                }
                jump = true;
            }
        } else if !partial && nis / 3.0 > SURPRISE {
            // Too large for the model, too small for a jump: the rate is changing (loading
            // starts, stops or changes speed). Covariance matching at once: this interval's
            // process noise is scaled so that it explains the innovation, and — since that
            // noise is tiny over one interval — the prediction is also widened along the
            // innovation by the covariance that brings its NIS to 3 (`S + α d dᵀ` with
            // `α = (nis/3 − 1)/nis`, Sherman–Morrison), the rate by the same over the
            // interval, so position and rate are corrected in this set, not over the next
            // several (docs/control.md: the start of loading).
            let scale = (nis / 3.0 - 1.0).min(config.max_adapt);
            p_pred += q * scale;
            let alpha = (nis / 3.0 - 1.0) / nis;
            let widen = d * d.transpose() * alpha;
            let mut pp = p_pred.fixed_view_mut::<3, 3>(0, 0);
            pp += widen;
            let mut pv = p_pred.fixed_view_mut::<3, 3>(3, 3);
            pv += widen / (dt_rate * dt_rate);
            self.adapt = (self.adapt * nis / 3.0).min(config.max_adapt);
        }
        if !partial {
            self.nis = (1.0 - NIS_WEIGHT) * self.nis + NIS_WEIGHT * (nis / 3.0).min(GATE);
            // Covariance matching: raise the process noise while innovations are larger than
            // the model expects, relax it back while they are not.
            if self.nis > 2.0 {
                self.adapt = (self.adapt * 2.0).min(config.max_adapt);
            } else if self.nis < 1.2 {
                self.adapt = (self.adapt * 0.8).max(1.0);
            }
            self.jumped_last = jump;
        }
        let s = h * p_pred * h.transpose() + r;
        let s_inv = s.try_inverse()?;
        let k = p_pred * h.transpose() * s_inv;
        // Joseph form: stays symmetric positive definite.
        let ikh = M6::identity() - k * h;
        let p = ikh * p_pred * ikh.transpose() + k * r * k.transpose();
        self.x = x_pred + k * d;
        self.p = (p + p.transpose()) * 0.5;
        Some(ModeStep { x_pred, p_pred, log_likelihood, jump })
    }
}

/// Moment-matched mean and covariance of weighted Gaussians.
fn combine<'a>(parts: impl Iterator<Item = (f64, &'a V6, &'a M6)> + Clone) -> (V6, M6) {
    let x: V6 = parts.clone().map(|(w, x, _)| x * w).sum();
    let p: M6 = parts
        .map(|(w, xi, pi)| {
            let d = xi - x;
            (pi + d * d.transpose()) * w
        })
        .sum();
    (x, (p + p.transpose()) * 0.5)
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
}

impl TagFilter {
    /// A filter started at a first measurement (`cov`: its pixel-noise covariance).
    pub fn new(config: TemporalConfig, t_ns: i64, centre: Vector3<f64>, cov: &Matrix3<f64>) -> TagFilter {
        let blank =
            Step { t_ns, x_pred: V6::zeros(), p_pred: M6::zeros(), x: V6::zeros(), p: M6::zeros(), f: M6::identity(), restart: true };
        let mode = Mode::new(1.0, V6::zeros(), M6::zeros());
        let mut f = TagFilter { config, t_ns, modes: [mode; 2], mu: [0.5; 2], x: V6::zeros(), p: M6::zeros(), history: None, last: blank };
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
        let update = |m: &mut Mode| m.update(&self.config, &f, dt, centre, noise_cov, full_cov, partial);
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
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};

    const DT: i64 = 33_333_333;

    fn iso(s: f64) -> Matrix3<f64> {
        Matrix3::identity() * s * s
    }

    /// Runs a filter over `truth(k)` with noise σ = `sigma` mm; returns (raw errors, filtered errors).
    fn run(truth: impl Fn(usize) -> f64, sets: usize, sigma: f64) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
        run_seeded(truth, sets, sigma, 7)
    }

    /// [`run`] with the noise drawn from `seed`.
    fn run_seeded(truth: impl Fn(usize) -> f64, sets: usize, sigma: f64, seed: u64) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let n = Normal::new(0.0, sigma).unwrap();
        let mut f: Option<TagFilter> = None;
        let (mut raw, mut est, mut sig) = (Vec::new(), Vec::new(), Vec::new());
        for k in 0..sets {
            let z = Vector3::new(n.sample(&mut rng), n.sample(&mut rng), truth(k) + n.sample(&mut rng));
            let t = k as i64 * DT;
            let u = match f.as_mut() {
                None => {
                    f = Some(TagFilter::new(TemporalConfig::default(), t, z, &iso(sigma)));
                    f.as_ref().unwrap().result(false, false)
                }
                Some(f) => f.update(t, z, &iso(sigma), &iso(sigma * 3.0), false),
            };
            raw.push(z.z - truth(k));
            est.push(u.centre.z - truth(k));
            sig.push(u.covariance[(2, 2)].sqrt());
        }
        (raw, est, sig)
    }

    fn rms(v: &[f64]) -> f64 {
        (v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64).sqrt()
    }

    #[test]
    fn noise_at_rest_falls_to_less_than_half() {
        let (raw, est, sig) = run(|_| 0.0, 600, 0.003);
        let (r, e) = (rms(&raw[100..]), rms(&est[100..]));
        println!("at rest: raw {r:.5} mm, estimated {e:.5} mm, σ {:.5}", sig[500]);
        // Measured 0.31× (one filter of the configured density: 0.43×).
        assert!(e <= 0.4 * r, "raw {r}, estimated {e}");
        let within = est[100..].iter().zip(&sig[100..]).filter(|(e, s)| e.abs() <= 2.0 * **s).count();
        assert!(within as f64 >= 0.85 * 500.0, "{within} of 500 within 2σ");
    }

    #[test]
    fn a_sudden_step_is_followed_within_two_frames() {
        let step = 0.05;
        let (_, est, _) = run(|k| if k >= 300 { step } else { 0.0 }, 320, 0.003);
        // Within 10 % of the step from the second frame after it on.
        for (k, e) in est.iter().enumerate().skip(301) {
            assert!(e.abs() <= 0.1 * step, "frame {k} after the step: error {e}");
        }
    }

    #[test]
    fn a_ramp_is_followed_without_lag() {
        // 1 mm/min, then 6 mm/min (a rate change), then on.
        let truth = |k: usize| {
            let t = k as f64 * DT as f64 * 1e-9;
            if t < 10.0 {
                t / 60.0
            } else {
                10.0 / 60.0 + (t - 10.0) * 0.1
            }
        };
        let (raw, est, _) = run(truth, 600, 0.003);
        let (r, e) = (rms(&raw[30..]), rms(&est[30..]));
        println!("ramp: raw {r:.5} mm, estimated {e:.5} mm");
        assert!(e < r, "raw {r}, estimated {e}");
    }

    /// Loading starts from rest at a rate whose first innovations are too large for the
    /// steady model and too small for a jump (0.011 mm a set against 0.003 mm of noise; 20
    /// mm/min at 30 sets/s, some 200× a flexural test's rate): the changing model takes over
    /// within a few sets and the rate is learned. The first set of such a ramp is a 3.7σ
    /// innovation, which no filter quiet at rest tells from noise. Measured over 20 noise
    /// draws, estimated / raw RMS over the first eight sets 0.81–2.14 (one filter of the
    /// configured density, before the two models: 0.78–2.18), over the 31 after them
    /// 0.33–0.96 (0.50–1.04).
    #[test]
    fn the_start_of_loading_is_followed_within_a_few_sets() {
        let truth = |k: usize| if k < 60 { 0.0 } else { (k - 60) as f64 * 0.011 };
        let (mut first, mut after) = (Vec::new(), Vec::new());
        for seed in 0..20 {
            let (raw, est, _) = run_seeded(truth, 100, 0.003, seed);
            first.push(rms(&est[61..69]) / rms(&raw[61..69]));
            after.push(rms(&est[69..100]) / rms(&raw[69..100]));
        }
        println!("start of loading, estimated / raw RMS: first eight sets {first:.2?}, after them {after:.2?}");
        let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
        assert!(first.iter().all(|r| *r <= 2.5) && mean(&first) <= 1.8, "the ramp's first sets: {first:?}");
        assert!(after.iter().all(|r| *r <= 1.1) && mean(&after) <= 0.8, "after the first eight sets: {after:?}");
    }

    /// The steady model holds a tag at rest; a change of rate hands it to the changing model,
    /// and a steady ramp back to the steady one.
    #[test]
    fn the_models_take_turns_as_the_motion_changes() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let n = Normal::new(0.0, 0.003).unwrap();
        // Rest for 10 s, then 0.05 mm/s from 10 s on (a fast rate, 3 mm/min).
        let truth = |t: f64| if t < 10.0 { 0.0 } else { (t - 10.0) * 0.05 };
        let mut f = TagFilter::new(TemporalConfig::default(), 0, Vector3::zeros(), &iso(0.003));
        let mut steady = Vec::new();
        for k in 1..900 {
            let t = k as f64 * DT as f64 * 1e-9;
            let z = Vector3::new(n.sample(&mut rng), n.sample(&mut rng), truth(t) + n.sample(&mut rng));
            f.update(k as i64 * DT, z, &iso(0.003), &iso(0.003), false);
            steady.push(f.steady_probability());
        }
        let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
        let (rest, change, ramp) = (mean(&steady[150..299]), steady[300..330].iter().copied().fold(1.0, f64::min), mean(&steady[700..]));
        println!("steady probability: at rest {rest:.2}, least after the change {change:.2}, on the ramp {ramp:.2}");
        assert!(rest > 0.7, "at rest {rest}");
        assert!(change < 0.3, "after the change {change}");
        assert!(ramp > 0.7, "on the ramp {ramp}");
    }

    /// Lag of the estimate behind a tag that rests for 12 s and then moves at 0.5 mm/s
    /// (a sudden ramp from rest), `fps` sets/s, white noise of `noise_mm` per set while the
    /// solve states `stated_mm` (1 σ, each axis): the largest error from the second set of the
    /// ramp through 3 s of it over `seeds` noise draws, mm.
    fn lag_after_two_sets(fps: f64, noise_mm: f64, stated_mm: f64, seeds: u64) -> f64 {
        let dt_ns = (1e9 / fps).round() as i64;
        let start = (12.0 * fps).round() as i64;
        let rate_mm_s = 0.5;
        let mut worst = 0.0f64;
        for seed in 0..seeds {
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(100 + seed);
            let n = Normal::new(0.0, noise_mm).unwrap();
            let truth = |k: i64| if k <= start { 0.0 } else { (k - start) as f64 * dt_ns as f64 * 1e-9 * rate_mm_s };
            let mut f = TagFilter::new(TemporalConfig::default(), 0, Vector3::zeros(), &iso(stated_mm));
            for k in 1..start + (3.0 * fps) as i64 {
                let z = Vector3::new(n.sample(&mut rng), n.sample(&mut rng), truth(k) + n.sample(&mut rng));
                let u = f.update(k * dt_ns, z, &iso(stated_mm), &iso(stated_mm * 3.0), false);
                if k >= start + 2 {
                    worst = worst.max((u.centre.z - truth(k)).abs());
                }
            }
        }
        worst
    }

    /// A ramp from rest at 0.5 mm/s is followed from its second set on, at 5 and at 30 sets/s,
    /// whatever the solve states of its noise. On a rendered scene the solve's pixel-noise σ
    /// (from the corner residuals, most of which are the same from set to set) states ~95 µm
    /// for a tag whose set-to-set noise is ~5 µm (the EN day's recording, docs/report.md): the
    /// innovations of a ramp then look like noise, and the estimate fell behind by hundreds of
    /// µm. Bound: 5 σ of the set-to-set noise (25 µm) after the ramp's second set.
    #[test]
    #[ignore = "fails on today's estimator (docs/report.md, the EN day's clock offset): with the stated noise 19x the set-to-set noise the lag grows to hundreds of µm"]
    fn a_ramp_from_rest_is_followed_from_its_second_set() {
        let lags: Vec<(f64, f64, f64)> =
            [5.0, 30.0].map(|fps| (fps, lag_after_two_sets(fps, 0.005, 0.005, 10), lag_after_two_sets(fps, 0.005, 0.095, 10))).into();
        for (fps, honest, overstated) in &lags {
            println!("ramp from rest at 0.5 mm/s, {fps} sets/s: worst lag from the second set {:.1} µm (noise stated as it is), {:.1} µm (stated 19x)", honest * 1e3, overstated * 1e3);
        }
        for (fps, honest, overstated) in lags {
            assert!(honest <= 0.025, "{fps} sets/s, noise stated as it is: lag {honest} mm");
            assert!(overstated <= 0.025, "{fps} sets/s, noise stated 19x: lag {overstated} mm");
        }
    }

    #[test]
    fn a_partial_set_moves_the_state_only_where_it_observes() {
        let mut f = TagFilter::new(TemporalConfig::default(), 0, Vector3::zeros(), &iso(0.002));
        for k in 1..30 {
            f.update(k * DT, Vector3::zeros(), &iso(0.002), &iso(0.004), false);
        }
        // One camera: 1 mm off along y (its line of sight), good in x and z.
        let full = Matrix3::from_diagonal(&Vector3::new(0.004f64.powi(2), 0.5f64.powi(2), 0.004f64.powi(2)));
        let u = f.update(30 * DT, Vector3::new(0.0, 1.0, 0.0), &full, &full, true);
        assert!(u.partial && !u.jump);
        assert!(u.centre.y.abs() < 0.01, "depth kept from the state: {}", u.centre);
    }

    #[test]
    fn the_smoother_is_no_worse_than_the_filter() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let n = Normal::new(0.0, 0.003).unwrap();
        let mut f = TagFilter::new(TemporalConfig::default(), 0, Vector3::zeros(), &iso(0.003)).keep_history();
        let mut filt = Vec::new();
        for k in 1..400 {
            let z = Vector3::new(n.sample(&mut rng), n.sample(&mut rng), n.sample(&mut rng));
            filt.push(f.update(k as i64 * DT, z, &iso(0.003), &iso(0.003), false).centre.z);
        }
        let sm: Vec<f64> = smooth(f.history()).iter().skip(1).map(|(_, c, _)| c.z).collect();
        assert_eq!(sm.len(), filt.len());
        assert!(rms(&sm[50..]) <= rms(&filt[50..]), "smoothed {} filtered {}", rms(&sm[50..]), rms(&filt[50..]));
    }
}
