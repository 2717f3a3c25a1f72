//! The start of the fit (module docs of [`crate::solve`], "Start"): Zhang's closed form,
//! OpenCV's centred fallback, and each view's pose alone under given intrinsics.

use nalgebra::{Matrix3, SMatrix, Vector2};

use tagdeflect_core::camera::{CameraIntrinsics, Pose};
use tagdeflect_estimate::camera_pose::camera_point_terms;
use tagdeflect_estimate::init::{homography, pose_from_homography};
use tagdeflect_estimate::lm::{minimize, Evaluation, LmOptions, PoseProblem};

use super::View;

/// Zhang's closed form: intrinsics (no skew, no distortion) from ≥ 3 homographies.
pub(super) fn zhang(hs: &[Matrix3<f64>], width: u32, height: u32) -> Option<CameraIntrinsics> {
    if hs.len() < 3 {
        return None;
    }
    let v = |h: &Matrix3<f64>, i: usize, j: usize| -> SMatrix<f64, 1, 6> {
        let (hi, hj) = (h.column(i), h.column(j));
        SMatrix::<f64, 1, 6>::from_row_slice(&[
            hi[0] * hj[0],
            hi[0] * hj[1] + hi[1] * hj[0],
            hi[1] * hj[1],
            hi[2] * hj[0] + hi[0] * hj[2],
            hi[2] * hj[1] + hi[1] * hj[2],
            hi[2] * hj[2],
        ])
    };
    // Condition the homographies: pixels scaled to ~1 around the image centre.
    let s = 2.0 / (width.max(height).max(1) as f64);
    let (ccx, ccy) = (0.5 * (width as f64 - 1.0), 0.5 * (height as f64 - 1.0));
    let t = Matrix3::new(s, 0.0, -s * ccx, 0.0, s, -s * ccy, 0.0, 0.0, 1.0);
    let mut vtv = SMatrix::<f64, 6, 6>::zeros();
    for h in hs {
        let h = t * h;
        let h = h / h.norm();
        let a = v(&h, 0, 1);
        let b = v(&h, 0, 0) - v(&h, 1, 1);
        // No skew: B12 = 0, added as a constraint row.
        vtv += a.transpose() * a + b.transpose() * b;
    }
    let skew_row = SMatrix::<f64, 1, 6>::from_row_slice(&[0.0, 1.0, 0.0, 0.0, 0.0, 0.0]);
    vtv += skew_row.transpose() * skew_row * (vtv.trace() + 1.0);
    let eig = vtv.symmetric_eigen();
    let (imin, _) = eig.eigenvalues.iter().enumerate().min_by(|a, b| a.1.total_cmp(b.1))?;
    let mut b = eig.eigenvectors.column(imin).into_owned();
    if b[0] < 0.0 {
        b = -b;
    }
    let (b11, b12, b22, b13, b23, b33) = (b[0], b[1], b[2], b[3], b[4], b[5]);
    let den = b11 * b22 - b12 * b12;
    if den <= 0.0 || b11 <= 0.0 {
        return None;
    }
    let v0 = (b12 * b13 - b11 * b23) / den;
    let lambda = b33 - (b13 * b13 + v0 * (b12 * b13 - b11 * b23)) / b11;
    if lambda / b11 <= 0.0 || lambda * b11 / den <= 0.0 {
        return None;
    }
    let alpha = (lambda / b11).sqrt();
    let beta = (lambda * b11 / den).sqrt();
    let u0 = -b13 * alpha * alpha / lambda;
    // Undo the conditioning.
    let k = CameraIntrinsics { width, height, fx: alpha / s, fy: beta / s, cx: u0 / s + ccx, cy: v0 / s + ccy, dist: [0.0; 5] };
    let ok = [k.fx, k.fy, k.cx, k.cy].iter().all(|v| v.is_finite())
        && k.cx > 0.0
        && k.cy > 0.0
        && k.cx < width as f64
        && k.cy < height as f64
        && (k.fx / k.fy - 1.0).abs() < 0.5;
    ok.then_some(k)
}

/// OpenCV's start: principal point at the image centre, focal lengths from the vanishing
/// points of every homography (least squares in 1/fx², 1/fy²).
pub(super) fn centred(hs: &[Matrix3<f64>], width: u32, height: u32, aspect: Option<f64>) -> Option<CameraIntrinsics> {
    let (cx, cy) = (0.5 * (width as f64 - 1.0), 0.5 * (height as f64 - 1.0));
    let t = Matrix3::new(1.0, 0.0, -cx, 0.0, 1.0, -cy, 0.0, 0.0, 1.0);
    let mut ata = nalgebra::Matrix2::zeros();
    let mut atb = Vector2::zeros();
    for h in hs {
        let h = t * h;
        let h = h / h.norm();
        let (h1, h2) = (h.column(0), h.column(1));
        let rows = [
            (Vector2::new(h1[0] * h2[0], h1[1] * h2[1]), -h1[2] * h2[2]),
            (Vector2::new(h1[0] * h1[0] - h2[0] * h2[0], h1[1] * h1[1] - h2[1] * h2[1]), -(h1[2] * h1[2] - h2[2] * h2[2])),
        ];
        for (a, b) in rows {
            ata += a * a.transpose();
            atb += a * b;
        }
    }
    let (fx, fy) = match aspect {
        Some(a) => {
            // fx = a fy: one unknown u = 1/fy², coefficient a⁻² on the first column.
            let c = Vector2::new(1.0 / (a * a), 1.0);
            let den = c.dot(&(ata * c));
            let u = c.dot(&atb) / den;
            if u.is_nan() || u <= 0.0 {
                return None;
            }
            let fy = 1.0 / u.sqrt();
            (a * fy, fy)
        }
        None => {
            let x = ata.try_inverse()? * atb;
            if !(x[0] > 0.0 && x[1] > 0.0) {
                return None;
            }
            (1.0 / x[0].sqrt(), 1.0 / x[1].sqrt())
        }
    };
    (fx.is_finite() && fy.is_finite()).then_some(CameraIntrinsics { width, height, fx, fy, cx, cy, dist: [0.0; 5] })
}

/// One view's pose alone (intrinsics fixed), by the solver's six-parameter LM.
struct ViewPose<'a> {
    k: &'a CameraIntrinsics,
    view: &'a View,
}

impl PoseProblem for ViewPose<'_> {
    fn evaluate(&self, pose: &Pose, with_jacobian: bool) -> Option<Evaluation> {
        let mut e = Evaluation::zero();
        for (x, u) in self.view.object.iter().zip(&self.view.image) {
            let (r, j) = camera_point_terms(self.k, pose, x, u)?;
            e.add(&r, &j, with_jacobian);
        }
        Some(e)
    }
}

/// The pose of one view for given intrinsics: homography of the undistorted points, then LM.
pub(super) fn view_pose(k: &CameraIntrinsics, view: &View) -> Option<Pose> {
    let plane: Vec<Vector2<f64>> = view.object.iter().map(|p| Vector2::new(p.x, p.y)).collect();
    let norm: Vec<Vector2<f64>> = view.image.iter().map(|p| k.undistort(p)).collect();
    let h = homography(&plane, &norm)?;
    let (r, t) = pose_from_homography(&h)?;
    let start = Pose { rotation: r, translation: t };
    let out = minimize(&ViewPose { k, view }, &start, &LmOptions { max_iterations: 30, ..LmOptions::default() })?;
    Some(out.pose)
}
