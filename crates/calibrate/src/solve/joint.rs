//! The joint fit: Levenberg–Marquardt over the free intrinsics and every view's pose at
//! once, from the closed-form start, with the covariance of the result.

use nalgebra::{DMatrix, DVector, Matrix2x6, Matrix3, SMatrix, Vector2, Vector6};

use tagdeflect_core::camera::{CameraIntrinsics, Pose};
use tagdeflect_estimate::camera_pose::camera_point_terms;
use tagdeflect_estimate::init::homography;
use tagdeflect_estimate::lm::retract;

use super::start::{centred, view_pose, zhang};
use super::{basis, from_vector, to_vector, Calibration, SolveError, SolveOptions, View};

/// Sum of squared residuals of all views (None when a point falls behind a camera).
pub(super) fn cost(k: &CameraIntrinsics, poses: &[Pose], views: &[View]) -> Option<f64> {
    let mut ssr = 0.0;
    for (pose, view) in poses.iter().zip(views) {
        for (x, u) in view.object.iter().zip(&view.image) {
            let p = k.project(&pose.transform(x))?;
            ssr += (p - u).norm_squared();
        }
    }
    Some(ssr)
}

/// Normal equations of the joint problem: `JᵀJ`, `Jᵀr` over (q, poses).
pub(super) fn normal_equations(
    k: &CameraIntrinsics,
    poses: &[Pose],
    views: &[View],
    b: &DMatrix<f64>,
) -> Option<(DMatrix<f64>, DVector<f64>)> {
    let m = b.ncols();
    let n = m + 6 * views.len();
    let mut a = DMatrix::<f64>::zeros(n, n);
    let mut g = DVector::<f64>::zeros(n);
    let bt = b.transpose();
    for (v, (pose, view)) in poses.iter().zip(views).enumerate() {
        let o = m + 6 * v;
        let mut aii = DMatrix::<f64>::zeros(m, m);
        let mut aip = DMatrix::<f64>::zeros(m, 6);
        let mut app = nalgebra::Matrix6::<f64>::zeros();
        let mut gi = DVector::<f64>::zeros(m);
        let mut gp = Vector6::<f64>::zeros();
        for (x, u) in view.object.iter().zip(&view.image) {
            let (r, jp): (Vector2<f64>, Matrix2x6<f64>) = camera_point_terms(k, pose, x, u)?;
            let ji9 = k.project_intrinsics_jacobian(&pose.transform(x))?;
            // 2 × m: the intrinsics Jacobian in the free directions.
            let ji = DMatrix::from_fn(2, 9, |r, c| ji9[(r, c)]) * b;
            let jit = ji.transpose();
            aii += &jit * &ji;
            aip += &jit * DMatrix::from_fn(2, 6, |r, c| jp[(r, c)]);
            app += jp.transpose() * jp;
            gi += &jit * DVector::from_column_slice(r.as_slice());
            gp += jp.transpose() * r;
        }
        let _ = &bt;
        let mut blk = a.view_mut((0, 0), (m, m));
        blk += &aii;
        a.view_mut((0, o), (m, 6)).copy_from(&aip);
        a.view_mut((o, 0), (6, m)).copy_from(&aip.transpose());
        a.view_mut((o, o), (6, 6)).copy_from(&app);
        let mut gblk = g.rows_mut(0, m);
        gblk += &gi;
        g.rows_mut(o, 6).copy_from(&gp);
    }
    Some((a, g))
}

