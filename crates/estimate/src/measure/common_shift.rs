//! A tag's common shift per camera, learned from the views' disagreement beyond the noise
//! (with `TAGDEFLECT_CORNER_CORRELATION=edges`; docs/accuracy.md, "A tag's common shift").
//!
//! **What it is.** An edge model that is off biases each fitted edge by an amount that
//! depends on where the edge falls on the pixel grid; a tag's four edges in one camera share
//! much of it, so the four corners move together: a 2-D shift of the whole tag in that view.
//! The pixel noise's covariance (corners correlated through their edge lines) has no such
//! term, and the corners' residuals show it only in part — the rigid tag's pose, fitted over
//! every view, absorbs what the views agree on. What is left of it is the view's **mean
//! corner residual** `ā_v`: with a shift of variance `q` per coordinate in every view
//! (independent between views), `E|ā_v|²` holds `2 q ρ_v` beside the noise, `ρ_v` the
//! view's residual share ([`ViewShift::residual_share`](crate::tag_pose::ViewShift)).
//!
//! **The two variances, per camera, the noise cancelled as `model_drift` does.** With `ā_0`
//! the view's mean residual in the tag's reference set and `ā_{t−1}` in its last:
//! * the shift's change since the reference, the displacement's model error:
//!   `q_moved = Σ(|ā_t − ā_0|² − |ā_t − ā_{t−1}|²) / Σ 2ρ` (a tag moves a small part of a
//!   pixel a set: the last set shares the bias, the noise is new);
//! * the shift itself, the position's: `q = Σ(|ā_t|² − |ā_t − ā_{t−1}|² / 2) / Σ 2ρ` (the
//!   white part of the mean residual taken out with the set-to-set difference).
//!
//! Each is carried to a tag's centre as a fully correlated block of the view's four corners
//! (`common_shift_covariance`).

use nalgebra::Vector2;

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

/// A view's mean corner residual now, in the tag's reference set and in its last set, px.
pub(super) struct MeanResiduals {
    pub(super) now: Vector2<f64>,
    pub(super) first: Vector2<f64>,
    pub(super) last: Vector2<f64>,
}

impl CommonShift {
    /// Adds one view of `camera` with residual share `share` (skipped below 0.05: a shift
    /// the pose absorbs tells nothing).
    pub(super) fn add(&mut self, camera: usize, share: f64, m: &MeanResiduals) {
        if !(share >= 0.05) {
            return;
        }
        if self.cameras.len() <= camera {
            self.cameras.resize(camera + 1, CameraSums::default());
        }
        let step = (m.now - m.last).norm_squared();
        let c = &mut self.cameras[camera];
        c.moved += (m.now - m.first).norm_squared() - step;
        c.level += m.now.norm_squared() - step / 2.0;
        c.share += 2.0 * share;
        c.views += 1.0;
    }

    fn told(&self, camera: usize) -> Option<&CameraSums> {
        self.cameras.get(camera).filter(|c| c.views >= MIN_VIEWS && c.share > 0.0)
    }

    /// The variance of the camera's common shift's change since a tag's reference, px² per
    /// coordinate (0 when the noise explains the scatter; `None` before enough views).
    pub(super) fn moved_px2(&self, camera: usize) -> Option<f64> {
        self.told(camera).map(|c| (c.moved / c.share).max(0.0))
    }

    /// The variance of the camera's common shift, px² per coordinate.
    pub(super) fn level_px2(&self, camera: usize) -> Option<f64> {
        self.told(camera).map(|c| (c.level / c.share).max(0.0))
    }
}

/// The mean of four corner residuals.
pub(super) fn mean(r: &[Vector2<f64>; 4]) -> Vector2<f64> {
    r.iter().sum::<Vector2<f64>>() / 4.0
}
