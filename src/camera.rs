//! The camera model: OpenCV pinhole with radial-tangential distortion (k1, k2, p1, p2, k3),
//! its analytic Jacobians, undistortion, and rigid poses.
//!
//! Pixel convention (OpenCV): pixel centres at integer coordinates, (0, 0) is the centre of
//! the top-left pixel. Poses map world to camera: `x_cam = R x_world + t` (mm).

use nalgebra::{Matrix2, Matrix2x3, Matrix3, Point2, Rotation3, Vector2, Vector3};
use serde::{Deserialize, Serialize};

/// Intrinsic parameters of one camera.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct CameraIntrinsics {
    /// Image width, pixels (0 when unknown, e.g. a calibration file without it).
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// Focal length x, pixels.
    pub fx: f64,
    /// Focal length y, pixels.
    pub fy: f64,
    /// Principal point x, pixels.
    pub cx: f64,
    /// Principal point y, pixels.
    pub cy: f64,
    /// k1, k2, p1, p2, k3.
    pub dist: [f64; 5],
}

impl CameraIntrinsics {
    /// Applies distortion to normalised coordinates (x/z, y/z).
    pub fn distort(&self, xn: Vector2<f64>) -> Vector2<f64> {
        let [k1, k2, p1, p2, k3] = self.dist;
        let (x, y) = (xn.x, xn.y);
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
        Vector2::new(x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x), y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y)
    }

    /// Jacobian of [`distort`](Self::distort) with respect to the normalised coordinates.
    pub fn distort_jacobian(&self, xn: Vector2<f64>) -> Matrix2<f64> {
        let [k1, k2, p1, p2, k3] = self.dist;
        let (x, y) = (xn.x, xn.y);
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
        let dradial_dr2 = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2);
        let dxx = radial + x * dradial_dr2 * 2.0 * x + 2.0 * p1 * y + p2 * 6.0 * x;
        let dxy = x * dradial_dr2 * 2.0 * y + 2.0 * p1 * x + p2 * 2.0 * y;
        let dyx = y * dradial_dr2 * 2.0 * x + p1 * 2.0 * x + 2.0 * p2 * y;
        let dyy = radial + y * dradial_dr2 * 2.0 * y + p1 * 6.0 * y + 2.0 * p2 * x;
        Matrix2::new(dxx, dxy, dyx, dyy)
    }

    /// Projects a point in camera coordinates (mm) to pixels. `None` behind the camera.
    pub fn project(&self, p: &Vector3<f64>) -> Option<Point2<f64>> {
        if p.z <= 1e-9 {
            return None;
        }
        let d = self.distort(Vector2::new(p.x / p.z, p.y / p.z));
        Some(Point2::new(self.fx * d.x + self.cx, self.fy * d.y + self.cy))
    }

    /// Projection and its Jacobian d(pixel)/d(p_cam).
    pub fn project_with_jacobian(&self, p: &Vector3<f64>) -> Option<(Point2<f64>, Matrix2x3<f64>)> {
        if p.z <= 1e-9 {
            return None;
        }
        let iz = 1.0 / p.z;
        let xn = Vector2::new(p.x * iz, p.y * iz);
        let d = self.distort(xn);
        let jd = self.distort_jacobian(xn);
        // d(xn)/d(p)
        let jn = Matrix2x3::new(iz, 0.0, -p.x * iz * iz, 0.0, iz, -p.y * iz * iz);
        let jf = Matrix2::new(self.fx, 0.0, 0.0, self.fy);
        Some((Point2::new(self.fx * d.x + self.cx, self.fy * d.y + self.cy), jf * jd * jn))
    }

    /// Jacobian of [`project`](Self::project) with respect to the intrinsics, columns in the
    /// order fx, fy, cx, cy, k1, k2, p1, p2, k3 (for calibration). `None` behind the camera.
    pub fn project_intrinsics_jacobian(&self, p: &Vector3<f64>) -> Option<nalgebra::SMatrix<f64, 2, 9>> {
        if p.z <= 1e-9 {
            return None;
        }
        let (x, y) = (p.x / p.z, p.y / p.z);
        let d = self.distort(Vector2::new(x, y));
        let r2 = x * x + y * y;
        let (fx, fy) = (self.fx, self.fy);
        let mut j = nalgebra::SMatrix::<f64, 2, 9>::zeros();
        j[(0, 0)] = d.x;
        j[(1, 1)] = d.y;
        j[(0, 2)] = 1.0;
        j[(1, 3)] = 1.0;
        // Radial terms: d/dk = (x, y) * r2^n.
        for (col, pow) in [(4, r2), (5, r2 * r2), (8, r2 * r2 * r2)] {
            j[(0, col)] = fx * x * pow;
            j[(1, col)] = fy * y * pow;
        }
        // Tangential: dx/dp1 = 2xy, dy/dp1 = r2 + 2y²; dx/dp2 = r2 + 2x², dy/dp2 = 2xy.
        j[(0, 6)] = fx * 2.0 * x * y;
        j[(1, 6)] = fy * (r2 + 2.0 * y * y);
        j[(0, 7)] = fx * (r2 + 2.0 * x * x);
        j[(1, 7)] = fy * 2.0 * x * y;
        Some(j)
    }

    /// Removes distortion: pixel → normalised coordinates, by Gauss–Newton on
    /// [`distort`](Self::distort) (exact to ~1e-12 inside the calibrated field).
    pub fn undistort(&self, px: &Point2<f64>) -> Vector2<f64> {
        let target = Vector2::new((px.x - self.cx) / self.fx, (px.y - self.cy) / self.fy);
        let mut x = target;
        for _ in 0..20 {
            let r = self.distort(x) - target;
            if r.norm_squared() < 1e-24 {
                break;
            }
            let j = self.distort_jacobian(x);
            match j.try_inverse() {
                Some(ji) => x -= ji * r,
                None => break,
            }
        }
        x
    }

    /// True when a pixel lies inside the image with `margin` pixels to spare.
    pub fn in_image(&self, px: &Point2<f64>, margin: f64) -> bool {
        px.x >= margin - 0.5
            && px.y >= margin - 0.5
            && px.x <= self.width as f64 - 0.5 - margin
            && px.y <= self.height as f64 - 0.5 - margin
    }
}

