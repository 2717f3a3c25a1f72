//! Slow camera drift (thermal, creep, a settling floor) estimated from the background tags
//! while a camera's pose is held.
//!
//! Why: a held pose makes per-frame pose noise vanish from the displacements (the pose's
//! error is a constant that cancels), but it also turns any real motion of the camera below
//! the bump threshold into fake deflection: 0.05° at 1 m is ~0.9 mm. The background tags are
//! seen in every frame, so the camera's motion since its pose was fixed is observable; the
//! question is how to use it without letting the per-frame pose noise back in.
//!
//! Model (per camera, a linear Kalman filter, 18 states): the camera's pose relative to the
//! held pose `H`, in the parameters `(ω, Δc)` — rotation vector (rad, `R = exp(ω) R_H`) and
//! camera-centre shift (mm, world) — is `x₀ + d(t)`:
//!
//! * `x₀` (6): the held pose's own error against the images (constant; prior = the held
//!   pose's covariance). It must be a state of its own: the displacements are taken against
//!   the first solved positions, which were solved with `H`, so what has to be applied is the
//!   camera's motion *since then*, `d(t)`, not its offset from `H` — estimating the offset
//!   would move the pose by the first pose's error over the run (a fake displacement of the
//!   size of one frame's pose noise).
//! * `d` (6): the drift since the pose was fixed, exactly 0 at that moment.
//! * `ḋ` (6): its rate. Prior N(0, σ²) with σ = [`DriftConfig::rate_deg_per_h`] and
//!   [`DriftConfig::rate_mm_per_h`]; the rate itself is a random walk that changes by about
//!   σ over [`DriftConfig::rate_change_h`] (white-noise acceleration), so a drift that turns
//!   round is followed and a constant drift is followed without lag.
//!
//! Each frame's measurement is the pose solved from that frame's background corners
//! alone, `z = x₀ + d + v`, with `v`'s covariance from the solve. The camera pose used for
//! the specimen tags is then `H` moved by `d̂`. For a static camera `d̂` stays at the level
//! the rate prior and the data allow (over a short run at video rate: nothing — the pose is
//! held as before); for a drifting one it follows the drift with the noise of a line fitted
//! through the frames seen so far, a small fraction of one frame's pose noise. An
//! innovation far outside its covariance (a mis-detected frame) is down-weighted, not
//! dropped, so the filter can never lock itself out; a real jump is the bump test's job.

use nalgebra::{Matrix3, Matrix6, SMatrix, SVector, Vector3, Vector6};
use tagdeflect_core::camera::{skew, Pose};

/// Tracking of slow camera drift while a pose is held (`[measure]` keys `drift_tracking`,
/// `drift_rate_deg_per_h`, `drift_rate_mm_per_h`, `drift_rate_change_h`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DriftConfig {
    /// Estimate and correct slow drift (false = hold the pose exactly, as without drift).
    pub enabled: bool,
    /// Expected size (1 σ) of a camera's turning rate, degrees per hour.
    pub rate_deg_per_h: f64,
    /// Expected size (1 σ) of the creep rate of a camera's centre, mm per hour.
    pub rate_mm_per_h: f64,
    /// Time over which the drift rate may change by about its σ, hours.
    pub rate_change_h: f64,
}

impl Default for DriftConfig {
    fn default() -> Self {
        Self { enabled: true, rate_deg_per_h: 0.1, rate_mm_per_h: 1.0, rate_change_h: 1.0 }
    }
}

impl DriftConfig {
    /// The drift options of a `[measure]` section.
    pub fn from_measure(m: &crate::measure_config::MeasureConfig) -> Self {
        Self {
            enabled: m.drift_tracking,
            rate_deg_per_h: m.drift_rate_deg_per_h,
            rate_mm_per_h: m.drift_rate_mm_per_h,
            rate_change_h: m.drift_rate_change_h,
        }
    }

    /// Checks the values; keys as in `[measure]` (`drift_rate_deg_per_h`, …).
    pub fn validate(&self) -> Result<(), tagdeflect_core::Problem> {
        for (key, v) in
            [("rate_deg_per_h", self.rate_deg_per_h), ("rate_mm_per_h", self.rate_mm_per_h), ("rate_change_h", self.rate_change_h)]
        {
            if !(v.is_finite() && v > 0.0 && v <= 1e6) {
                return Err(tagdeflect_core::Problem::new(
                    format!("drift_{key}"),
                    format!("{v}: expected a positive number (at most 1e6)"),
                ));
            }
        }
        Ok(())
    }
}

