//! A view's edge offsets: each of its four edge lines moved along its normal — an edge
//! model's bias, which depends on where an edge falls on the pixel grid and so moves an edge
//! line as a whole, both its corners alike along its normal (a shift of the whole tag and a
//! change of its apparent size among them), which the pixel noise's covariance does not hold.
//! What such offsets do to the solve, per view: how far each moves the tag's centre, and how
//! much of them stays in the view's edge-offset residuals (the rest the rigid tag's pose
//! absorbs), so that their variance can be learned from the residuals
//! (`measure::model_drift`) and carried to the centre, each edge's offset a fully correlated
//! block of its two corners (docs/accuracy.md, "A tag's edge offsets as a model-error term").

use nalgebra::{Matrix3, Matrix3x4, Matrix4, Matrix4x6, Matrix6, Point2, Vector2};

/// What offsets of one view's four edge lines do to a solve.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ViewShift {
    /// The view's index in the solve's input slice.
    pub index: usize,
    /// The tag centre's move per pixel of each edge's offset along its normal
    /// ([`edge_normals`]; edge `i` joins corners `i` and `i + 1`), mm/px.
    pub centre_mm_per_px: Matrix3x4<f64>,
    /// The share of an edge offset's variance that stays in the view's edge-offset residual
    /// (per edge: the mean of its two corners' residuals along its normal) when every edge
    /// of every view used has an offset of that variance, independent from edge to edge:
    /// `Σ_u ‖M_vu‖²_F / 4`, `M_vu = E_v H⁻¹ E_uᵀ / 2 − δ_vu I`, row `i` of `E_v` the edge's
    /// normal times its two corners' Jacobians summed.
    pub residual_share: f64,
}

/// The unit normals of a view's four edges in the image (edge `i` from corner `i` to corner
/// `i + 1`).
pub fn edge_normals(corners: &[Point2<f64>; 4]) -> [Vector2<f64>; 4] {
    std::array::from_fn(|i| {
        let u = corners[(i + 1) % 4] - corners[i];
        Vector2::new(-u.y, u.x).normalize()
    })
}

/// Each view's [`ViewShift`] from its edges' Jacobians `E_v` (by input index) and the
/// solve's inverse normal matrix.
pub(super) fn view_shifts(edges: &[(usize, Matrix4x6<f64>)], h_inv: &Matrix6<f64>) -> Vec<ViewShift> {
    edges
        .iter()
        .map(|(index, ev)| {
            let residual_share = edges
                .iter()
                .map(|(u, eu)| {
                    let own = if u == index { Matrix4::identity() } else { Matrix4::zeros() };
                    (ev * h_inv * eu.transpose() * 0.5 - own).norm_squared()
                })
                .sum::<f64>()
                / 4.0;
            let step = h_inv * ev.transpose();
            ViewShift { index: *index, centre_mm_per_px: step.fixed_view::<3, 4>(3, 0).into_owned(), residual_share }
        })
        .collect()
}

/// The centre's covariance from edge offsets of variance `q_px2(index)` px² in each view,
/// independent from edge to edge, mm².
pub fn common_shift_covariance(shifts: &[ViewShift], q_px2: impl Fn(usize) -> f64) -> Matrix3<f64> {
    shifts.iter().map(|s| s.centre_mm_per_px * s.centre_mm_per_px.transpose() * q_px2(s.index).max(0.0)).sum()
}
