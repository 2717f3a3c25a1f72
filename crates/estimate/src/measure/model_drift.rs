//! The position error an edge model that is off causes, as the tags move across the pixels
//! (the σ widening of `TAGDEFLECT_SIGMA_WIDENING=on`; docs/accuracy.md, "σ widened by the
//! fits' model error").
//!
//! **Why not the fits' residual energy.** At an edge fit's optimum its residuals are
//! orthogonal to its Jacobian: the part of a wrong profile's misfit that moves the edge is
//! exactly the part the residuals do not show. What shows the error along the position is
//! the pattern across phases: a corner's bias depends on where the edges fall on the pixel
//! grid, so as the tag moves the bias changes, and the corners disagree with the rigid tag
//! differently from frame set to frame set.
//!
//! **The estimate.** For each view of a tag solved with others (the rigid tag's fit, so the
//! tag's motion cancels), its four corners' reprojection residuals `r_t` (px) are kept for the
//! tag's first full set (`r_0`) and its last (`r_{t−1}`), per camera and pose epoch (a
//! re-posed camera starts again). Per coordinate, with corner biases `b` and pixel noise `σ`,
//! `E(r_t − r_0)² = c (2σ² + D_t)` and `E(r_t − r_{t−1})² = c (2σ² + d_t)`, where
//! `D_t = E(b_t − b_0)²` is how far the bias moved since the tag's reference, `d_t` how far
//! it moved in one set (≈ 0: a tag moves a small part of a pixel a set), and
//! `c = (n − 6)/n` the share of an independent corner error a pose fit of `n` coordinates
//! leaves in its residuals. So `D = [E(r_t − r_0)² − E(r_t − r_{t−1})²] / c` is the variance
//! of the bias's change — a displacement's model error — per corner coordinate, with the
//! pixel noise cancelled, pooled over every tag and camera of the measurement. Carried to a
//! tag's centre as an independent corner error is, its covariance is `D / s² ×` the solve's
//! pixel-noise covariance (`s` the pooled corner noise that covariance was scaled by).
//!
//! **Where it goes.** Into the σ given out only (beside the camera poses' part, which the
//! smoother adds back too), never into the temporal estimate's weights: the bias changes
//! slowly, so averaging sets does not shrink it, and weighing sets by it would move the
//! positions (measured with the residual-energy widening: the Bayer scene 0.024 → 0.052 mm).

use nalgebra::{Matrix3, Vector2};

use crate::tag_pose::corner_residuals_px;
use crate::TagView;

/// One view's four corner residuals (px) with its camera and that camera's pose epoch.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct ViewResiduals {
    pub(super) camera: usize,
    /// The tag's frame set these were kept from (counted by [`TagResiduals`]).
    pub(super) set: u64,
    pub(super) epoch: u64,
    pub(super) residuals_px: [Vector2<f64>; 4],
}

/// A tag's corner residuals in one frame set (its views used, rigid tag fitted over them).
pub(super) type SetResiduals = Vec<ViewResiduals>;

/// The residuals of a solve's views used (`cameras[i]` saw `views[i]`; `rejected` left out).
pub(super) fn set_residuals(
    views: &[TagView],
    cameras: &[usize],
    rejected: &[usize],
    epochs: &[u64],
    tag_to_world: &tagdeflect_core::camera::Pose,
    size_mm: f64,
) -> SetResiduals {
    let used = (0..views.len()).filter(|i| !rejected.contains(i));
    used.filter_map(|i| {
        let residuals_px = corner_residuals_px(&views[i], tag_to_world, size_mm)?;
        Some(ViewResiduals { camera: cameras[i], set: 0, epoch: epochs[cameras[i]], residuals_px })
    })
    .collect()
}

/// What a tag keeps for the estimate: per camera its first full set's residuals in the
/// camera's pose epoch (the reference), and its last full set's.
#[derive(Debug, Clone, Default)]
pub(super) struct TagResiduals {
    first: SetResiduals,
    last: SetResiduals,
    /// Full sets kept so far.
    sets: u64,
}