/// Squared Mahalanobis distance of an innovation above which its measurement is
/// down-weighted (χ² with 6 degrees of freedom: 99.99 %).
const GATE: f64 = 27.9;

type V18 = SVector<f64, 18>;
type M18 = SMatrix<f64, 18, 18>;

/// One camera's drift since its pose was fixed, as estimated now.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DriftEstimate {
    /// Rotation vector of the drift (rad), `R = exp(ω) R_held`.
    pub rotation: Vector3<f64>,
    /// Shift of the camera centre (mm, world).
    pub centre_mm: Vector3<f64>,
    /// Covariance of `(rotation, centre_mm)`.
    pub covariance: Matrix6<f64>,
    /// Seconds since the pose was fixed.
    pub since_s: f64,
}

impl DriftEstimate {
    /// The drift's rotation angle, degrees.
    pub fn angle_deg(&self) -> f64 {
        self.rotation.norm().to_degrees()
    }

    /// The drift's centre shift, mm.
    pub fn shift_mm(&self) -> f64 {
        self.centre_mm.norm()
    }
}

/// The Kalman filter of one camera's drift (see the module docs).
#[derive(Debug, Clone)]
pub struct DriftFilter {
    config: DriftConfig,
    held: Pose,
    t0_ns: i64,
    t_ns: i64,
    x: V18,
    p: M18,
    updates: usize,
    /// Scale of the rate's process noise (≥ 1), raised by the innovations (see [`Adapt`]).
    adapt: Adapt,
}

/// The drift's process noise adapted to the innovations.
///
/// The rate prior (0.1°/h, 1 mm/h) is right for a tripod cooling over an hour, but a leg
/// settling under vibration turns a camera by 0.02° and moves it by 0.2 mm within seconds:
/// a rate a hundred times the prior, which the filter would follow only over minutes (and
/// which stays below the bump test). Each step's innovation is small against one frame's
/// pose noise, so their size says little; their *sign* says it all: while the model fits,
/// the whitened innovations `w = L⁻¹ y` (`S = L Lᵀ`) are independent with unit covariance,
/// and their running mean `m ← (1 − a) m + a w` has covariance `a / (2 − a)`; a drift the
/// model does not follow makes them lean the same way. So `|m|² (2 − a) / a`, χ² with 6
/// degrees of freedom while the model fits, above [`ADAPT_GATE`] (99.9 %) multiplies the
/// rate's process noise by [`ADAPT_GROWTH`] per update (up to [`ADAPT_MAX`]); below the
/// mean (6) it relaxes by [`ADAPT_RELAX`] per update.
#[derive(Debug, Clone, Copy)]
struct Adapt {
    scale: f64,
    mean: Vector6<f64>,
}

impl Default for Adapt {
    fn default() -> Self {
        Self { scale: 1.0, mean: Vector6::zeros() }
    }
}

/// Weight of the newest whitened innovation in the running mean.
const ADAPT_WEIGHT: f64 = 0.1;
/// χ²₆ at 99.9 %: the running mean leans further than chance allows.
const ADAPT_GATE: f64 = 22.5;
/// Growth of the process noise's scale per update while the drift outruns the model.
const ADAPT_GROWTH: f64 = 4.0;
/// Relaxation per update once it does not.
const ADAPT_RELAX: f64 = 0.9;
/// Largest scale: a rate 10⁵ × the prior's σ can be reached within seconds.
const ADAPT_MAX: f64 = 1e10;

impl Adapt {
    /// Takes one update's whitened innovation; true when the running mean leans beyond
    /// chance (the mean is then started afresh, so one lean is acted on once).
    fn observe(&mut self, w: &Vector6<f64>) -> bool {
        // A mis-detected frame's innovation is clipped so it cannot lean the mean alone.
        let w = w.map(|v| v.clamp(-5.0, 5.0));
        self.mean = self.mean * (1.0 - ADAPT_WEIGHT) + w * ADAPT_WEIGHT;
        let chi2 = self.mean.norm_squared() * (2.0 - ADAPT_WEIGHT) / ADAPT_WEIGHT;
        if chi2 > ADAPT_GATE {
            self.scale = (self.scale * ADAPT_GROWTH).min(ADAPT_MAX);
            return true;
        }
        if chi2 < 6.0 {
            self.scale = (self.scale * ADAPT_RELAX).max(1.0);
        }
        false
    }
}