/// A rigid transform from world to camera: `x_cam = rotation * x_world + translation` (mm).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose {
    /// Rotation world → camera.
    pub rotation: Rotation3<f64>,
    /// Translation, mm.
    pub translation: Vector3<f64>,
}

impl Default for Pose {
    fn default() -> Self {
        Self::identity()
    }
}

impl Pose {
    /// The identity pose.
    pub fn identity() -> Self {
        Self { rotation: Rotation3::identity(), translation: Vector3::zeros() }
    }

    /// From an OpenCV rotation vector (axis × angle, rad) and a translation.
    pub fn from_rvec_tvec(rvec: [f64; 3], tvec: [f64; 3]) -> Self {
        Self { rotation: Rotation3::new(Vector3::from(rvec)), translation: Vector3::from(tvec) }
    }

    /// The rotation as an OpenCV rotation vector.
    pub fn rvec(&self) -> [f64; 3] {
        let v = self.rotation.scaled_axis();
        [v.x, v.y, v.z]
    }

    /// Maps a world point into this frame.
    pub fn transform(&self, p: &Vector3<f64>) -> Vector3<f64> {
        self.rotation * p + self.translation
    }

    /// The inverse transform (camera → world).
    pub fn inverse(&self) -> Pose {
        let r = self.rotation.inverse();
        Pose { rotation: r, translation: -(r * self.translation) }
    }

    /// `self ∘ other`: first `other`, then `self`.
    pub fn compose(&self, other: &Pose) -> Pose {
        Pose { rotation: self.rotation * other.rotation, translation: self.rotation * other.translation + self.translation }
    }

    /// Camera centre in world coordinates.
    pub fn centre(&self) -> Vector3<f64> {
        -(self.rotation.inverse() * self.translation)
    }

    /// Rotation angle between two poses, radians (accurate near zero, unlike an `acos` of
    /// the trace).
    pub fn angle_to(&self, other: &Pose) -> f64 {
        rotation_angle(&(self.rotation.inverse() * other.rotation))
    }
}