/// The measurement's pooled sums (see the module docs).
#[derive(Debug, Clone, Default, PartialEq)]
pub(super) struct ModelDrift {
    /// `Σ (r_t − r_0)² / c` and `Σ (r_t − r_{t−1})² / c` over coordinates, and their count.
    from_first: f64,
    from_last: f64,
    coordinates: f64,
}

impl ModelDrift {
    /// Adds a tag's full set `now` against what the tag kept, then keeps it.
    pub(super) fn observe(&mut self, kept: &mut TagResiduals, mut now: SetResiduals) {
        let n = 8.0 * now.len() as f64;
        now.iter_mut().for_each(|v| v.set = kept.sets);
        kept.sets += 1;
        if now.len() >= 2 {
            self.add(&kept.first, &kept.last, &now, (n - 6.0) / n);
        }
        for v in &now {
            if find(&kept.first, v).is_none() {
                kept.first.retain(|f| f.camera != v.camera);
                kept.first.push(*v);
            }
        }
        kept.last = now;
    }

    /// Adds the corners of `now` seen in `first` and `last` (two different sets) by the same
    /// camera in the same pose epoch.
    fn add(&mut self, first: &SetResiduals, last: &SetResiduals, now: &SetResiduals, c: f64) {
        for v in now {
            let (Some(f), Some(l)) = (find(first, v), find(last, v)) else { continue };
            if f.set == l.set {
                continue;
            }
            for k in 0..4 {
                self.from_first += (v.residuals_px[k] - f.residuals_px[k]).norm_squared() / c;
                self.from_last += (v.residuals_px[k] - l.residuals_px[k]).norm_squared() / c;
                self.coordinates += 2.0;
            }
        }
    }

    /// `D`, px² per corner coordinate (0 when the noise explains the scatter), once 200
    /// coordinates were compared.
    pub(super) fn variance_px2(&self) -> Option<f64> {
        (self.coordinates >= 200.0).then(|| ((self.from_first - self.from_last) / self.coordinates).max(0.0))
    }

    /// The pixel noise that changes from one set to the next, px² per corner coordinate:
    /// `Σ(r_t − r_{t−1})² / (2 c · count)` (an upper bound: the bias's move in one set, `d`,
    /// is in it), once 200 coordinates were compared. The pooled corner noise `s²` holds
    /// this and the corners' bias that stays; only this part does not cancel from a
    /// displacement (`disp_sigma`).
    pub(super) fn white_variance_px2(&self) -> Option<f64> {
        (self.coordinates >= 200.0).then(|| self.from_last / (2.0 * self.coordinates))
    }

    /// The covariance the model error adds to a tag's centre: `D / s²` times the solve's
    /// pixel-noise covariance `noise` (scaled by the pooled corner noise `pooled_px`).
    pub(super) fn centre_covariance(&self, noise: &Matrix3<f64>, pooled_px: Option<f64>) -> Matrix3<f64> {
        match (self.variance_px2(), pooled_px) {
            (Some(d), Some(s)) if s > 0.0 => noise * (d / (s * s)),
            _ => Matrix3::zeros(),
        }
    }
}

/// The view of `set` by `v`'s camera in `v`'s pose epoch.
fn find(set: &SetResiduals, v: &ViewResiduals) -> Option<ViewResiduals> {
    set.iter().find(|w| w.camera == v.camera && w.epoch == v.epoch).copied()
}

/// Whether the σ given out carries the model error's position error:
/// `TAGDEFLECT_SIGMA_WIDENING=on` (a measurement; read once per process).
pub fn model_drift_switch() -> bool {
    static ON: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *ON.get_or_init(|| std::env::var("TAGDEFLECT_SIGMA_WIDENING").is_ok_and(|v| v == "on"))
}