/// The pose `held` moved by `d = (ω, Δc)`: `R = exp(ω) R_held`, centre `c_held + Δc`.
pub(crate) fn drifted_pose(held: &Pose, d: &Vector6<f64>) -> Pose {
    let w = Vector3::new(d[0], d[1], d[2]);
    let dc = Vector3::new(d[3], d[4], d[5]);
    let rotation = nalgebra::Rotation3::new(w) * held.rotation;
    let centre = held.centre() + dc;
    Pose { rotation, translation: -(rotation * centre) }
}

/// `pose` relative to `held` in `(ω, Δc)` and its covariance, from the covariance of `pose`
/// in the solver's step parameters `(ω, v)` (`R ← exp(ω) R`, `t ← t + v`).
pub(crate) fn pose_offset(held: &Pose, pose: &Pose, step_covariance: &Matrix6<f64>) -> (Vector6<f64>, Matrix6<f64>) {
    let w = (pose.rotation * held.rotation.inverse()).scaled_axis();
    let dc = pose.centre() - held.centre();
    let j = offset_jacobian(pose);
    let mut z = Vector6::zeros();
    z.fixed_rows_mut::<3>(0).copy_from(&w);
    z.fixed_rows_mut::<3>(3).copy_from(&dc);
    (z, j * step_covariance * j.transpose())
}

/// Jacobian of `(ω, c)` (rotation, camera centre) with respect to the solver's step
/// `(ω, v)` at `pose`: from `c = −Rᵀ t`, `dc = −Rᵀ [t]× dω − Rᵀ dv`.
pub(crate) fn offset_jacobian(pose: &Pose) -> Matrix6<f64> {
    let rt: Matrix3<f64> = *pose.rotation.inverse().matrix();
    let mut j = Matrix6::identity();
    j.fixed_view_mut::<3, 3>(3, 0).copy_from(&(-rt * skew(&pose.translation)));
    j.fixed_view_mut::<3, 3>(3, 3).copy_from(&(-rt));
    j
}

impl DriftFilter {
    /// Starts at `t_ns`, the moment `held` was fixed; `held_covariance` is the held pose's
    /// covariance in the solver's step parameters (the prior of its own error).
    pub fn new(config: DriftConfig, held: Pose, held_covariance: Option<&Matrix6<f64>>, t_ns: i64) -> Self {
        let mut p = M18::zeros();
        p.fixed_view_mut::<6, 6>(0, 0).copy_from(&Self::held_prior(&held, held_covariance));
        let (sr, sc) = Self::rate_sigmas(&config);
        for i in 0..3 {
            p[(12 + i, 12 + i)] = sr * sr;
            p[(15 + i, 15 + i)] = sc * sc;
        }
        Self { config, held, t0_ns: t_ns, t_ns, x: V18::zeros(), p, updates: 0, adapt: Adapt::default() }
    }

    /// Prior covariance of the held pose's own error in `(ω, Δc)`.
    fn held_prior(held: &Pose, held_covariance: Option<&Matrix6<f64>>) -> Matrix6<f64> {
        let c = match held_covariance {
            Some(c) if c.iter().all(|v| v.is_finite()) => pose_offset(held, held, c).1,
            // No covariance: a loose prior (0.1°, 1 mm).
            _ => Matrix6::from_diagonal(&Vector6::new(3e-6, 3e-6, 3e-6, 1.0, 1.0, 1.0)),
        };
        0.5 * (c + c.transpose())
    }

    /// Replaces the held pose by a re-fit of the same moment (the drift so far is kept; the
    /// new pose's own error starts from its prior).
    pub fn rebase(&mut self, held: Pose, held_covariance: Option<&Matrix6<f64>>) {
        self.held = held;
        for i in 0..6 {
            self.x[i] = 0.0;
            for j in 0..18 {
                self.p[(i, j)] = 0.0;
                self.p[(j, i)] = 0.0;
            }
        }
        self.p.fixed_view_mut::<6, 6>(0, 0).copy_from(&Self::held_prior(&held, held_covariance));
    }

    /// σ of the rate, (rad/s, mm/s).
    fn rate_sigmas(c: &DriftConfig) -> (f64, f64) {
        (c.rate_deg_per_h.to_radians() / 3600.0, c.rate_mm_per_h / 3600.0)
    }

    /// The pose this filter corrects.
    pub fn held(&self) -> &Pose {
        &self.held
    }

    /// Measurements used so far.
    pub fn updates(&self) -> usize {
        self.updates
    }

    /// The scale the innovations put on the rate's process noise now (1 = the configured
    /// prior; see [`Adapt`]).
    pub fn adaptive_scale(&self) -> f64 {
        self.adapt.scale
    }