/// Angle of a rotation, radians, accurate at small angles: `atan2(|vee(R − Rᵀ)| / 2, (tr R − 1) / 2)`.
pub fn rotation_angle(r: &Rotation3<f64>) -> f64 {
    let m = r.matrix();
    let s = Vector3::new(m[(2, 1)] - m[(1, 2)], m[(0, 2)] - m[(2, 0)], m[(1, 0)] - m[(0, 1)]).norm() / 2.0;
    let c = (m.trace() - 1.0) / 2.0;
    s.atan2(c)
}

/// Skew-symmetric matrix of a vector (`skew(a) * b = a × b`).
pub fn skew(v: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cam() -> CameraIntrinsics {
        CameraIntrinsics { width: 640, height: 480, fx: 500.0, fy: 510.0, cx: 319.5, cy: 239.5, dist: [-0.25, 0.08, 0.001, -0.0005, -0.01] }
    }

    #[test]
    fn jacobian_matches_finite_differences() {
        let c = cam();
        let p = Vector3::new(30.0, -20.0, 400.0);
        let (_, j) = c.project_with_jacobian(&p).unwrap();
        for k in 0..3 {
            let mut dp = Vector3::zeros();
            dp[k] = 1e-4;
            let a = c.project(&(p + dp)).unwrap();
            let b = c.project(&(p - dp)).unwrap();
            let fd = (a - b) / 2e-4;
            assert!((fd.x - j[(0, k)]).abs() < 1e-5 && (fd.y - j[(1, k)]).abs() < 1e-5, "column {k}: {fd} vs {j}");
        }
    }

    #[test]
    fn intrinsics_jacobian_matches_finite_differences() {
        let c = cam();
        let p = Vector3::new(-60.0, 45.0, 300.0);
        let j = c.project_intrinsics_jacobian(&p).unwrap();
        let get = |k: &CameraIntrinsics, i: usize| match i {
            0 => k.fx,
            1 => k.fy,
            2 => k.cx,
            3 => k.cy,
            _ => k.dist[i - 4],
        };
        let set = |k: &mut CameraIntrinsics, i: usize, v: f64| match i {
            0 => k.fx = v,
            1 => k.fy = v,
            2 => k.cx = v,
            3 => k.cy = v,
            _ => k.dist[i - 4] = v,
        };
        for i in 0..9 {
            let h = 1e-6 * get(&c, i).abs().max(1e-3);
            let (mut a, mut b) = (c, c);
            set(&mut a, i, get(&c, i) + h);
            set(&mut b, i, get(&c, i) - h);
            let fd = (a.project(&p).unwrap() - b.project(&p).unwrap()) / (2.0 * h);
            let tol = 1e-5 * (1.0 + j[(0, i)].abs().max(j[(1, i)].abs()));
            assert!((fd.x - j[(0, i)]).abs() < tol && (fd.y - j[(1, i)]).abs() < tol, "column {i}: {fd} vs {}, {}", j[(0, i)], j[(1, i)]);
        }
    }

    #[test]
    fn undistort_inverts_distort() {
        let c = cam();
        for &(x, y) in &[(0.0, 0.0), (0.3, -0.2), (-0.4, 0.35)] {
            let p = Vector3::new(x, y, 1.0);
            let px = c.project(&p).unwrap();
            let n = c.undistort(&px);
            assert!((n.x - x).abs() < 1e-10 && (n.y - y).abs() < 1e-10);
        }
    }

    #[test]
    fn pose_inverse_and_rvec_round_trip() {
        let p = Pose::from_rvec_tvec([0.1, -0.2, 0.3], [10.0, 20.0, 30.0]);
        let q = p.compose(&p.inverse());
        assert!(q.translation.norm() < 1e-12 && rotation_angle(&q.rotation) < 1e-12);
        let r = p.rvec();
        assert!((r[0] - 0.1).abs() < 1e-12 && (r[1] + 0.2).abs() < 1e-12 && (r[2] - 0.3).abs() < 1e-12);
    }
}
