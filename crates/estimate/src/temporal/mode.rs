//! One motion model of the temporal filter (see the module docs of [`super`]): a
//! constant-velocity Kalman filter with its own adaptive process noise, its jump and its
//! surprise, judged on the learned set-to-set scale ([`super::noise_scale`]).

use nalgebra::{Matrix3, SMatrix, Vector3};

use super::{TemporalConfig, GATE, M6, NIS_WEIGHT, SURPRISE, V6};

/// How long full sets are weighed by the learned noise after a detected change of motion, s
/// (the rate is learned over it; each change restarts it).
const FOLLOW_S: f64 = 1.0;

/// One motion model's filter: the state, its covariance and the model's own adaptation
/// (see [`TagFilter`]: two of them, mixed).
#[derive(Debug, Clone, Copy)]
pub(super) struct Mode {
    /// Share of the configured process-noise density this model assumes.
    density_share: f64,
    pub(super) x: V6,
    pub(super) p: M6,
    /// Adaptive scale of the process noise (≥ 1).
    pub(super) adapt: f64,
    /// Running mean of the full sets' NIS / 3.
    nis: f64,
    /// The last full update was a jump.
    jumped_last: bool,
    /// Seconds left of weighting full sets by the learned noise after a detected change.
    follow_s: f64,
}

/// What one mode's update made of a set.
pub(super) struct ModeStep {
    pub(super) x_pred: V6,
    pub(super) p_pred: M6,
    /// Log-likelihood of the set's centre under the mode's prediction (before any widening),
    /// up to a constant common to the modes.
    pub(super) log_likelihood: f64,
    pub(super) jump: bool,
}

impl Mode {
    pub(super) fn new(density_share: f64, x: V6, p: M6) -> Mode {
        Mode { density_share, x, p, adapt: 1.0, nis: 1.0, jumped_last: false, follow_s: 0.0 }
    }

    /// The process noise over `dt` seconds for a white-noise acceleration of density `q`.
    pub(super) fn process_noise(&self, config: &TemporalConfig, dt: f64) -> M6 {
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
    /// [`TagFilter::update`](super::TagFilter::update)); `None` when the innovation's
    /// covariance is singular (nothing changed then). `scale`: the learned set-to-set scale of
    /// a full set's noise against the stated (a variance ratio in (0, 1],
    /// [`super::noise_scale`]): a full set's tests for a change of motion, and the widening
    /// that follows one, are on that scale; the weighting of every set is the stated one.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn update(
        &mut self,
        config: &TemporalConfig,
        f: &M6,
        dt: f64,
        centre: Vector3<f64>,
        noise_cov: &Matrix3<f64>,
        full_cov: &Matrix3<f64>,
        partial: bool,
        scale: f64,
    ) -> Option<ModeStep> {
        let q = self.process_noise(config, dt);
        let x_pred = f * self.x;
        let mut p_pred = f * self.p * f.transpose() + q;
        let mut r = if partial { *full_cov } else { *noise_cov };
        let d = centre - x_pred.fixed_rows::<3>(0);
        let s = p_pred.fixed_view::<3, 3>(0, 0) + r;
        let nis = d.dot(&(s.try_inverse()? * d));
        let log_likelihood = -0.5 * (nis + s.determinant().max(f64::MIN_POSITIVE).ln());
        let mut jump = false;
        if partial {
            if nis > GATE {
                // Suspect depth: down-weight, never lock out.
                r *= nis / GATE;
            }
        } else {
            let following = self.follow_s > 0.0;
            let nis_learned = if following { nis_against(&p_pred, &(r * scale), &d)? } else { nis / scale };
            let change = nis_learned / 3.0 > SURPRISE;
            if change || following {
                // The update that follows a change: the set weighed by the noise it has.
                r *= scale;
            }
            if nis_learned > GATE {
                self.widen_for_jump(&mut p_pred, &d, dt);
                jump = true;
            } else if change {
                let nis_real = nis_against(&p_pred, &r, &d)?;
                self.widen_for_surprise(config, &mut p_pred, &q, &d, dt, nis_real);
                self.adapt = (self.adapt * nis_learned / 3.0).min(config.max_adapt);
            }
            self.adapt_to(config, nis_learned, jump);
            self.follow_s = if change { FOLLOW_S } else { self.follow_s - dt };
        }
        self.correct(x_pred, p_pred, &r, &d)?;
        if !partial && self.follow_s <= 0.0 && self.follow_s + dt > 0.0 {
            // Back to the stated weighting: the covariance into its units, so the state is
            // trusted against the stated noise as much as it was against the real one.
            self.p /= scale;
        }
        Some(ModeStep { x_pred, p_pred, log_likelihood, jump })
    }