    fn predicted(&self, t_ns: i64) -> (V18, M18) {
        let dt = ((t_ns - self.t_ns) as f64 * 1e-9).max(0.0);
        if dt == 0.0 {
            return (self.x, self.p);
        }
        let mut f = M18::identity();
        for i in 0..6 {
            f[(6 + i, 12 + i)] = dt;
        }
        let (sr, sc) = Self::rate_sigmas(&self.config);
        let tc = self.config.rate_change_h * 3600.0;
        let mut q = M18::zeros();
        for i in 0..6 {
            let s2 = if i < 3 { sr * sr } else { sc * sc };
            let qa = s2 / tc * self.adapt.scale; // rate variance gained per second
            q[(6 + i, 6 + i)] = qa * dt.powi(3) / 3.0;
            q[(6 + i, 12 + i)] = qa * dt * dt / 2.0;
            q[(12 + i, 6 + i)] = qa * dt * dt / 2.0;
            q[(12 + i, 12 + i)] = qa * dt;
        }
        (f * self.x, f * self.p * f.transpose() + q)
    }

    fn estimate_of(&self, x: &V18, p: &M18, t_ns: i64) -> DriftEstimate {
        DriftEstimate {
            rotation: x.fixed_rows::<3>(6).into_owned(),
            centre_mm: x.fixed_rows::<3>(9).into_owned(),
            covariance: p.fixed_view::<6, 6>(6, 6).into_owned(),
            since_s: (t_ns - self.t0_ns) as f64 * 1e-9,
        }
    }

    /// The drift as of the last update.
    pub fn estimate(&self) -> DriftEstimate {
        self.estimate_of(&self.x, &self.p, self.t_ns)
    }

    /// The drift predicted at `t_ns` (no update).
    pub fn predict(&self, t_ns: i64) -> DriftEstimate {
        let (x, p) = self.predicted(t_ns);
        self.estimate_of(&x, &p, t_ns)
    }

    /// The held pose moved by the drift as of the last update.
    pub fn pose(&self) -> Pose {
        drifted_pose(&self.held, &self.x.fixed_rows::<6>(6).into_owned())
    }

    /// The held pose moved by the drift predicted at `t_ns`.
    pub fn predicted_pose(&self, t_ns: i64) -> Pose {
        drifted_pose(&self.held, &self.predicted(t_ns).0.fixed_rows::<6>(6).into_owned())
    }

