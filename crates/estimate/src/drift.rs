//! Slow camera drift (thermal, creep, a settling floor) estimated from the background tags
//! while a camera's pose is held.
//!
//! Why: a held pose makes per-frame pose noise vanish from the displacements (the pose's
//! error is a constant that cancels), but it also turns any real motion of the camera below
//! the bump threshold into fake deflection: 0.05° at 1 m is ~0.9 mm. The background tags are
//! seen in every frame, so the camera's motion since its pose was fixed is observable; the
//! question is how to use it without letting the per-frame pose noise back in.
//!
//! Model (per camera, linear Kalman filters of 18 states): the camera's pose relative to the
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
//!   round is followed and a constant drift is followed without lag. A second model of the
//!   same states lets the rate change far faster (a leg settling within seconds); the two
//!   are weighted by how well each predicts the frames ([`MODEL_SCALES`]).
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

/// The filter of one camera's drift (see the module docs): two motion models run side by
/// side and weighted by how well each predicts the frames (see [`DriftFilter::update`]).
#[derive(Debug, Clone)]
pub struct DriftFilter {
    config: DriftConfig,
    held: Pose,
    t0_ns: i64,
    t_ns: i64,
    /// The slow model ([`MODEL_SCALES`]`[0]`, the configured prior) and the fast one.
    models: [Model; 2],
    /// Probability of each model given the frames so far.
    probability: [f64; 2],
    updates: usize,
}

/// One motion model's state `(x₀, d, ḋ)` and covariance.
#[derive(Debug, Clone, Copy)]
struct Model {
    x: V18,
    p: M18,
}