/// Calibrates from the views: closed-form start, then LM over intrinsics and all poses.
/// `width` × `height` is the image size in pixels.
pub(crate) fn calibrate(views: &[View], width: u32, height: u32, options: &SolveOptions) -> Result<Calibration, SolveError> {
    let usable: Vec<&View> = views.iter().filter(|v| v.object.len() >= 6).collect();
    if usable.len() < 2 || usable.len() != views.len() {
        return Err(SolveError::TooFewViews { views: usable.len(), need: 2 });
    }
    let hs: Vec<Matrix3<f64>> = views
        .iter()
        .filter_map(|v| {
            let plane: Vec<Vector2<f64>> = v.object.iter().map(|p| Vector2::new(p.x, p.y)).collect();
            let img: Vec<Vector2<f64>> = v.image.iter().map(|p| p.coords).collect();
            homography(&plane, &img)
        })
        .collect();
    let aspect_hold = options.fix_aspect_ratio.then(|| options.aspect_ratio.unwrap_or(1.0));
    let mut start_kind = "zhang";
    let zh = if options.fix_principal_point { None } else { zhang(&hs, width, height) };
    let mut k = match zh {
        Some(mut k) => {
            if let Some(a) = aspect_hold {
                let f = 0.5 * (k.fx / a + k.fy);
                k.fx = a * f;
                k.fy = f;
            }
            k
        }
        None => {
            start_kind = "centred";
            centred(&hs, width, height, aspect_hold).ok_or(SolveError::NoStart)?
        }
    };
    if options.fix_principal_point {
        k.cx = 0.5 * (width as f64 - 1.0);
        k.cy = 0.5 * (height as f64 - 1.0);
    }
    let aspect = k.fx / k.fy;
    let mut poses = Vec::with_capacity(views.len());
    for v in views {
        poses.push(view_pose(&k, v).ok_or(SolveError::NoStart)?);
    }
    let b = basis(options, aspect);
    let m = b.ncols();
    let n = m + 6 * views.len();
    let npts: usize = views.iter().map(|v| v.object.len()).sum();
    if 2 * npts <= n {
        return Err(SolveError::TooFewViews { views: views.len(), need: views.len() + 1 });
    }
    let apply = |k: &CameraIntrinsics, poses: &[Pose], delta: &DVector<f64>| -> (CameraIntrinsics, Vec<Pose>) {
        let dq = delta.rows(0, m).into_owned();
        let dtheta = &b * dq;
        let theta = to_vector(k) + SMatrix::<f64, 9, 1>::from_iterator(dtheta.iter().copied());
        let k2 = from_vector(&theta, width, height);
        let p2 =
            poses.iter().enumerate().map(|(i, p)| retract(p, &Vector6::from_iterator(delta.rows(m + 6 * i, 6).iter().copied()))).collect();
        (k2, p2)
    };
    let mut ssr = cost(&k, &poses, views).ok_or(SolveError::NoStart)?;
    let mut lambda = 1e-3;
    let mut iterations = 0;
    for _ in 0..200 {
        iterations += 1;
        let Some((a, g)) = normal_equations(&k, &poses, views, &b) else { return Err(SolveError::NoStart) };
        let mut accepted = false;
        for _ in 0..15 {
            let mut ad = a.clone();
            for i in 0..n {
                ad[(i, i)] += lambda * a[(i, i)].max(1e-12);
            }
            let Some(chol) = ad.cholesky() else {
                lambda *= 10.0;
                continue;
            };
            let delta = -chol.solve(&g);
            let (k2, p2) = apply(&k, &poses, &delta);
            match cost(&k2, &p2, views) {
                Some(c) if c.is_finite() && c <= ssr => {
                    let gain = ssr - c;
                    k = k2;
                    poses = p2;
                    let old = ssr;
                    ssr = c;
                    lambda = (lambda * 0.3).max(1e-12);
                    accepted = true;
                    if gain <= 1e-14 * old.max(1e-300) {
                        return finish(k, poses, views, &b, ssr, iterations, start_kind);
                    }
                    break;
                }
                _ => lambda *= 10.0,
            }
        }
        if !accepted {
            break;
        }
    }
    finish(k, poses, views, &b, ssr, iterations, start_kind)
}

fn finish(
    k: CameraIntrinsics,
    poses: Vec<Pose>,
    views: &[View],
    b: &DMatrix<f64>,
    ssr: f64,
    iterations: usize,
    start: &'static str,
) -> Result<Calibration, SolveError> {
    let (a, _) = normal_equations(&k, &poses, views, b).ok_or(SolveError::Singular)?;
    let m = b.ncols();
    let n = a.nrows();
    let npts: usize = views.iter().map(|v| v.object.len()).sum();
    let dof = (2 * npts).saturating_sub(n).max(1);
    let s2 = ssr / dof as f64;
    // Scale to unit diagonal before inverting (focal lengths and k3 differ by 10⁶).
    let d: Vec<f64> = (0..n).map(|i| a[(i, i)].max(1e-300).sqrt()).collect();
    let an = DMatrix::from_fn(n, n, |i, j| a[(i, j)] / (d[i] * d[j]));
    let inv = an.cholesky().ok_or(SolveError::Singular)?.inverse();
    let sq = DMatrix::from_fn(m, m, |i, j| inv[(i, j)] / (d[i] * d[j]) * s2);
    let cov_d = b * sq * b.transpose();
    let covariance = SMatrix::<f64, 9, 9>::from_fn(|i, j| cov_d[(i, j)]);
    let view_rms_px: Vec<f64> = poses
        .iter()
        .zip(views)
        .map(|(p, v)| {
            let s: f64 =
                v.object.iter().zip(&v.image).map(|(x, u)| k.project(&p.transform(x)).map_or(f64::NAN, |q| (q - u).norm_squared())).sum();
            (s / v.object.len() as f64).sqrt()
        })
        .collect();
    Ok(Calibration {
        intrinsics: k,
        poses,
        covariance,
        view_rms_px,
        rms_px: (ssr / npts as f64).sqrt(),
        sigma_px: s2.sqrt(),
        parameters: n,
        iterations,
        start,
        corner_bias: Vec::new(),
    })
}