    /// Feeds the pose solved from one frame's background corners at `t_ns`, with its
    /// covariance in the solver's step parameters. Returns the innovation's squared
    /// Mahalanobis distance (`None` when the measurement was unusable).
    pub fn update(&mut self, t_ns: i64, pose: &Pose, step_covariance: &Matrix6<f64>) -> Option<f64> {
        let (z, r) = pose_offset(&self.held, pose, step_covariance);
        if !(z.iter().all(|v| v.is_finite()) && r.iter().all(|v| v.is_finite())) {
            return None;
        }
        let (x, p) = self.predicted(t_ns);
        let mut h = SMatrix::<f64, 6, 18>::zeros();
        for i in 0..6 {
            h[(i, i)] = 1.0;
            h[(i, 6 + i)] = 1.0;
        }
        let y = z - h * x;
        let hph = h * p * h.transpose();
        let mut s = hph + r;
        let (m2, white, lean) = {
            let c = s.cholesky()?;
            let white = c.l().solve_lower_triangular(&y).unwrap_or_else(Vector6::zeros);
            // The innovations' running mean back in (ω, Δc): how far the model is behind.
            let lean = c.l() * self.adapt.mean;
            (y.dot(&c.solve(&y)), white, lean)
        };
        if m2 > GATE {
            // Down-weight, so that the innovation sits on the gate.
            s = hph + r * (m2 / GATE);
        }
        let s = 0.5 * (s + s.transpose());
        let c = s.cholesky()?;
        let k = (c.solve(&(h * p))).transpose(); // P Hᵀ S⁻¹ (P, S symmetric)
        let x = x + k * y;
        // Joseph form keeps P symmetric and positive.
        let ikh = M18::identity() - k * h;
        let rr = if m2 > GATE { r * (m2 / GATE) } else { r };
        let p = ikh * p * ikh.transpose() + k * rr * k.transpose();
        self.x = x;
        self.p = 0.5 * (p + p.transpose());
        let dt = ((t_ns - self.t_ns) as f64 * 1e-9).max(1e-3);
        self.t_ns = self.t_ns.max(t_ns);
        self.updates += 1;
        if self.adapt.observe(&white) {
            // The model has fallen behind by about `lean` over the running mean's window:
            // the rate may be off by that over the window's time. Its covariance is widened
            // so (twice over), and the next innovations place it.
            let window_s = dt / ADAPT_WEIGHT;
            for i in 0..6 {
                self.p[(12 + i, 12 + i)] += 4.0 * (lean[i] / window_s).powi(2);
            }
            self.adapt.mean = Vector6::zeros();
        }
        Some(m2)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cov() -> Matrix6<f64> {
        Matrix6::from_diagonal(&Vector6::new(1e-10, 1e-10, 1e-10, 1e-3, 1e-3, 1e-3))
    }

    #[test]
    fn offset_and_drifted_pose_are_inverse() {
        let held = Pose::from_rvec_tvec([0.1, -0.2, 0.05], [10.0, -20.0, 1000.0]);
        let d = Vector6::new(1e-3, -2e-3, 5e-4, 0.3, -0.1, 0.2);
        let moved = drifted_pose(&held, &d);
        let (z, _) = pose_offset(&held, &moved, &cov());
        assert!((z - d).norm() < 1e-9, "{z} vs {d}");
    }

    #[test]
    fn covariance_transform_matches_finite_differences() {
        let pose = Pose::from_rvec_tvec([0.1, -0.2, 0.05], [10.0, -20.0, 1000.0]);
        // A step e_k in (ω, v) moves (ω, Δc) by column k of J.
        let mut j = Matrix6::zeros();
        for k in 0..6 {
            let h = if k < 3 { 1e-7 } else { 1e-4 };
            let mut w = Vector3::zeros();
            let mut v = Vector3::zeros();
            if k < 3 {
                w[k] = h;
            } else {
                v[k - 3] = h;
            }
            let r = nalgebra::Rotation3::new(w) * pose.rotation;
            let stepped = Pose { rotation: r, translation: pose.translation + v };
            let (z, _) = pose_offset(&pose, &stepped, &cov());
            j.set_column(k, &(z / h));
        }
        let e = Matrix6::from_diagonal(&Vector6::new(1.0, 2.0, 3.0, 4.0, 5.0, 6.0));
        let (_, c) = pose_offset(&pose, &pose, &e);
        let fd = j * e * j.transpose();
        assert!((c - fd).norm() < 1e-3 * fd.norm(), "{c} vs {fd}");
    }

    #[test]
    fn follows_a_ramp_and_stays_still_when_static() {
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        let held = Pose::from_rvec_tvec([0.1, -0.2, 0.05], [10.0, -20.0, 1000.0]);
        let r = cov();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let n = Normal::new(0.0, 1.0).unwrap();
        let noise = |rng: &mut rand_chacha::ChaCha8Rng| Vector6::from_fn(|i, _| n.sample(rng) * r[(i, i)].sqrt());
        let cfg = DriftConfig::default();
        // 0.05° and 0.3 mm over 3000 s, measured every 100 s.
        let total = Vector6::new(0.05f64.to_radians() * 0.6, 0.0, 0.05f64.to_radians() * 0.8, 0.0, 0.18, -0.24);
        let ji = offset_jacobian(&held).try_inverse().unwrap();
        let step = ji * r * ji.transpose();
        let mut drifting = DriftFilter::new(cfg, held, Some(&step), 0);
        let mut still = DriftFilter::new(cfg, held, Some(&step), 0);
        let x0 = noise(&mut rng);
        for k in 1..=30 {
            let t = k as i64 * 100_000_000_000;
            let truth = total * (k as f64 / 30.0);
            drifting.update(t, &drifted_pose(&held, &(x0 + truth + noise(&mut rng))), &step).unwrap();
            still.update(t, &drifted_pose(&held, &(x0 + noise(&mut rng))), &step).unwrap();
        }
        let d = drifting.estimate();
        let s = still.estimate();
        let sigma_w = d.covariance[(0, 0)].sqrt();
        println!(
            "drift {:.5}° {:.4} mm (σ ω {:.2e}); static {:.5}° {:.4} mm",
            d.angle_deg(),
            d.shift_mm(),
            sigma_w,
            s.angle_deg(),
            s.shift_mm()
        );
        assert!((d.angle_deg() - 0.05).abs() < 0.003, "{}", d.angle_deg());
        assert!((d.shift_mm() - 0.3).abs() < 0.05, "{}", d.shift_mm());
        // Static: the noise of a line fitted through 30 measurements (σ 0.03 mm per axis of
        // the centre in one frame), no trend.
        assert!(s.angle_deg() < 0.003 && s.shift_mm() < 0.12);
    }
}
