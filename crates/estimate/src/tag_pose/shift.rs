//! A view's common shift: its four corners moved by one 2-D offset — an edge model's bias
//! shared by a tag's edges in one camera (a pixel-phase bias of the profile moves all four
//! lines alike), which the pixel noise's covariance does not hold. What such a shift does to
//! the solve, per view: how far it moves the tag's centre, and how much of it stays in the
//! view's mean corner residual (the rest the rigid tag's pose absorbs), so that its variance
//! can be learned from the residuals (`measure::model_drift`) and carried to the centre as a
//! fully correlated block of the view's corners (docs/accuracy.md, "A tag's common shift").

use nalgebra::{Matrix2, Matrix2x6, Matrix3, Matrix3x2, Matrix6};

/// What a common shift of one view's corners does to a solve.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ViewShift {
    /// The view's index in the solve's input slice.
    pub index: usize,
    /// The tag centre's move per pixel of the view's common shift (world x y z by image
    /// x y), mm/px.
    pub centre_mm_per_px: Matrix3x2<f64>,
    /// The share of a common shift's variance that stays in this view's mean corner
    /// residual, per coordinate, when every view used has a shift of that variance,
    /// independent between views: `Σ_u ‖M_vu‖²_F / 2`, `M_vu = J̄_v H⁻¹ J̄_uᵀ / 4 − δ_vu I`,
    /// `J̄_v` the sum of the view's four corners' Jacobians (≈ 0 for one view alone: its
    /// shift is a move of the tag; about (2V − 3)/2V with V views).
    pub residual_share: f64,
}

/// Each view's [`ViewShift`] from its corners' summed Jacobian `J̄_v` (by input index) and the
/// solve's inverse normal matrix.
pub(super) fn view_shifts(summed: &[(usize, Matrix2x6<f64>)], h_inv: &Matrix6<f64>) -> Vec<ViewShift> {
    summed
        .iter()
        .map(|(index, jv)| {
            let residual_share = summed
                .iter()
                .map(|(u, ju)| {
                    let own = if u == index { Matrix2::identity() } else { Matrix2::zeros() };
                    (jv * h_inv * ju.transpose() * 0.25 - own).norm_squared()
                })
                .sum::<f64>()
                / 2.0;
            let step = h_inv * jv.transpose();
            ViewShift { index: *index, centre_mm_per_px: step.fixed_view::<3, 2>(3, 0).into_owned(), residual_share }
        })
        .collect()
}

/// The centre's covariance from common shifts of variance `q_px2(index)` px² per coordinate
/// in each view, independent between views, mm².
pub fn common_shift_covariance(shifts: &[ViewShift], q_px2: impl Fn(usize) -> f64) -> Matrix3<f64> {
    shifts.iter().map(|s| s.centre_mm_per_px * s.centre_mm_per_px.transpose() * q_px2(s.index).max(0.0)).sum()
}