/// Scale of each model's rate process noise on the configured one.
///
/// The configured prior (0.1°/h, 1 mm/h, changing over an hour) is right for a tripod
/// cooling, but a leg settling under vibration turns a camera by 0.02° and moves it by
/// 0.2 mm within seconds: a rate a hundred times and more the prior's, which a filter on
/// that prior follows only over minutes and which stays below the bump test. So a second
/// model lets the rate change by ~1700 σ within a second (10¹⁰ × the rate's variance gained
/// per unit time; 10⁸ and 10⁹ followed a 0.05° / 0.5 mm drift over 2 s less well, 10¹¹ as
/// well, docs/drift.md), and the two are run as an interacting multiple model (Blom and
/// Bar-Shalom): each update mixes the models by their switching probabilities, updates
/// each with the frame, and weights them by the likelihood of its innovation. While the
/// camera is still, the fast model predicts worse (its wide prediction spreads the
/// likelihood) and its weight stays near [`TO_FAST`]; once a drift outruns the slow model
/// its innovations lean, the fast model gains weight, and the mixing hands the slow model
/// the fast one's state — even a modest weight moves the estimate onto the drift — until
/// the motion stops and the slow model predicts best again.
const MODEL_SCALES: [f64; 2] = [1.0, 1e10];
/// Probability per update that the camera starts moving fast (slow → fast).
const TO_FAST: f64 = 0.01;
/// Probability per update that a fast motion stops (fast → slow).
const TO_SLOW: f64 = 0.05;
/// `SWITCH[i][j]`: probability of model `j` at an update after model `i` at the one before.
const SWITCH: [[f64; 2]; 2] = [[1.0 - TO_FAST, TO_FAST], [TO_SLOW, 1.0 - TO_SLOW]];

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
        let model = Model { x: V18::zeros(), p };
        Self { config, held, t0_ns: t_ns, t_ns, models: [model; 2], probability: [1.0 - TO_FAST, TO_FAST], updates: 0 }
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
        let prior = Self::held_prior(&held, held_covariance);
        for m in &mut self.models {
            for i in 0..6 {
                m.x[i] = 0.0;
                for j in 0..18 {
                    m.p[(i, j)] = 0.0;
                    m.p[(j, i)] = 0.0;
                }
            }
            m.p.fixed_view_mut::<6, 6>(0, 0).copy_from(&prior);
        }
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

    /// Probability, given the frames so far, that the camera moves faster than the
    /// configured prior allows (see [`MODEL_SCALES`]).
    pub fn fast_probability(&self) -> f64 {
        self.probability[1]
    }

    /// `model` predicted `dt` seconds on with its rate process noise scaled by `scale`.
    fn predict_model(&self, model: &Model, dt: f64, scale: f64) -> Model {
        if dt == 0.0 {
            return *model;
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
            let qa = s2 / tc * scale; // rate variance gained per second
            q[(6 + i, 6 + i)] = qa * dt.powi(3) / 3.0;
            q[(6 + i, 12 + i)] = qa * dt * dt / 2.0;
            q[(12 + i, 6 + i)] = qa * dt * dt / 2.0;
            q[(12 + i, 12 + i)] = qa * dt;
        }
        Model { x: f * model.x, p: f * model.p * f.transpose() + q }
    }

    /// The models' mixture with weights `w`: its mean and covariance (spread included).
    fn combine(models: &[Model; 2], w: &[f64; 2]) -> Model {
        let x = models[0].x * w[0] + models[1].x * w[1];
        let mut p = M18::zeros();
        for (m, &wi) in models.iter().zip(w) {
            let d = m.x - x;
            p += (m.p + d * d.transpose()) * wi;
        }
        Model { x, p: 0.5 * (p + p.transpose()) }
    }

    fn predicted(&self, t_ns: i64) -> (V18, M18) {
        let dt = ((t_ns - self.t_ns) as f64 * 1e-9).max(0.0);
        let models = [0, 1].map(|j| self.predict_model(&self.models[j], dt, MODEL_SCALES[j]));
        let m = Self::combine(&models, &self.probability);
        (m.x, m.p)
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
        let m = Self::combine(&self.models, &self.probability);
        self.estimate_of(&m.x, &m.p, self.t_ns)
    }

    /// The drift predicted at `t_ns` (no update).
    pub fn predict(&self, t_ns: i64) -> DriftEstimate {
        let (x, p) = self.predicted(t_ns);
        self.estimate_of(&x, &p, t_ns)
    }

    /// The held pose moved by the drift as of the last update.
    pub fn pose(&self) -> Pose {
        let m = Self::combine(&self.models, &self.probability);
        drifted_pose(&self.held, &m.x.fixed_rows::<6>(6).into_owned())
    }

    /// The held pose moved by the drift predicted at `t_ns`.
    pub fn predicted_pose(&self, t_ns: i64) -> Pose {
        drifted_pose(&self.held, &self.predicted(t_ns).0.fixed_rows::<6>(6).into_owned())
    }

    /// Feeds the pose solved from one frame's background corners at `t_ns`, with its
    /// covariance in the solver's step parameters. Returns the innovation's squared
    /// Mahalanobis distance under the model more likely before the frame (`None` when the
    /// measurement was unusable).
    ///
    /// One step of the interacting multiple model: each model starts from the mixture of
    /// both by the probabilities of switching into it, is predicted with its own process
    /// noise and updated with the frame; the models' probabilities are then weighted by the
    /// likelihood of their innovations. An innovation beyond [`GATE`] (a mis-detected frame)
    /// is down-weighted in each model, so it cannot flip the models by itself.
    pub fn update(&mut self, t_ns: i64, pose: &Pose, step_covariance: &Matrix6<f64>) -> Option<f64> {
        let (z, r) = pose_offset(&self.held, pose, step_covariance);
        if !(z.iter().all(|v| v.is_finite()) && r.iter().all(|v| v.is_finite())) {
            return None;
        }
        let dt = ((t_ns - self.t_ns) as f64 * 1e-9).max(0.0);
        let mut h = SMatrix::<f64, 6, 18>::zeros();
        for i in 0..6 {
            h[(i, i)] = 1.0;
            h[(i, 6 + i)] = 1.0;
        }
        // Mixing: the chance of being in model j now, and where each model comes from.
        let into = [0, 1].map(|j| SWITCH[0][j] * self.probability[0] + SWITCH[1][j] * self.probability[1]);
        let mut updated = self.models;
        let mut log_likelihood = [0.0; 2];
        let mut m2_of = [0.0; 2];
        for j in 0..2 {
            let w = [0, 1].map(|i| SWITCH[i][j] * self.probability[i] / into[j].max(f64::MIN_POSITIVE));
            let start = Self::combine(&self.models, &w);
            let pred = self.predict_model(&start, dt, MODEL_SCALES[j]);
            let y = z - h * pred.x;
            let hph = h * pred.p * h.transpose();
            let symmetric = |s: Matrix6<f64>| 0.5 * (s + s.transpose());
            let c = symmetric(hph + r).cholesky()?;
            let m2 = y.dot(&c.solve(&y));
            // Down-weight, so that the innovation sits near the gate.
            let (rr, c, m2_used) = if m2 > GATE {
                let rr = r * (m2 / GATE);
                let c = symmetric(hph + rr).cholesky()?;
                let m2_used = y.dot(&c.solve(&y));
                (rr, c, m2_used)
            } else {
                (r, c, m2)
            };
            let k = (c.solve(&(h * pred.p))).transpose(); // P Hᵀ S⁻¹ (P, S symmetric)
            let x = pred.x + k * y;
            // Joseph form keeps P symmetric and positive.
            let ikh = M18::identity() - k * h;
            let p = ikh * pred.p * ikh.transpose() + k * rr * k.transpose();
            updated[j] = Model { x, p: 0.5 * (p + p.transpose()) };
            let log_det: f64 = c.l().diagonal().iter().map(|v| 2.0 * v.ln()).sum();
            log_likelihood[j] = -0.5 * (m2_used + log_det);
            m2_of[j] = m2;
        }
        let best = log_likelihood[0].max(log_likelihood[1]);
        let weights = [0, 1].map(|j| into[j] * (log_likelihood[j] - best).exp());
        let total = weights[0] + weights[1];
        if !(total.is_finite() && total > 0.0) {
            return None;
        }
        self.models = updated;
        // A model is never ruled out for good: it can always be switched back into.
        self.probability = [0, 1].map(|j| (weights[j] / total).clamp(1e-9, 1.0 - 1e-9));
        self.t_ns = self.t_ns.max(t_ns);
        self.updates += 1;
        Some(if into[0] >= into[1] { m2_of[0] } else { m2_of[1] })
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

    /// A still camera that starts moving fast (0.02° and 0.2 mm within 2 s at 10 fps, some
    /// 400 × the prior's rate, each frame's step a third of one frame's noise) and stops
    /// again: the drift is followed (error below one frame's noise and a fraction of what
    /// holding the pose gives), the fast model weighs more than on a still camera while it
    /// moves and little once it is still again; a still camera stays still.
    #[test]
    fn a_fast_drift_is_followed_and_handed_back_to_the_slow_model() {
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        let held = Pose::from_rvec_tvec([0.1, -0.2, 0.05], [10.0, -20.0, 1000.0]);
        // One frame's pose noise: 1e-4 rad and 0.03 mm per axis.
        let r: Matrix6<f64> = Matrix6::from_diagonal(&Vector6::new(1e-8, 1e-8, 1e-8, 1e-3, 1e-3, 1e-3));
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let n = Normal::new(0.0, 1.0).unwrap();
        let noise = |rng: &mut rand_chacha::ChaCha8Rng| Vector6::from_fn(|i, _| n.sample(rng) * r[(i, i)].sqrt());
        let ji = offset_jacobian(&held).try_inverse().unwrap();
        let step = ji * r * ji.transpose();
        let total = Vector6::new(0.02f64.to_radians() * 0.6, 0.0, 0.02f64.to_radians() * 0.8, 0.0, 0.12, -0.16);
        let truth = |k: usize| total * ((k as f64 - 30.0) / 20.0).clamp(0.0, 1.0);
        let mut moving = DriftFilter::new(DriftConfig::default(), held, Some(&step), 0);
        let mut still = DriftFilter::new(DriftConfig::default(), held, Some(&step), 0);
        let (mut err_sq, mut held_sq, mut err_n, mut fast_sum, mut still_fast_sum) = (0.0f64, 0.0f64, 0usize, 0.0f64, 0.0f64);
        for k in 1..=100usize {
            let t = k as i64 * 100_000_000;
            moving.update(t, &drifted_pose(&held, &(truth(k) + noise(&mut rng))), &step).unwrap();
            still.update(t, &drifted_pose(&held, &noise(&mut rng)), &step).unwrap();
            let e = moving.estimate();
            if (30..=60).contains(&k) {
                err_sq += (e.centre_mm - truth(k).fixed_rows::<3>(3)).norm_squared();
                held_sq += truth(k).fixed_rows::<3>(3).norm_squared();
                err_n += 1;
                fast_sum += moving.fast_probability();
                still_fast_sum += still.fast_probability();
            }
        }
        let (rms, held_rms) = ((err_sq / err_n as f64).sqrt(), (held_sq / err_n as f64).sqrt());
        let (fast_mean, still_fast_mean) = (fast_sum / err_n as f64, still_fast_sum / err_n as f64);
        let (end, still_end) = (moving.estimate(), still.estimate());
        println!(
            "fast drift: centre error RMS {rms:.4} mm while moving (held: {held_rms:.4} mm), mean fast probability {fast_mean:.3} (a still camera's {still_fast_mean:.3}), {:.3} at the end; end {:.5}° {:.4} mm; still camera {:.5}° {:.4} mm",
            moving.fast_probability(),
            end.angle_deg(),
            end.shift_mm(),
            still_end.angle_deg(),
            still_end.shift_mm()
        );
        // One frame's centre noise is 0.03 mm per axis (0.052 mm in 3D); the drift is 0.2 mm.
        assert!(rms < 0.04 && rms < 0.35 * held_rms, "followed: {rms} (held {held_rms})");
        assert!(fast_mean > 2.0 * still_fast_mean, "the fast model leads while moving: {fast_mean} vs {still_fast_mean}");
        assert!(moving.fast_probability() < 0.2, "and hands back: {}", moving.fast_probability());
        assert!((end.angle_deg() - 0.02).abs() < 0.003 && (end.shift_mm() - 0.2).abs() < 0.03, "{} {}", end.angle_deg(), end.shift_mm());
        assert!(still_end.angle_deg() < 0.003 && still_end.shift_mm() < 0.03, "{} {}", still_end.angle_deg(), still_end.shift_mm());
    }
}
