//! The camera model: OpenCV pinhole with radial-tangential distortion (k1, k2, p1, p2, k3),
//! its analytic Jacobians, undistortion (one Newton solver; [`Lens`] for the fast pixel-run
//! path of refinement), plane homographies, and rigid poses.
//!
//! Pixel convention (OpenCV): pixel centres at integer coordinates, (0, 0) is the centre of
//! the top-left pixel. Poses map world to camera: `x_cam = R x_world + t` (mm).

use nalgebra::{Matrix2, Matrix2x3, Matrix3, Point2, Rotation3, SMatrix, SVector, Vector2, Vector3};
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

    /// Removes distortion: pixel → normalised coordinates, by Newton's method on
    /// [`distort`](Self::distort) (exact to ~1e-12 inside the calibrated field).
    pub fn undistort(&self, px: &Point2<f64>) -> Vector2<f64> {
        let target = Vector2::new((px.x - self.cx) / self.fx, (px.y - self.cy) / self.fy);
        self.undistort_normalised(target, target, 1e-24)
    }

    /// Newton's method for `distort(x) = target` from `x`, until the residual's square is
    /// below `tol`: the one undistortion of the model (see also [`Lens`]).
    fn undistort_normalised(&self, target: Vector2<f64>, mut x: Vector2<f64>, tol: f64) -> Vector2<f64> {
        for _ in 0..20 {
            let r = self.distort(x) - target;
            if r.norm_squared() < tol {
                break;
            }
            match self.distort_jacobian(x).try_inverse() {
                Some(ji) => x -= ji * r,
                None => break,
            }
        }
        x
    }

    /// The lens of this camera in pixel units (see [`Lens`]).
    pub fn lens(&self) -> Lens<'_> {
        Lens::new(Some(self))
    }

    /// True when a pixel lies inside the image with `margin` pixels to spare.
    pub fn in_image(&self, px: &Point2<f64>, margin: f64) -> bool {
        px.x >= margin - 0.5
            && px.y >= margin - 0.5
            && px.x <= self.width as f64 - 0.5 - margin
            && px.y <= self.height as f64 - 0.5 - margin
    }
}

/// The last solution of [`Lens::pixel_to_ideal_run`] (normalised coordinates): the start
/// of the next pixel of the run.
#[derive(Debug, Clone, Copy)]
pub struct Undistorted {
    target: Vector2<f64>,
    x: Vector2<f64>,
    jinv: Matrix2<f64>,
}

/// Pixel ↔ ideal (undistorted) pixel coordinates (`fx·xn + cx`, `fy·yn + cy`) of a camera;
/// the identity without intrinsics or without distortion. The fast paths of sub-pixel
/// refinement and tag confirmation: a run of neighbouring pixels is undistorted by chord
/// steps from the previous pixel's solution ([`Lens::pixel_to_ideal_run`]).
#[derive(Debug, Clone, Copy)]
pub struct Lens<'a> {
    intr: Option<&'a CameraIntrinsics>,
    /// The ideal coordinates of pixel centres, kept per block (see [`IdealPixelMap`]).
    map: Option<&'a IdealPixelMap>,
}

impl<'a> Lens<'a> {
    /// The lens of `intrinsics` (the identity for `None`, unusable or distortion-free intrinsics).
    pub fn new(intrinsics: Option<&'a CameraIntrinsics>) -> Self {
        // Without distortion ideal pixels are the pixels themselves.
        Lens {
            intr: intrinsics.filter(|k| k.fx > 0.0 && k.fy > 0.0 && k.fx.is_finite() && k.fy.is_finite() && k.dist != [0.0; 5]),
            map: None,
        }
    }

    /// The lens of `map`'s camera, with pixel centres looked up in `map`
    /// ([`Lens::pixel_centre_to_ideal`]).
    pub fn with_map(map: &'a IdealPixelMap) -> Self {
        let lens = Lens::new(Some(&map.intr));
        Lens { map: lens.intr.map(|_| map), ..lens }
    }