    /// A jump: the position may be anywhere along the innovation `d` (a first crack moves
    /// the tag at once). A second jump in a row says the rate changed (the start or end of
    /// loading, a crack's softening): the rate may then be off by as much as the innovation
    /// over the interval. One jump alone leaves the rate as it was, so a step is followed in
    /// one set without a rate thrown by noise.
    fn widen_for_jump(&self, p_pred: &mut M6, d: &Vector3<f64>, dt: f64) {
        let widen = d * d.transpose();
        let mut pp = p_pred.fixed_view_mut::<3, 3>(0, 0);
        pp += widen;
        if self.jumped_last {
            let dt_rate = dt.max(1e-3);
            let mut pv = p_pred.fixed_view_mut::<3, 3>(3, 3);
            pv += widen / (dt_rate * dt_rate);
        }
    }

    /// Too large for the model, too small for a jump: the rate is changing (loading starts,
    /// stops or changes speed). Covariance matching at once: this interval's process noise
    /// `q` is scaled so that it explains the innovation, and — since that noise is tiny over
    /// one interval — the prediction is also widened along the innovation by the covariance
    /// that brings its NIS to 3 (`S + α d dᵀ` with `α = (nis/3 − 1)/nis`, Sherman–Morrison,
    /// on the learned scale), the rate by the same over the interval, so position and rate
    /// are corrected in this set, not over the next several (docs/control.md: the start of
    /// loading). `nis`: against the noise the set is weighed by.
    fn widen_for_surprise(&mut self, config: &TemporalConfig, p_pred: &mut M6, q: &M6, d: &Vector3<f64>, dt: f64, nis: f64) {
        if nis <= 3.0 {
            return;
        }
        let scale = (nis / 3.0 - 1.0).min(config.max_adapt);
        *p_pred += q * scale;
        let alpha = (nis / 3.0 - 1.0) / nis;
        let widen = d * d.transpose() * alpha;
        let dt_rate = dt.max(1e-3);
        let mut pp = p_pred.fixed_view_mut::<3, 3>(0, 0);
        pp += widen;
        let mut pv = p_pred.fixed_view_mut::<3, 3>(3, 3);
        pv += widen / (dt_rate * dt_rate);
    }

    /// Covariance matching over full sets (`nis` on the learned scale): raise the process
    /// noise while innovations are larger than the model expects, relax it back while they
    /// are not.
    fn adapt_to(&mut self, config: &TemporalConfig, nis: f64, jump: bool) {
        self.nis = (1.0 - NIS_WEIGHT) * self.nis + NIS_WEIGHT * (nis / 3.0).min(GATE);
        if self.nis > 2.0 {
            self.adapt = (self.adapt * 2.0).min(config.max_adapt);
        } else if self.nis < 1.2 {
            self.adapt = (self.adapt * 0.8).max(1.0);
        }
        self.jumped_last = jump;
    }

    /// The Kalman update of the prediction with innovation `d` of noise `r`.
    fn correct(&mut self, x_pred: V6, p_pred: M6, r: &Matrix3<f64>, d: &Vector3<f64>) -> Option<()> {
        let h = SMatrix::<f64, 3, 6>::identity();
        let s = h * p_pred * h.transpose() + r;
        let k = p_pred * h.transpose() * s.try_inverse()?;
        // Joseph form: stays symmetric positive definite.
        let ikh = M6::identity() - k * h;
        let p = ikh * p_pred * ikh.transpose() + k * r * k.transpose();
        self.x = x_pred + k * d;
        self.p = (p + p.transpose()) * 0.5;
        Some(())
    }
}

/// The NIS of innovation `d` against the predicted covariance `p_pred` and the noise `r`.
fn nis_against(p_pred: &M6, r: &Matrix3<f64>, d: &Vector3<f64>) -> Option<f64> {
    let s = p_pred.fixed_view::<3, 3>(0, 0) + r;
    Some(d.dot(&(s.try_inverse()? * d)))
}

/// Moment-matched mean and covariance of weighted Gaussians.
pub(super) fn combine<'a>(parts: impl Iterator<Item = (f64, &'a V6, &'a M6)> + Clone) -> (V6, M6) {
    let x: V6 = parts.clone().map(|(w, x, _)| x * w).sum();
    let p: M6 = parts
        .map(|(w, xi, pi)| {
            let d = xi - x;
            (pi + d * d.transpose()) * w
        })
        .sum();
    (x, (p + p.transpose()) * 0.5)
}
