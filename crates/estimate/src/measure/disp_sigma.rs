//! The σ of a tag's displacement from its zero (the feed's `disp_sigma_mm`; docs/accuracy.md,
//! "The displacement's σ").
//!
//! A displacement is `x̂_t − z_0`: the estimate now minus the tag's first solve (its zero).
//! Its error is `e_t − v_0`, the estimate's error minus the zero's. What the two share
//! cancels: the held camera poses' errors (the same poses, until a camera is re-posed) and
//! the part of the edge model's bias that has not moved since the zero. What is left:
//!
//! `Cov(e_t − v_0) = P_t + N_0 − C_t − C_tᵀ + M_t (+ the poses' parts after a re-pose)`
//!
//! * The pixel-noise covariances are scaled by the pooled corner noise `s²`, the scatter of
//!   one set's corners about the rigid tag: the noise that changes from set to set and the
//!   corners' bias that stays, which cancels from a displacement with the zero's. So the
//!   pixel-noise terms (`P_t + N_0 − C_t − C_tᵀ`) are taken at the white share
//!   `w = σ_w² / s²` (≤ 1), `σ_w²` from the corners' set-to-set change
//!   (`model_drift::ModelDrift::white_variance_px2`); `w = 1` until that is known.
//! * `P_t` the estimator's covariance of the position (pixel noise; a partial set's camera
//!   poses where the filter took them), `N_0` the zero's pixel-noise covariance;
//! * `C_t = Cov(e_t, v_0)`, because the estimate still holds some of the zero's measurement.
//!   The temporal filter starts at the zero (`e_0 = v_0`, so `C_0 = N_0` on the position and
//!   `0` on the rate); each update makes `e_t = (I − K_t H)(F_t e_{t−1} − w_t) + K_t v_t` with
//!   `w_t`, `v_t` independent of `v_0`, so `C_t = (I − K_t H) F_t C_{t−1}`, and for the
//!   optimal gain `I − K_t H = P_t P⁻_t⁻¹` (posterior times the inverse of the prediction,
//!   the factor the smoother uses): the cross-covariance follows from the filter's own
//!   covariances, on the mixture's moments as the smoother does. A restart of the filter
//!   (a tag unseen for long) sets it to zero. The per-set estimator holds nothing of the
//!   zero: `C_t = 0`.
//! * `M_t` the edge model's error that moved since the zero: `D / s²` times the solve's
//!   pixel-noise covariance (`model_drift`, `D` the pooled variance of the corner bias's
//!   change since the tag's reference). This, not the σ floor of the absolute position,
//!   is what averaging sets does not shrink in a displacement.
//! * After a camera that saw the zero was re-posed, its pose's errors no longer cancel: that
//!   camera's part of the zero's camera-poses covariance and its part of today's are added
//!   (the cameras held since still cancel).

use nalgebra::{Matrix3, SMatrix};

use crate::smooth::DispStep;
use crate::temporal::Step;

type Cross = SMatrix<f64, 6, 3>;

/// What a displacement's covariance is made of now ([`DispZero::covariance`]).
#[derive(Debug, Clone, Copy)]
pub(super) struct DispInputs<'a> {
    /// The estimate's position covariance, mm² (the filter's when `temporal`).
    pub(super) estimate: &'a Matrix3<f64>,
    /// Whether the estimate is the temporal filter's (it holds some of the zero).
    pub(super) temporal: bool,
    /// The white share of the pixel noise ([`white_share`]).
    pub(super) white: f64,
    /// The edge model's error moved since the zero, mm².
    pub(super) model: &'a Matrix3<f64>,
    /// Today's camera-poses parts by camera.
    pub(super) pose_parts: &'a PoseParts,
    /// The cameras' pose epochs, by camera.
    pub(super) epochs: &'a [u64],
}

/// What a tag's displacement σ keeps of its zero.
#[derive(Debug, Clone)]
pub(super) struct DispZero {
    /// The zero's pixel-noise covariance `N_0`, mm².
    noise: Matrix3<f64>,
    /// Each camera that saw the zero: its index, its pose epoch then and its part of the
    /// zero's camera-poses covariance, mm².
    cameras: Vec<(usize, u64, Matrix3<f64>)>,
    /// `Cov(filter state error, v_0)` (position and rate rows), mm².
    cross: Cross,
    /// The time of the last filter step followed, ns.
    followed_ns: Option<i64>,
}

/// Each camera's part of a solve's camera-poses covariance: (camera index, mm²).
pub(super) type PoseParts = [(usize, Matrix3<f64>)];