    /// The intrinsics this lens undistorts with (`None` for the identity).
    pub fn intrinsics(&self) -> Option<&'a CameraIntrinsics> {
        self.intr
    }

    /// The ideal coordinates of the centre of pixel (`x`, `y`): looked up in the lens's
    /// [`IdealPixelMap`] when it has one and the pixel is inside it, else as
    /// [`Lens::pixel_to_ideal_run`] (for the pixels of a row, in order, sharing `prev`).
    #[inline]
    pub fn pixel_centre_to_ideal(&self, x: i64, y: i64, prev: &mut Option<Undistorted>) -> Vector2<f64> {
        if let Some(u) = self.map.and_then(|m| m.get(x, y)) {
            return u;
        }
        self.pixel_to_ideal_run(&Vector2::new(x as f64, y as f64), prev)
    }

    /// [`Lens::pixel_to_ideal`] for a run of nearby pixels (a row): the previous pixel's
    /// solution in `prev`, moved by its inverse Jacobian, predicts this one to a few 1e-4 px,
    /// so one Newton step usually finishes it (it iterates on until the step is below
    /// ~3e-7 in normalised coordinates, i.e. a remaining error below 1e-12).
    pub fn pixel_to_ideal_run(&self, p: &Vector2<f64>, prev: &mut Option<Undistorted>) -> Vector2<f64> {
        let Some(k) = self.intr else {
            return *p;
        };
        let target = Vector2::new((p.x - k.cx) / k.fx, (p.y - k.cy) / k.fy);
        // Along a run the previous pixel's inverse Jacobian serves for the step too (it
        // changes by ~1e-4 per pixel, so the step's error is ~1e-4 of an already tiny
        // one); a fresh Jacobian is taken at the start of a run and whenever the step is
        // not yet small.
        let (mut x, mut jinv) = match prev {
            Some(u) => (u.x + u.jinv * (target - u.target), Some(u.jinv)),
            None => (target, None),
        };
        for _ in 0..20 {
            let r = k.distort(x) - target;
            let ji = match jinv {
                Some(ji) => ji,
                None => match k.distort_jacobian(x).try_inverse() {
                    Some(ji) => ji,
                    None => break,
                },
            };
            let step = ji * r;
            x -= step;
            if step.norm_squared() < 1e-13 {
                jinv = Some(ji);
                break;
            }
            jinv = None;
        }
        let jinv = jinv.or_else(|| k.distort_jacobian(x).try_inverse()).unwrap_or_else(Matrix2::identity);
        *prev = Some(Undistorted { target, x, jinv });
        Vector2::new(k.fx * x.x + k.cx, k.fy * x.y + k.cy)
    }

    /// Distorted pixel → ideal pixel, warm-started from `guess` (ideal).
    pub fn pixel_to_ideal(&self, p: &Vector2<f64>, guess: Option<&Vector2<f64>>) -> Vector2<f64> {
        let Some(k) = self.intr else {
            return *p;
        };
        let target = Vector2::new((p.x - k.cx) / k.fx, (p.y - k.cy) / k.fy);
        let start = match guess {
            Some(g) => Vector2::new((g.x - k.cx) / k.fx, (g.y - k.cy) / k.fy),
            None => target,
        };
        let x = k.undistort_normalised(target, start, 1e-26);
        Vector2::new(k.fx * x.x + k.cx, k.fy * x.y + k.cy)
    }

    /// Ideal pixel → distorted pixel.
    pub fn ideal_to_pixel(&self, u: &Vector2<f64>) -> Vector2<f64> {
        let Some(k) = self.intr else {
            return *u;
        };
        let d = k.distort(Vector2::new((u.x - k.cx) / k.fx, (u.y - k.cy) / k.fy));
        Vector2::new(k.fx * d.x + k.cx, k.fy * d.y + k.cy)
    }
}

/// Side of the square blocks of an [`IdealPixelMap`], pixels.
const MAP_BLOCK: u32 = 16;

/// The ideal (undistorted) coordinates of a camera's pixel centres, computed a 16 × 16
/// block at a time on first use and kept: the tags a camera follows stay in the same few
/// blocks for a whole test, so their edge fits look the coordinates up instead of solving
/// the lens model for every pixel of every frame (about 4 KB per block touched; a
/// 1920x1080 camera following 20 tags touches ~1 MB). Shared by the threads that refine
/// one frame's tags (each block is computed once, by whichever thread needs it first).
pub struct IdealPixelMap {
    intr: CameraIntrinsics,
    width: u32,
    height: u32,
    blocks_per_row: u32,
    blocks: Vec<std::sync::OnceLock<Box<[Vector2<f64>]>>>,
}