/// Whether the tags' corner residuals are kept (both `D` and the white share come from
/// them): `TAGDEFLECT_CORNER_RESIDUALS=off` keeps none, so the displacement's σ takes the
/// whole pixel noise and no model error (a measurement of their cost, docs/performance.md;
/// read once per process).
pub(super) fn residuals_kept() -> bool {
    static KEPT: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *KEPT.get_or_init(|| std::env::var("TAGDEFLECT_CORNER_RESIDUALS").map_or(true, |v| v != "off"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_distr::{Distribution, StandardNormal};

    /// `sets` frame sets of `tags` tags seen by 3 cameras: each corner coordinate's residual
    /// is pixel noise `noise_px` plus a bias that wanders (a random walk of `step_px` a set,
    /// as a bias following the tag's phase does), both reduced by `c` as a fit's residuals are.
    fn drift_of(noise_px: f64, step_px: f64, sets: usize) -> ModelDrift {
        let (tags, cameras) = (8, 3);
        let c: f64 = (24.0 - 6.0) / 24.0;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0x2545_f491_4f6c_dd1d);
        let mut normal = || -> f64 { StandardNormal.sample(&mut rng) };
        let mut drift = ModelDrift::default();
        let mut kept = vec![TagResiduals::default(); tags];
        let mut bias = vec![[[0.0; 2]; 4]; tags * cameras];
        for _ in 0..sets {
            for (t, kept) in kept.iter_mut().enumerate() {
                let now: SetResiduals = (0..cameras)
                    .map(|cam| {
                        let b = &mut bias[t * cameras + cam];
                        let residuals_px = std::array::from_fn(|k| {
                            let mut r = [0.0; 2];
                            for (a, r) in r.iter_mut().enumerate() {
                                b[k][a] += step_px * normal();
                                *r = c.sqrt() * (b[k][a] + noise_px * normal());
                            }
                            Vector2::new(r[0], r[1])
                        });
                        ViewResiduals { camera: cam, set: 0, epoch: 0, residuals_px }
                    })
                    .collect();
                drift.observe(kept, now);
            }
        }
        drift
    }

    #[test]
    fn pixel_noise_alone_gives_no_model_error() {
        let drift = drift_of(0.05, 0.0, 40);
        let d = drift.variance_px2().expect("enough coordinates");
        assert!(d < 0.05 * 0.05 * 0.1, "D {d} px² against noise 0.0025 px²");
        let noise = Matrix3::identity() * 1e-6;
        assert!(drift.centre_covariance(&noise, Some(0.05)).norm() < 1e-7);
    }

    #[test]
    fn a_bias_that_moves_with_the_tag_is_measured_through_the_noise() {
        // A bias that wanders by 0.01 px a set beside 0.05 px of noise: after 40 sets it has
        // moved by ~0.06 px RMS from where it started; D averages E(b_t − b_0)² over the sets.
        let drift = drift_of(0.05, 0.01, 40);
        let d = drift.variance_px2().unwrap();
        // E(b_t − b_0)² = (t − 1)·step² at set t (the first set is the reference); averaged
        // over t = 2…39: ~19.5 step² = 0.00195 px².
        let expected = 19.5 * 0.01 * 0.01;
        assert!((d - expected).abs() < 0.3 * expected, "D {d} px² against {expected}");
        let noise = Matrix3::identity() * 1e-6;
        let widened = drift.centre_covariance(&noise, Some(0.05));
        assert!((widened[(0, 0)] - 1e-6 * d / 0.0025).abs() < 1e-12);
        assert_eq!(widened[(0, 1)], 0.0);
    }

    #[test]
    fn nothing_is_told_before_enough_corners_were_compared_or_across_a_re_pose() {
        let drift = drift_of(0.05, 0.01, 2);
        assert_eq!(drift.variance_px2(), None, "two sets compare nothing yet");
        let mut drift = ModelDrift::default();
        let mut kept = TagResiduals::default();
        let view = |epoch, r: f64| ViewResiduals { camera: 0, set: 0, epoch, residuals_px: [Vector2::new(r, r); 4] };
        for (epoch, r) in [(0, 0.0), (0, 0.1), (1, 0.5), (1, 0.6)] {
            drift.observe(&mut kept, vec![view(epoch, r), ViewResiduals { camera: 1, ..view(epoch, r) }]);
        }
        assert_eq!(drift.coordinates, 0.0, "a re-posed camera is not compared with its old pose's residuals");
        drift.observe(&mut kept, vec![view(1, 0.7), ViewResiduals { camera: 1, ..view(1, 0.7) }]);
        assert_eq!(drift.coordinates, 16.0, "its new epoch's first set is its reference");
        assert!((drift.from_first - drift.from_last - 16.0 * (0.04 - 0.01) / (10.0 / 16.0)).abs() < 1e-9);
    }
}