impl DispZero {
    /// The zero of a tag first solved with pixel-noise covariance `noise` and the camera-poses
    /// parts `pose_parts` of the cameras that saw it, in pose epochs `epochs` (by camera).
    pub(super) fn new(noise: Matrix3<f64>, pose_parts: &PoseParts, epochs: &[u64]) -> DispZero {
        let mut cross = Cross::zeros();
        cross.fixed_view_mut::<3, 3>(0, 0).copy_from(&noise);
        let cameras = pose_parts.iter().map(|&(c, part)| (c, epochs.get(c).copied().unwrap_or(0), part)).collect();
        DispZero { noise, cameras, cross, followed_ns: None }
    }

    /// The camera poses' errors that no longer cancel from the displacement: for each camera
    /// that saw the zero and was re-posed since (`epochs` by camera), its part of the zero's
    /// covariance and its part of today's (`now`). The cameras held since cancel.
    fn re_posed_part(&self, now: &PoseParts, epochs: &[u64]) -> Matrix3<f64> {
        let mut sum = Matrix3::zeros();
        for &(cam, e, zero_part) in &self.cameras {
            if epochs.get(cam).is_some_and(|&current| current != e) {
                sum += zero_part + now.iter().filter(|(c, _)| *c == cam).map(|(_, p)| p).sum::<Matrix3<f64>>();
            }
        }
        sum
    }

    /// Carries the cross-covariance over the filter's latest step (once per step; the
    /// filter's first step is the zero itself).
    pub(super) fn follow(&mut self, step: &Step) {
        if self.followed_ns.is_none() && step.restart {
            self.followed_ns = Some(step.t_ns);
            return;
        }
        if self.followed_ns == Some(step.t_ns) {
            return;
        }
        self.followed_ns = Some(step.t_ns);
        self.cross = match (step.restart, step.p_pred.try_inverse()) {
            (false, Some(pred_inv)) => step.p * pred_inv * step.f * self.cross,
            _ => Cross::zeros(),
        };
    }

    /// The displacement's covariance, mm², from the estimate's position covariance with the
    /// white share of the pixel noise, the model error moved since the zero, and today's
    /// camera-poses parts (a camera's, with the zero's, added when that camera saw the zero
    /// and was re-posed since).
    pub(super) fn covariance(&self, now: &DispInputs<'_>) -> Matrix3<f64> {
        let cov: Matrix3<f64> = self.terms(now).iter().sum();
        (cov + cov.transpose()) * 0.5
    }

    /// The covariance's terms, as [`DispZero::covariance`] sums them: `w·P`, `w·N_0`,
    /// `−w·(C + Cᵀ)`, `M` and the re-posed cameras' parts, mm².
    pub(super) fn terms(&self, now: &DispInputs<'_>) -> [Matrix3<f64>; 5] {
        let c: Matrix3<f64> = if now.temporal { self.cross.fixed_view::<3, 3>(0, 0).into_owned() } else { Matrix3::zeros() };
        let w = now.white;
        [now.estimate * w, self.noise * w, -(c + c.transpose()) * w, *now.model, self.re_posed_part(now.pose_parts, now.epochs)]
    }
}

/// Whether each tag's displacement σ terms are printed to stderr, one `DISP_TERMS` line a
/// tag a set: `TAGDEFLECT_DISP_SIGMA_TERMS=print` (a measurement; read once per process).
pub(super) fn terms_printed() -> bool {
    static ON: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *ON.get_or_init(|| std::env::var("TAGDEFLECT_DISP_SIGMA_TERMS").is_ok_and(|v| v == "print"))
}

/// Prints a tag's displacement σ terms (see [`terms_printed`]): its id, the set's time, the
/// displacement, then each term's diagonal (x y z, mm²): `w·P`, `w·N_0`, `−w·(C + Cᵀ)`, `M`,
/// re-posed cameras, the monocular departure.
pub(super) fn print_terms(id: u32, t_ns: i64, disp: &nalgebra::Vector3<f64>, terms: &[Matrix3<f64>]) {
    let mut line = format!("DISP_TERMS {id} {t_ns} {:.6} {:.6} {:.6}", disp.x, disp.y, disp.z);
    for m in terms {
        line.push_str(&format!(" {:.4e} {:.4e} {:.4e}", m[(0, 0)], m[(1, 1)], m[(2, 2)]));
    }
    eprintln!("{line}");
}

impl DispZero {
    /// What a smoother needs to give the smoothed displacement its σ at this step (the
    /// arguments as [`DispZero::covariance`]'s): this step's cross-covariance and the terms
    /// that do not depend on the estimate.
    pub(super) fn smoothing_part(&self, white: f64, model: &Matrix3<f64>, pose_parts: &PoseParts, epochs: &[u64]) -> DispStep {
        let rest = self.noise * white + model + self.re_posed_part(pose_parts, epochs);
        DispStep { cross: self.cross, white, rest }
    }
}

