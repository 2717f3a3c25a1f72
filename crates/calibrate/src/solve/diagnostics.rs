//! What a calibration says about its views: each view's residuals and pose alone, each
//! view's pull on the intrinsics (for the guard rails), and how a systematic corner shift
//! moves the intrinsics (module docs of [`crate::solve`], "Systematic corner errors").

use nalgebra::{DMatrix, DVector, SMatrix, Vector2, Vector6};

use tagdeflect_core::camera::{CameraIntrinsics, Pose};
use tagdeflect_estimate::camera_pose::camera_point_terms;

use super::joint::normal_equations;
use super::start::view_pose;
use super::{basis, Calibration, SolveOptions, View};

/// How the calibration `c` of `views` moves, to first order, per pixel of a systematic
/// displacement of the detected corners: point `i` of view `v` moved by `shift[v][i]`
/// (pixels per pixel of the bias). The poses are free and absorb what they can:
/// `Δθ = −(JᵀJ)⁻¹ Jᵀ ∂r/∂δ` over intrinsics and poses, with `Jᵀ ∂r/∂δ` the change of the
/// gradient `Jᵀr` when the corners move by `shift` (exact: `r` is affine in the corners and
/// `J` does not depend on them). Returns the change of the nine intrinsics (zero for fixed
/// ones); `None` when `shift` does not match `views` or the normal equations are singular.
pub fn bias_sensitivity(
    c: &Calibration,
    views: &[View],
    options: &SolveOptions,
    shift: &[Vec<Vector2<f64>>],
) -> Option<SMatrix<f64, 9, 1>> {
    if shift.len() != views.len() || views.len() != c.poses.len() || views.iter().zip(shift).any(|(v, s)| s.len() != v.image.len()) {
        return None;
    }
    let k = &c.intrinsics;
    let b = basis(options, k.fx / k.fy);
    let m = b.ncols();
    let (a, g0) = normal_equations(k, &c.poses, views, &b)?;
    let moved: Vec<View> = views
        .iter()
        .zip(shift)
        .map(|(v, s)| View { name: v.name.clone(), object: v.object.clone(), image: v.image.iter().zip(s).map(|(p, d)| p + d).collect() })
        .collect();
    let (_, g1) = normal_equations(k, &c.poses, &moved, &b)?;
    // Scaled to unit diagonal as in `finish`: A = D Â D.
    let n = a.nrows();
    let d: Vec<f64> = (0..n).map(|i| a[(i, i)].max(1e-300).sqrt()).collect();
    let an = DMatrix::from_fn(n, n, |i, j| a[(i, j)] / (d[i] * d[j]));
    let rhs = DVector::from_fn(n, |i, _| (g1[i] - g0[i]) / d[i]);
    let y = an.cholesky()?.solve(&rhs);
    let dq = DVector::from_fn(m, |i, _| -y[i] / d[i]);
    let dtheta = &b * dq;
    let out = SMatrix::<f64, 9, 1>::from_iterator(dtheta.iter().copied());
    out.iter().all(|v| v.is_finite()).then_some(out)
}

/// One view's pose fitted alone under fixed intrinsics `k` (PnP: homography start, then LM)
/// and its reprojection RMS (pixels, `√(mean |r|²)` over the points); `None` when no pose
/// is found.
pub fn view_pnp(k: &CameraIntrinsics, view: &View) -> Option<(Pose, f64)> {
    let pose = view_pose(k, view)?;
    let r = residuals(k, &pose, view);
    let rms = (r.iter().map(|r| r.norm_squared()).sum::<f64>() / r.len().max(1) as f64).sqrt();
    rms.is_finite().then_some((pose, rms))
}

/// Sum of squared residuals of one view with its pose fitted alone under intrinsics `k`
/// (`None` when no pose is found).
pub(crate) fn view_ssr(k: &CameraIntrinsics, view: &View) -> Option<f64> {
    let pose = view_pose(k, view)?;
    residuals(k, &pose, view).iter().map(|r| r.norm_squared()).sum::<f64>().into()
}

/// Every view's pull on the free intrinsics at a calibration's minimum, whitened: `L⁻¹ g_v`
/// with `g_v` the view's gradient of ½ SSR in the free intrinsics with its own pose
/// eliminated (Schur complement) and `L Lᵀ` the total reduced information. The pulls sum to
/// zero at the minimum; views of one camera scatter around zero like noise, while the
/// views of a second camera (or focus) all pull one way — the seed of
/// [`crate::guard::split_views`].
pub(crate) fn view_pulls(c: &Calibration, views: &[View], options: &SolveOptions) -> Option<Vec<DVector<f64>>> {
    let k = &c.intrinsics;
    let b = basis(options, k.fx / k.fy);
    let m = b.ncols();
    let mut total = DMatrix::<f64>::zeros(m, m);
    let mut grads = Vec::with_capacity(views.len());
    for (pose, view) in c.poses.iter().zip(views) {
        let mut aii = DMatrix::<f64>::zeros(m, m);
        let mut aip = DMatrix::<f64>::zeros(m, 6);
        let mut app = nalgebra::Matrix6::<f64>::zeros();
        let mut gi = DVector::<f64>::zeros(m);
        let mut gp = Vector6::<f64>::zeros();
        for (x, u) in view.object.iter().zip(&view.image) {
            let (r, jp) = camera_point_terms(k, pose, x, u)?;
            let ji9 = k.project_intrinsics_jacobian(&pose.transform(x))?;
            let ji = DMatrix::from_fn(2, 9, |r, c| ji9[(r, c)]) * &b;
            let jit = ji.transpose();
            aii += &jit * &ji;
            aip += &jit * DMatrix::from_fn(2, 6, |r, c| jp[(r, c)]);
            app += jp.transpose() * jp;
            gi += &jit * DVector::from_column_slice(r.as_slice());
            gp += jp.transpose() * r;
        }
        let app_inv = app.try_inverse()?;
        let app_inv = DMatrix::from_fn(6, 6, |r, c| app_inv[(r, c)]);
        let gp = DVector::from_column_slice(gp.as_slice());
        total += &aii - &aip * &app_inv * aip.transpose();
        grads.push(&gi - &aip * &app_inv * gp);
    }
    // Whiten in the scaled parameters (unit diagonal), as `finish` inverts.
    let d: Vec<f64> = (0..m).map(|i| total[(i, i)].max(1e-300).sqrt()).collect();
    let tn = DMatrix::from_fn(m, m, |i, j| total[(i, j)] / (d[i] * d[j]));
    let l = tn.cholesky()?.l();
    grads
        .into_iter()
        .map(|g| {
            let gn = DVector::from_fn(m, |i, _| g[i] / d[i]);
            l.solve_lower_triangular(&gn)
        })
        .collect()
}

/// Residuals (projection − detection, pixels) of one view under a calibration.
pub(crate) fn residuals(k: &CameraIntrinsics, pose: &Pose, view: &View) -> Vec<Vector2<f64>> {
    view.object.iter().zip(&view.image).map(|(x, u)| k.project(&pose.transform(x)).map_or(Vector2::repeat(f64::NAN), |q| q - u)).collect()
}
