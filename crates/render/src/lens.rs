//! The simulator's own lens: OpenCV's pinhole camera with Brown–Conrady distortion (k1, k2,
//! p1, p2, k3), written here again, plainly, from the numbers of the intrinsics only.
//!
//! The scenes must not share the product's lens code (`tagdeflect_core::camera`): were the
//! renderer to trace its rays with the product's undistortion, a wrong sign or term in the
//! product's model would be rendered into the images and measured back out of them, and no
//! accuracy test could see it. With this model a bug in the product's distortion shows as
//! an error against truth on every distorted camera.
//!
//! Convention (OpenCV): normalised coordinates `(x, y) = (X/Z, Y/Z)`, `r² = x² + y²`,
//! `x_d = x·(1 + k1 r² + k2 r⁴ + k3 r⁶) + 2 p1 x y + p2 (r² + 2x²)`,
//! `y_d = y·(1 + k1 r² + k2 r⁴ + k3 r⁶) + p1 (r² + 2y²) + 2 p2 x y`, pixel
//! `u = fx x_d + cx`, `v = fy y_d + cy` (pixel centres at integers).

use nalgebra::{Point2, Vector3};
use tagdeflect_core::camera::CameraIntrinsics;

/// A lens: focal lengths and principal point (px) and the five distortion coefficients.
#[derive(Debug, Clone, Copy)]
pub struct Lens {
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    k1: f64,
    k2: f64,
    p1: f64,
    p2: f64,
    k3: f64,
}

impl Lens {
    /// The lens of a camera's intrinsics (only their numbers are read).
    pub fn of(k: &CameraIntrinsics) -> Lens {
        let [k1, k2, p1, p2, k3] = k.dist;
        Lens { fx: k.fx, fy: k.fy, cx: k.cx, cy: k.cy, k1, k2, p1, p2, k3 }
    }

    /// Distorted normalised coordinates of the undistorted `(x, y)`.
    fn distorted(&self, x: f64, y: f64) -> (f64, f64) {
        let r2 = x * x + y * y;
        let radial = 1.0 + self.k1 * r2 + self.k2 * r2 * r2 + self.k3 * r2 * r2 * r2;
        (
            x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x),
            y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y,
        )
    }

    /// The pixel where the camera-frame point `p` (Z forward) is seen; `None` behind the
    /// camera.
    pub fn pixel(&self, p: &Vector3<f64>) -> Option<Point2<f64>> {
        if p.z <= 1e-9 {
            return None;
        }
        let (xd, yd) = self.distorted(p.x / p.z, p.y / p.z);
        Some(Point2::new(self.fx * xd + self.cx, self.fy * yd + self.cy))
    }

    /// The undistorted normalised ray `(X/Z, Y/Z)` through pixel `(u, v)`: the distortion
    /// inverted by Newton's method, its 2 × 2 Jacobian by central differences (the model is
    /// a polynomial: the differences are exact to rounding), until the step is below 1e-15.
    pub fn ray(&self, u: f64, v: f64) -> (f64, f64) {
        let (xd, yd) = ((u - self.cx) / self.fx, (v - self.cy) / self.fy);
        let (mut x, mut y) = (xd, yd);
        let h = 1e-6;
        for _ in 0..50 {
            let (fx0, fy0) = self.distorted(x, y);
            let (ex, ey) = (fx0 - xd, fy0 - yd);
            let (ax, ay) = self.distorted(x + h, y);
            let (bx, by) = self.distorted(x - h, y);
            let (cx_, cy_) = self.distorted(x, y + h);
            let (dx_, dy_) = self.distorted(x, y - h);
            let (j11, j21) = ((ax - bx) / (2.0 * h), (ay - by) / (2.0 * h));
            let (j12, j22) = ((cx_ - dx_) / (2.0 * h), (cy_ - dy_) / (2.0 * h));
            let det = j11 * j22 - j12 * j21;
            if det.abs() < 1e-12 {
                break;
            }
            let sx = (j22 * ex - j12 * ey) / det;
            let sy = (-j21 * ex + j11 * ey) / det;
            x -= sx;
            y -= sy;
            if sx.abs() < 1e-15 && sy.abs() < 1e-15 {
                break;
            }
        }
        (x, y)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_ray_through_a_pixel_projects_back_to_it() {
        for dist in [[0.0; 5], [-0.25, 0.125, 0.0004, -0.0003, 0.0], [0.1, -0.05, -0.001, 0.002, 0.01]] {
            let k = CameraIntrinsics { width: 1280, height: 960, fx: 1100.0, fy: 1090.0, cx: 641.3, cy: 478.9, dist };
            let lens = Lens::of(&k);
            for (u, v) in [(0.0, 0.0), (1279.0, 959.0), (640.0, 480.0), (10.5, 900.25), (1200.0, 30.0)] {
                let (x, y) = lens.ray(u, v);
                let back = lens.pixel(&Vector3::new(x, y, 1.0)).unwrap();
                assert!((back.x - u).abs() < 1e-9 && (back.y - v).abs() < 1e-9, "{dist:?} ({u}, {v}) → {back}");
            }
        }
    }

    /// Written independently of the product's model, it must agree with it: the two
    /// implementations of one documented convention.
    #[test]
    fn agrees_with_the_product_model_as_documented() {
        let k = CameraIntrinsics {
            width: 800,
            height: 600,
            fx: 900.0,
            fy: 905.0,
            cx: 399.5,
            cy: 300.2,
            dist: [-0.2, 0.1, 0.001, -0.002, 0.01],
        };
        let lens = Lens::of(&k);
        for p in [Vector3::new(0.3, -0.2, 1.0), Vector3::new(-120.0, 80.0, 900.0), Vector3::new(0.0, 0.0, 5.0)] {
            let (a, b) = (lens.pixel(&p).unwrap(), k.project(&p).unwrap());
            assert!((a - b).norm() < 1e-9, "{a} vs {b}");
        }
    }
}