/// The white share of the pooled corner noise `pooled_px` (see the module docs): 1 until
/// the set-to-set noise `white_px2` is known.
pub(super) fn white_share(white_px2: Option<f64>, pooled_px: Option<f64>) -> f64 {
    match (white_px2, pooled_px) {
        (Some(w), Some(s)) if s > 0.0 => (w / (s * s)).clamp(0.0, 1.0),
        _ => 1.0,
    }
}

/// The σ per axis of a covariance, mm.
pub(super) fn axis_sigma(cov: &Matrix3<f64>) -> nalgebra::Vector3<f64> {
    nalgebra::Vector3::new(cov[(0, 0)], cov[(1, 1)], cov[(2, 2)]).map(|v| v.max(0.0).sqrt())
}

/// Whether the displacement σ leaves the edge model's moved error out:
/// `TAGDEFLECT_DISP_SIGMA_DRIFT=off` (a measurement; read once per process).
pub(super) fn drift_left_out() -> bool {
    static OFF: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *OFF.get_or_init(|| std::env::var("TAGDEFLECT_DISP_SIGMA_DRIFT").is_ok_and(|v| v == "off"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::temporal::{TagFilter, TemporalConfig};
    use nalgebra::Vector3;
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};

    /// A tag at rest measured with white noise σ: the displacement's error `x̂_t − z_0` over
    /// many runs has the variance the derivation gives.
    #[test]
    fn the_displacement_variance_matches_its_scatter_over_runs() {
        let (sigma, sets, runs) = (0.003, 60usize, 400usize);
        let noise = Matrix3::identity() * sigma * sigma;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(42);
        let n = Normal::new(0.0, sigma).unwrap();
        let (mut sq, mut predicted) = (vec![0.0; sets], vec![0.0; sets]);
        for _ in 0..runs {
            let z0 = Vector3::new(n.sample(&mut rng), n.sample(&mut rng), n.sample(&mut rng));
            let mut f = TagFilter::new(TemporalConfig::default(), 0, z0, &noise);
            let mut zero = DispZero::new(noise, &[(0, Matrix3::zeros()), (1, Matrix3::zeros())], &[0, 0]);
            zero.follow(f.last_step());
            for (k, (sq, predicted)) in sq.iter_mut().zip(predicted.iter_mut()).enumerate().skip(1) {
                let z = Vector3::new(n.sample(&mut rng), n.sample(&mut rng), n.sample(&mut rng));
                let u = f.update(k as i64 * 33_333_333, z, &noise, &(noise * 9.0), false);
                zero.follow(f.last_step());
                let cov = zero.covariance(&DispInputs {
                    estimate: &u.covariance,
                    temporal: true,
                    white: 1.0,
                    model: &Matrix3::zeros(),
                    pose_parts: &[],
                    epochs: &[0, 0],
                });
                *sq += (u.centre.z - z0.z).powi(2) / runs as f64;
                *predicted += cov[(2, 2)] / runs as f64;
            }
        }
        for k in [2, 10, 59] {
            let ratio = sq[k] / predicted[k];
            println!("set {k}: scatter {:.3e} mm², predicted {:.3e} mm², ratio {ratio:.3}", sq[k], predicted[k]);
            assert!((0.8..=1.25).contains(&ratio), "set {k}: scatter / predicted {ratio:.3}");
        }
    }

    /// The same tag at rest, its lines smoothed (`replay --smooth`): the smoothed
    /// displacement's error over many runs has the variance the smoother's pass gives (the
    /// filtered line's printed beside it).
    #[test]
    fn the_smoothed_displacement_variance_matches_its_scatter_over_runs() {
        use crate::smooth::{FixedLag, TagStep};
        use tagdeflect_core::feed::{FeedLine, FeedTag};
        let (sigma, sets, runs) = (0.003, 40usize, 400usize);
        let noise = Matrix3::identity() * sigma * sigma;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let n = Normal::new(0.0, sigma).unwrap();
        let (mut sq, mut predicted, mut filtered) = (vec![0.0; sets], vec![0.0; sets], vec![0.0; sets]);
        for _ in 0..runs {
            let mut sample = || Vector3::new(n.sample(&mut rng), n.sample(&mut rng), n.sample(&mut rng));
            let z0 = sample();
            let mut f = TagFilter::new(TemporalConfig::default(), 0, z0, &noise);
            let mut zero = DispZero::new(noise, &[(0, Matrix3::zeros()), (1, Matrix3::zeros())], &[0, 0]);
            let mut lag = FixedLag::new(10, Vector3::new(0.0, 1.0, 0.0), Default::default());
            let mut out = Vec::new();
            for k in 0..sets {
                if k > 0 {
                    f.update(k as i64 * 33_333_333, sample(), &noise, &(noise * 9.0), false);
                }
                zero.follow(f.last_step());
                let cov = zero.covariance(&DispInputs {
                    estimate: &f.covariance(),
                    temporal: true,
                    white: 1.0,
                    model: &Matrix3::zeros(),
                    pose_parts: &[],
                    epochs: &[0, 0],
                });
                filtered[k] += cov[(2, 2)] / runs as f64;
                let disp = (f.centre() - z0).into();
                let tag = FeedTag {
                    id: 0,
                    pos_mm: f.centre().into(),
                    disp_mm: disp,
                    views: 2,
                    sigma_mm: None,
                    disp_sigma_mm: None,
                    reproj_px: None,
                };
                let disp_step = Some(zero.smoothing_part(1.0, &Matrix3::zeros(), &[], &[0, 0]));
                let step = TagStep {
                    id: 0,
                    step: *f.last_step(),
                    pose_part: Matrix3::zeros(),
                    floor: Matrix3::zeros(),
                    disp: disp_step,
                    departure_from: None,
                };
                let line = FeedLine { seq: k as u64, t_ns: k as i64 * 33_333_333, tags: vec![tag], ..FeedLine::default() };
                out.extend(lag.push(line, vec![step]));
            }
            out.extend(lag.finish());
            for (k, line) in out.iter().enumerate() {
                let t = &line.tags[0];
                sq[k] += t.disp_mm[2].powi(2) / runs as f64;
                predicted[k] += t.disp_sigma_mm.expect("a smoothed displacement σ")[2].powi(2) / runs as f64;
            }
        }
        for k in [1, 5, 20, 35] {
            let ratio = sq[k] / predicted[k];
            println!(
                "set {k}: smoothed scatter {:.3e} mm², predicted {:.3e} (filtered {:.3e}), ratio {ratio:.3}",
                sq[k], predicted[k], filtered[k]
            );
            assert!((0.8..=1.25).contains(&ratio), "set {k}: scatter / predicted {ratio:.3}");
        }
    }

    #[test]
    fn a_re_posed_camera_adds_its_own_poses_parts_and_the_per_set_estimate_holds_nothing_of_the_zero() {
        let noise = Matrix3::identity() * 1e-6;
        // The zero seen by cameras 0 and 2 (epochs 3 and 5), each with its part of the
        // camera-poses covariance.
        let zero = DispZero::new(noise, &[(0, Matrix3::identity() * 4e-6), (2, Matrix3::identity() * 1e-6)], &[3, 0, 5]);
        let now = Matrix3::identity() * 2e-6;
        let pose = [(0, Matrix3::identity() * 3e-6), (1, Matrix3::identity() * 7e-6), (2, Matrix3::identity() * 0.5e-6)];
        let same = zero.covariance(&DispInputs {
            estimate: &now,
            temporal: false,
            white: 1.0,
            model: &Matrix3::zeros(),
            pose_parts: &pose,
            epochs: &[3, 9, 5],
        });
        assert!((same[(0, 0)] - 3e-6).abs() < 1e-15, "a camera that did not see the zero changes nothing");
        // Camera 2 re-posed: its part then (1e-6) and now (0.5e-6); camera 0, held, cancels.
        let moved = zero.covariance(&DispInputs {
            estimate: &now,
            temporal: false,
            white: 1.0,
            model: &Matrix3::zeros(),
            pose_parts: &pose,
            epochs: &[3, 0, 6],
        });
        assert!((moved[(0, 0)] - 4.5e-6).abs() < 1e-15, "{moved}");
        // Both re-posed: both cameras' parts, then and now.
        let both = zero.covariance(&DispInputs {
            estimate: &now,
            temporal: false,
            white: 1.0,
            model: &Matrix3::zeros(),
            pose_parts: &pose,
            epochs: &[4, 0, 6],
        });
        assert!((both[(0, 0)] - 11.5e-6).abs() < 1e-15, "{both}");
        let half = zero.covariance(&DispInputs {
            estimate: &now,
            temporal: false,
            white: 0.5,
            model: &Matrix3::zeros(),
            pose_parts: &pose,
            epochs: &[3, 9, 5],
        });
        assert!((half[(0, 0)] - 1.5e-6).abs() < 1e-15, "the corners' bias that stays cancels: {half}");
        assert!((white_share(Some(0.02), Some(0.2)) - 0.5).abs() < 1e-12);
        assert_eq!(white_share(None, Some(0.2)), 1.0);
        assert_eq!(white_share(Some(0.09), Some(0.2)), 1.0);
    }
}