impl std::fmt::Debug for IdealPixelMap {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let computed = self.blocks.iter().filter(|b| b.get().is_some()).count();
        f.debug_struct("IdealPixelMap")
            .field("width", &self.width)
            .field("height", &self.height)
            .field("blocks_computed", &computed)
            .finish()
    }
}

impl IdealPixelMap {
    /// An empty map of a `width` × `height` image of the camera `intrinsics`.
    pub fn new(intrinsics: CameraIntrinsics, width: u32, height: u32) -> Self {
        let blocks_per_row = width.div_ceil(MAP_BLOCK);
        let n = blocks_per_row as usize * height.div_ceil(MAP_BLOCK) as usize;
        Self { intr: intrinsics, width, height, blocks_per_row, blocks: (0..n).map(|_| std::sync::OnceLock::new()).collect() }
    }

    /// The image size the map covers.
    pub fn size(&self) -> (u32, u32) {
        (self.width, self.height)
    }

    /// The camera's intrinsics.
    pub fn intrinsics(&self) -> &CameraIntrinsics {
        &self.intr
    }

    /// The ideal coordinates of pixel (`x`, `y`)'s centre; `None` outside the image.
    #[inline]
    pub fn get(&self, x: i64, y: i64) -> Option<Vector2<f64>> {
        if x < 0 || y < 0 || x >= self.width as i64 || y >= self.height as i64 {
            return None;
        }
        let (x, y) = (x as u32, y as u32);
        let (bx, by) = (x / MAP_BLOCK, y / MAP_BLOCK);
        let block = self.blocks[(by * self.blocks_per_row + bx) as usize].get_or_init(|| self.compute(bx, by));
        Some(block[((y % MAP_BLOCK) * MAP_BLOCK + x % MAP_BLOCK) as usize])
    }

    /// Block (`bx`, `by`): every pixel centre undistorted, row by row.
    fn compute(&self, bx: u32, by: u32) -> Box<[Vector2<f64>]> {
        let lens = Lens::new(Some(&self.intr));
        let mut out = Vec::with_capacity((MAP_BLOCK * MAP_BLOCK) as usize);
        for dy in 0..MAP_BLOCK {
            let mut prev = None;
            for dx in 0..MAP_BLOCK {
                let p = Vector2::new((bx * MAP_BLOCK + dx) as f64, (by * MAP_BLOCK + dy) as f64);
                out.push(lens.pixel_to_ideal_run(&p, &mut prev));
            }
        }
        out.into_boxed_slice()
    }
}

/// Homography `H` with `[x, y, 1]ᵀ ~ H [u, v, 1]ᵀ` from point pairs `from` (u, v) → `to`
/// (x, y): exact from four pairs (8 × 8 linear solve, `H₃₃ = 1`), the normalised DLT from
/// more. `None` for degenerate input.
pub fn homography(from: &[Vector2<f64>], to: &[Vector2<f64>]) -> Option<Matrix3<f64>> {
    if from.len() < 4 || from.len() != to.len() {
        return None;
    }
    let h = if from.len() == 4 { homography_4(from, to)? } else { homography_dlt(from, to)? };
    (h.iter().all(|v| v.is_finite()) && h.norm() > 0.0).then_some(h)
}

/// The exact homography of four point pairs.
fn homography_4(from: &[Vector2<f64>], to: &[Vector2<f64>]) -> Option<Matrix3<f64>> {
    let mut a = SMatrix::<f64, 8, 8>::zeros();
    let mut b = SVector::<f64, 8>::zeros();
    for i in 0..4 {
        let (x, y) = (from[i].x, from[i].y);
        let (u, v) = (to[i].x, to[i].y);
        let r = 2 * i;
        a.row_mut(r).copy_from_slice(&[x, y, 1.0, 0.0, 0.0, 0.0, -u * x, -u * y]);
        a.row_mut(r + 1).copy_from_slice(&[0.0, 0.0, 0.0, x, y, 1.0, -v * x, -v * y]);
        b[r] = u;
        b[r + 1] = v;
    }
    let h = a.lu().solve(&b)?;
    Some(Matrix3::new(h[0], h[1], h[2], h[3], h[4], h[5], h[6], h[7], 1.0))
}

