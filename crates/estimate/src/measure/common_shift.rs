//! A tag's edge offsets per camera, learned from the views' disagreement beyond the noise
//! (with `TAGDEFLECT_CORNER_CORRELATION=edges`; docs/accuracy.md, "A tag's edge offsets as a model-error term").
//!
//! **What it is.** An edge model that is off biases each fitted edge line along its normal
//! by an amount that depends on where the edge falls on the pixel grid: both corners of the
//! edge move alike (the tag shifts in the image, or looks larger or smaller). The pixel
//! noise's covariance (corners correlated through their edge lines) has no such term, and
//! the corners' residuals show it only in part — the rigid tag's pose, fitted over every
//! view, absorbs what the views agree on. What is left of it is each edge's **offset
//! residual** `o_i`, the mean of its two corners' residuals along its normal: with an offset
//! of variance `q` on every edge of every view (independent from edge to edge), `E o_i²`
//! holds `q ρ_v` beside the noise, `ρ_v` the view's residual share
//! ([`ViewShift::residual_share`](crate::tag_pose::ViewShift)).
//!
//! **The two variances, per camera, the noise cancelled as `model_drift` does.** With `o_0`
//! the view's offset residuals in the tag's reference set and `o_{t−1}` in its last:
//! * the offsets' change since the reference, the displacement's model error:
//!   `q_moved = Σ(|o_t − o_0|² − |o_t − o_{t−1}|²) / Σ 4ρ` (a tag moves a small part of a
//!   pixel a set: the last set shares the bias, the noise is new);
//! * the offsets themselves, the position's: `q = Σ(|o_t|² − |o_t − o_{t−1}|² / 2) / Σ 4ρ`
//!   (the white part taken out with the set-to-set difference).
//!
//! Each is carried to a tag's centre with each edge's offset a fully correlated block of its
//! two corners along its normal (`common_shift_covariance`).

use nalgebra::{Vector2, Vector4};

/// View comparisons a camera needs before its variances are told.
const MIN_VIEWS: f64 = 50.0;

/// One camera's sums (see the module docs).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
struct CameraSums {
    moved: f64,
    level: f64,
    share: f64,
    views: f64,
}

/// The measurement's sums per camera.
#[derive(Debug, Clone, Default, PartialEq)]
pub(super) struct CommonShift {
    cameras: Vec<CameraSums>,
}

/// A view's edge-offset residuals now, in the tag's reference set and in its last set, px.
pub(super) struct MeanResiduals {
    pub(super) now: Vector4<f64>,
    pub(super) first: Vector4<f64>,
    pub(super) last: Vector4<f64>,
}

impl CommonShift {
    /// Adds one view of `camera` with residual share `share` (skipped below 0.05: offsets
    /// the pose absorbs tell nothing).
    pub(super) fn add(&mut self, camera: usize, share: f64, m: &MeanResiduals) {
        if share.is_nan() || share < 0.05 {
            return;
        }
        if self.cameras.len() <= camera {
            self.cameras.resize(camera + 1, CameraSums::default());
        }
        let step = (m.now - m.last).norm_squared();
        let c = &mut self.cameras[camera];
        c.moved += (m.now - m.first).norm_squared() - step;
        c.level += m.now.norm_squared() - step / 2.0;
        c.share += 4.0 * share;
        c.views += 1.0;
    }

    fn told(&self, camera: usize) -> Option<&CameraSums> {
        self.cameras.get(camera).filter(|c| c.views >= MIN_VIEWS && c.share > 0.0)
    }

    /// The variance of the camera's edge offsets' change since a tag's reference, px² per
    /// edge (0 when the noise explains the scatter; `None` before enough views).
    pub(super) fn moved_px2(&self, camera: usize) -> Option<f64> {
        self.told(camera).map(|c| (c.moved / c.share).max(0.0))
    }

    /// The variance of the camera's edge offsets, px² per edge.
    pub(super) fn level_px2(&self, camera: usize) -> Option<f64> {
        self.told(camera).map(|c| (c.level / c.share).max(0.0))
    }
}

/// A view's edge-offset residuals: per edge (`normals`, edge `i` from corner `i` to `i + 1`)
/// the mean of its two corners' residuals `r` along its normal.
pub(super) fn offsets(r: &[Vector2<f64>; 4], normals: &[Vector2<f64>; 4]) -> Vector4<f64> {
    Vector4::from_fn(|i, _| normals[i].dot(&(r[i] + r[(i + 1) % 4])) / 2.0)
}

/// Corner residuals `r` less their edges' offsets `o` (each corner less the offsets of its
/// two edges along their normals): what an edge's offset does not reach.
pub(super) fn less_offsets(r: &[Vector2<f64>; 4], o: &Vector4<f64>, normals: &[Vector2<f64>; 4]) -> [Vector2<f64>; 4] {
    std::array::from_fn(|k| r[k] - normals[k] * o[k] - normals[(k + 3) % 4] * o[(k + 3) % 4])
}