/// The normalised DLT of five or more point pairs.
fn homography_dlt(plane: &[Vector2<f64>], image: &[Vector2<f64>]) -> Option<Matrix3<f64>> {
    let (tp, _) = normaliser(plane)?;
    let (ti, ti_inv) = normaliser(image)?;
    let mut ata = SMatrix::<f64, 9, 9>::zeros();
    for (p, q) in plane.iter().zip(image) {
        let p = tp * Vector3::new(p.x, p.y, 1.0);
        let q = ti * Vector3::new(q.x, q.y, 1.0);
        let (u, v) = (p.x / p.z, p.y / p.z);
        let (x, y) = (q.x / q.z, q.y / q.z);
        let rows = [
            SMatrix::<f64, 1, 9>::from_row_slice(&[u, v, 1.0, 0.0, 0.0, 0.0, -x * u, -x * v, -x]),
            SMatrix::<f64, 1, 9>::from_row_slice(&[0.0, 0.0, 0.0, u, v, 1.0, -y * u, -y * v, -y]),
        ];
        for r in rows {
            ata += r.transpose() * r;
        }
    }
    let eig = ata.symmetric_eigen();
    let (imin, _) = eig.eigenvalues.iter().enumerate().min_by(|a, b| a.1.total_cmp(b.1))?;
    let h = eig.eigenvectors.column(imin);
    let hn = Matrix3::new(h[0], h[1], h[2], h[3], h[4], h[5], h[6], h[7], h[8]);
    Some(ti_inv * hn * tp)
}

/// Similarity moving points to zero mean and mean distance √2, and its inverse.
fn normaliser(pts: &[Vector2<f64>]) -> Option<(Matrix3<f64>, Matrix3<f64>)> {
    let n = pts.len() as f64;
    let c = pts.iter().fold(Vector2::zeros(), |a, p| a + p) / n;
    let d = pts.iter().map(|p| (p - c).norm()).sum::<f64>() / n;
    if !d.is_finite() || d <= 1e-15 {
        return None;
    }
    let s = std::f64::consts::SQRT_2 / d;
    let t = Matrix3::new(s, 0.0, -s * c.x, 0.0, s, -s * c.y, 0.0, 0.0, 1.0);
    let ti = Matrix3::new(1.0 / s, 0.0, c.x, 0.0, 1.0 / s, c.y, 0.0, 0.0, 1.0);
    Some((t, ti))
}

/// Applies a homography to a point; `None` at infinity.
pub fn apply_homography(h: &Matrix3<f64>, p: &Vector2<f64>) -> Option<Vector2<f64>> {
    let q = h * Vector3::new(p.x, p.y, 1.0);
    if q.z.abs() < 1e-12 {
        return None;
    }
    Some(Vector2::new(q.x / q.z, q.y / q.z))
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
    fn pixel_map_matches_the_lens_and_stays_inside_the_image() {
        let k = cam();
        let map = IdealPixelMap::new(k, 100, 70);
        let lens = Lens::new(Some(&k));
        for (x, y) in [(0, 0), (15, 15), (16, 16), (17, 3), (99, 69), (50, 33), (31, 47)] {
            let exact = lens.pixel_to_ideal(&Vector2::new(x as f64, y as f64), None);
            let got = map.get(x, y).unwrap();
            assert!((got - exact).norm() < 1e-9, "pixel ({x}, {y}): {got} vs {exact}");
            let mut prev = None;
            assert_eq!(Lens::with_map(&map).pixel_centre_to_ideal(x, y, &mut prev), got);
        }
        assert!(map.get(100, 0).is_none() && map.get(0, 70).is_none() && map.get(-1, 5).is_none());
        // Outside the map the lens solves the model itself.
        let mut prev = None;
        let outside = Lens::with_map(&map).pixel_centre_to_ideal(120, 5, &mut prev);
        assert!((outside - lens.pixel_to_ideal(&Vector2::new(120.0, 5.0), None)).norm() < 1e-9);
        // No distortion: the identity, no map needed.
        let flat = IdealPixelMap::new(CameraIntrinsics { dist: [0.0; 5], ..k }, 10, 10);
        assert_eq!(Lens::with_map(&flat).pixel_centre_to_ideal(3, 4, &mut None), Vector2::new(3.0, 4.0));
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
