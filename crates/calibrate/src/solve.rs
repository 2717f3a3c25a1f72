//! The calibration itself: Zhang's closed-form start and Levenberg–Marquardt over the
//! intrinsics and every view's pose at once, with the covariance of the result.
//!
//! **Model.** The product's camera model ([`CameraIntrinsics`]: pinhole + radial-tangential
//! k1, k2, p1, p2, k3, OpenCV convention) with its analytic Jacobians
//! ([`CameraIntrinsics::project_with_jacobian`], [`CameraIntrinsics::project_intrinsics_jacobian`]),
//! and each view's board pose updated on the manifold like every pose in the solver
//! ([`tagdeflect_estimate::lm::retract`]).
//!
//! **Fixed parameters** are handled by a basis: the nine intrinsics move as `θ = θ₀ + B q`
//! with `q` the free parameters. Fixing k3 or the tangential terms drops columns of `B`;
//! fixing the aspect ratio (OpenCV's `CALIB_FIX_ASPECT_RATIO`) replaces the fx and fy columns
//! by one column `(a, 1)` with `a = fx / fy` held at its start value. The covariance of `θ` is
//! `B Σ_q Bᵀ`, so a fixed parameter reports σ = 0 and fx, fy are fully correlated under a
//! fixed ratio.
//!
//! **Start.** Zhang (2000): one plane → image homography per view, the image of the
//! absolute conic from their orthogonality constraints, intrinsics from it, distortion zero.
//! When that fails (fewer than three usable views, near-degenerate views — all parallel
//! boards — or a principal point off the image) the start falls back to OpenCV's variant
//! with the principal point at the image centre and only the focal lengths solved. Each
//! view's pose then comes from its homography and is refined alone (six-parameter LM)
//! before the joint fit.
//!
//! **Uncertainty.** `Σ = s² (JᵀJ)⁻¹` at the minimum with `s² = SSR / (2N − p)` (the
//! residuals' own scatter), i.e. the usual first-order covariance of a least-squares fit
//! with independent, equal corner noise. It is honest when the model fits (reprojection
//! residuals are noise, not an unmodelled lens); an RMS much larger than the corner
//! detector's precision is itself the warning.
//!
//! **Systematic corner errors** do not average out over views and are not in `s`: a shift
//! of every corner by `δ · d_i` (pixels, `d_i` a fixed pattern, e.g. along each tag
//! corner's diagonal) moves the fit, to first order with every pose free to absorb what it
//! can, by `Δθ = −(JᵀJ)⁻¹ Jᵀ ∂r/∂δ · δ` ([`bias_sensitivity`]). With a prior σ_b on δ, its
//! covariance `σ_b² Δθ Δθᵀ` is added to the statistical one, one term per independent
//! pattern ([`Calibration::set_corner_bias`]); the tag targets do this
//! ([`crate::calibrate_target_views`]), checkerboards have no such term.

mod diagnostics;
mod joint;
mod start;

use nalgebra::{DMatrix, Point2, SMatrix, Vector3};

use tagdeflect_core::camera::{CameraIntrinsics, Pose};

pub use diagnostics::{bias_sensitivity, view_pnp};
pub(crate) use diagnostics::{residuals, view_pulls, view_ssr};
pub(crate) use joint::calibrate;

/// Names of the nine intrinsic parameters, in the order of every 9-vector here.
pub const PARAM_NAMES: [&str; 9] = ["fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"];

/// One view of the target: board points (mm, board frame, z = 0) and their detected pixels.
#[derive(Debug, Clone, PartialEq)]
pub struct View {
    /// Where the view came from (file name or frame number).
    pub name: String,
    /// Board points, mm.
    pub object: Vec<Vector3<f64>>,
    /// Detected pixels (OpenCV convention), same order.
    pub image: Vec<Point2<f64>>,
}

/// Which intrinsics are held fixed (OpenCV's flags).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct SolveOptions {
    /// Hold k3 at zero (`CALIB_FIX_K3`).
    pub fix_k3: bool,
    /// Hold fx / fy at its start value, `aspect_ratio` (`CALIB_FIX_ASPECT_RATIO`).
    pub fix_aspect_ratio: bool,
    /// The ratio fx / fy held by `fix_aspect_ratio` (OpenCV takes it from the initial
    /// camera matrix; 1 when `None`).
    pub aspect_ratio: Option<f64>,
    /// Hold p1 = p2 = 0 (`CALIB_ZERO_TANGENT_DIST`).
    pub zero_tangent_dist: bool,
    /// Hold cx, cy at the image centre (`CALIB_FIX_PRINCIPAL_POINT`).
    pub fix_principal_point: bool,
}

/// Why a calibration could not be computed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SolveError {
    /// Not enough views or points.
    #[error("too few views of the target: {views} usable (need at least {need})")]
    TooFewViews {
        /// Usable views.
        views: usize,
        /// Views needed.
        need: usize,
    },
    /// The closed-form start found no focal length.
    #[error("no initial estimate of the focal length (are the views all frontal and parallel?)")]
    NoStart,
    /// The normal equations were singular (the views do not constrain the free parameters).
    #[error("the views do not constrain the camera parameters (singular normal equations); move the target through more orientations")]
    Singular,
}

/// The result of a calibration (the fit inside [`crate::calibrate_views`]).
#[derive(Debug, Clone, PartialEq)]
pub struct Calibration {
    /// The intrinsics at the minimum.
    pub intrinsics: CameraIntrinsics,
    /// The board pose of every view (board → camera, mm).
    pub poses: Vec<Pose>,
    /// 9×9 covariance of (fx, fy, cx, cy, k1, k2, p1, p2, k3); fixed parameters have zero rows.
    pub covariance: SMatrix<f64, 9, 9>,
    /// Reprojection RMS per view, pixels: `√(Σ|e|² / n)` over the view's points (OpenCV's
    /// per-view error).
    pub view_rms_px: Vec<f64>,
    /// Reprojection RMS over all points: `√(Σ|e|² / N)` (what `cv::calibrateCamera` returns).
    pub rms_px: f64,
    /// Residual scatter per axis `s = √(SSR / (2N − p))`, pixels (scales the covariance).
    pub sigma_px: f64,
    /// Number of free parameters (intrinsics + 6 per view).
    pub parameters: usize,
    /// LM iterations of the joint fit.
    pub iterations: usize,
    /// Which start was used: "zhang" or "centred" (principal point at the image centre).
    pub start: &'static str,
    /// The systematic corner biases whose effect `covariance` includes (tag targets; empty:
    /// `covariance` is the statistical one alone).
    pub corner_bias: Vec<CornerBias>,
}

/// One pattern of systematic corner displacement, shared by every view, of unknown
/// amplitude `δ` (pixels) with a prior σ, and what it does to the intrinsics (module docs,
/// "Systematic corner errors"). Modes are independent: their covariances add.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CornerBias {
    /// What the pattern is, for reports (e.g. "uniform along the diagonals").
    pub mode: &'static str,
    /// Prior 1-σ of the amplitude `δ`, pixels.
    pub sigma_px: f64,
    /// First-order change of (fx, fy, cx, cy, k1, k2, p1, p2, k3) per pixel of `δ`
    /// ([`bias_sensitivity`]); zero for fixed parameters.
    pub sensitivity_per_px: SMatrix<f64, 9, 1>,
}

impl CornerBias {
    /// Its covariance of the nine intrinsics: `σ_b² Δθ Δθᵀ`.
    pub fn covariance(&self) -> SMatrix<f64, 9, 9> {
        self.sensitivity_per_px * self.sensitivity_per_px.transpose() * (self.sigma_px * self.sigma_px)
    }
}

impl Calibration {
    /// 1-σ of the nine intrinsics (fx, fy, cx, cy, k1, k2, p1, p2, k3), the systematic
    /// corner biases included when there are any; 0 for fixed ones.
    pub fn sigmas(&self) -> [f64; 9] {
        std::array::from_fn(|i| self.covariance[(i, i)].max(0.0).sqrt())
    }

    /// The corner noise's part of [`covariance`](Self::covariance): without the systematic
    /// corner biases.
    pub fn statistical_covariance(&self) -> SMatrix<f64, 9, 9> {
        self.corner_bias.iter().fold(self.covariance, |c, b| c - b.covariance())
    }

    /// 1-σ of the nine intrinsics from the corner noise alone ([`statistical_covariance`](Self::statistical_covariance)).
    pub fn statistical_sigmas(&self) -> [f64; 9] {
        let c = self.statistical_covariance();
        std::array::from_fn(|i| c[(i, i)].max(0.0).sqrt())
    }

    /// 1-σ of the nine intrinsics from the systematic corner biases alone.
    pub fn systematic_sigmas(&self) -> [f64; 9] {
        let c = self.corner_bias.iter().fold(SMatrix::<f64, 9, 9>::zeros(), |c, b| c + b.covariance());
        std::array::from_fn(|i| c[(i, i)].max(0.0).sqrt())
    }

    /// Replaces the systematic corner biases held in [`covariance`](Self::covariance)
    /// (empty: the statistical covariance alone).
    pub fn set_corner_bias(&mut self, modes: Vec<CornerBias>) {
        let stat = self.statistical_covariance();
        self.covariance = modes.iter().fold(stat, |c, b| c + b.covariance());
        self.corner_bias = modes;
    }
}

/// The nine intrinsics as a vector (order of [`PARAM_NAMES`]).
pub fn to_vector(k: &CameraIntrinsics) -> SMatrix<f64, 9, 1> {
    SMatrix::<f64, 9, 1>::from_column_slice(&[k.fx, k.fy, k.cx, k.cy, k.dist[0], k.dist[1], k.dist[2], k.dist[3], k.dist[4]])
}

fn from_vector(v: &SMatrix<f64, 9, 1>, width: u32, height: u32) -> CameraIntrinsics {
    CameraIntrinsics { width, height, fx: v[0], fy: v[1], cx: v[2], cy: v[3], dist: [v[4], v[5], v[6], v[7], v[8]] }
}

/// Columns of the basis `B` (9 × m): which directions of θ are free.
fn basis(options: &SolveOptions, aspect: f64) -> DMatrix<f64> {
    let mut cols: Vec<SMatrix<f64, 9, 1>> = Vec::new();
    let unit = |i: usize| {
        let mut c = SMatrix::<f64, 9, 1>::zeros();
        c[i] = 1.0;
        c
    };
    if options.fix_aspect_ratio {
        let mut c = SMatrix::<f64, 9, 1>::zeros();
        c[0] = aspect;
        c[1] = 1.0;
        cols.push(c);
    } else {
        cols.push(unit(0));
        cols.push(unit(1));
    }
    if !options.fix_principal_point {
        cols.push(unit(2));
        cols.push(unit(3));
    }
    cols.push(unit(4));
    cols.push(unit(5));
    if !options.zero_tangent_dist {
        cols.push(unit(6));
        cols.push(unit(7));
    }
    if !options.fix_k3 {
        cols.push(unit(8));
    }
    let mut b = DMatrix::zeros(9, cols.len());
    for (j, c) in cols.iter().enumerate() {
        b.column_mut(j).copy_from(c);
    }
    b
}

#[cfg(test)]
mod tests {
    use nalgebra::{DVector, Vector2, Vector6};
    use tagdeflect_estimate::lm::retract;

    use super::joint::{cost, normal_equations};
    use super::start::view_pose;
    use super::*;

    fn truth() -> CameraIntrinsics {
        CameraIntrinsics { width: 800, height: 600, fx: 700.0, fy: 690.0, cx: 405.0, cy: 296.0, dist: [-0.3, 0.12, 0.001, -0.0008, -0.02] }
    }

    fn synthetic(k: &CameraIntrinsics, noise: f64, seed: u64) -> Vec<View> {
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let nd = Normal::new(0.0, noise.max(1e-12)).unwrap();
        let object: Vec<Vector3<f64>> =
            (0..6).flat_map(|j| (0..9).map(move |i| Vector3::new(i as f64 * 30.0, j as f64 * 30.0, 0.0))).collect();
        let mut views = Vec::new();
        for (n, (rx, ry, rz, tx, ty, tz)) in [
            (0.3, -0.2, 0.1, -150.0, -80.0, 500.0),
            (-0.4, 0.3, -0.2, -100.0, -60.0, 450.0),
            (0.1, 0.5, 0.3, -60.0, -120.0, 520.0),
            (0.5, 0.1, -0.4, -200.0, -20.0, 600.0),
            (-0.2, -0.45, 1.2, 20.0, -150.0, 480.0),
            (0.25, 0.35, -1.0, -250.0, 10.0, 550.0),
        ]
        .into_iter()
        .enumerate()
        {
            let pose = Pose::from_rvec_tvec([rx, ry, rz], [tx, ty, tz]);
            let image: Vec<Point2<f64>> = object
                .iter()
                .map(|x| {
                    let p = k.project(&pose.transform(x)).unwrap();
                    Point2::new(p.x + nd.sample(&mut rng), p.y + nd.sample(&mut rng))
                })
                .collect();
            views.push(View { name: format!("v{n}"), object: object.clone(), image });
        }
        views
    }

    #[test]
    fn recovers_exact_intrinsics_from_noiseless_views() {
        let k = truth();
        let views = synthetic(&k, 0.0, 1);
        let c = calibrate(&views, 800, 600, &SolveOptions::default()).unwrap();
        let e = to_vector(&c.intrinsics) - to_vector(&k);
        assert!(e.iter().take(4).all(|v| v.abs() < 1e-5), "{e}");
        assert!(e.iter().skip(4).all(|v| v.abs() < 1e-6), "{e}");
        assert!(c.rms_px < 1e-6);
    }

    #[test]
    fn stated_sigma_matches_the_scatter() {
        let k = truth();
        let mut within = 0;
        let mut total = 0;
        for seed in 0..12 {
            let views = synthetic(&k, 0.3, 100 + seed);
            let c = calibrate(&views, 800, 600, &SolveOptions::default()).unwrap();
            let s = c.sigmas();
            let e = to_vector(&c.intrinsics) - to_vector(&k);
            for i in 0..9 {
                total += 1;
                if e[i].abs() <= 2.0 * s[i] {
                    within += 1;
                }
            }
            assert!((c.sigma_px - 0.3).abs() < 0.05, "sigma {}", c.sigma_px);
        }
        let frac = within as f64 / total as f64;
        assert!(frac > 0.88, "{within}/{total} within 2σ");
    }

    #[test]
    fn fixed_parameters_stay_fixed() {
        let mut k = truth();
        k.fy = k.fx;
        k.dist[4] = 0.0;
        k.dist[2] = 0.0;
        k.dist[3] = 0.0;
        let views = synthetic(&k, 0.1, 7);
        let o = SolveOptions { fix_k3: true, fix_aspect_ratio: true, zero_tangent_dist: true, ..SolveOptions::default() };
        let c = calibrate(&views, 800, 600, &o).unwrap();
        assert_eq!(c.intrinsics.dist[4], 0.0);
        assert_eq!(c.intrinsics.dist[2], 0.0);
        assert!((c.intrinsics.fx / c.intrinsics.fy - 1.0).abs() < 1e-12);
        let s = c.sigmas();
        assert_eq!(s[8], 0.0);
        assert!((s[0] - s[1]).abs() < 1e-9 * s[0]);
        assert!((c.intrinsics.fx - k.fx).abs() < 4.0 * s[0] + 1e-9);
    }

    #[test]
    fn bias_sensitivity_matches_recalibration() {
        let k = truth();
        let views = synthetic(&k, 0.1, 2);
        // A pattern like tag corners: 2 × 2 blocks of points, each moved along its block's
        // diagonals (outwards).
        let pattern: Vec<Vec<Vector2<f64>>> = views
            .iter()
            .map(|v| {
                v.object
                    .iter()
                    .map(|x| {
                        let (i, j) = ((x.x / 30.0).round() as i64, (x.y / 30.0).round() as i64);
                        Vector2::new(if i % 2 == 0 { -1.0 } else { 1.0 }, if j % 2 == 0 { -1.0 } else { 1.0 }) / 2f64.sqrt()
                    })
                    .collect()
            })
            .collect();
        let o = SolveOptions::default();
        let c = calibrate(&views, 800, 600, &o).unwrap();
        let s = bias_sensitivity(&c, &views, &o, &pattern).unwrap();
        // Central differences of the full (nonlinear) calibration with the corners moved.
        let eps = 0.05;
        let moved = |e: f64| -> SMatrix<f64, 9, 1> {
            let vs: Vec<View> = views
                .iter()
                .zip(&pattern)
                .map(|(v, p)| View { image: v.image.iter().zip(p).map(|(u, d)| u + d * e).collect(), ..v.clone() })
                .collect();
            to_vector(&calibrate(&vs, 800, 600, &o).unwrap().intrinsics)
        };
        let fd = (moved(eps) - moved(-eps)) / (2.0 * eps);
        // Pixel terms and distortion terms apart (their scales differ by 10³).
        for rows in [0..4, 4..9] {
            let diff = rows.clone().map(|i| (s[i] - fd[i]).powi(2)).sum::<f64>().sqrt();
            let size = rows.clone().map(|i| fd[i].powi(2)).sum::<f64>().sqrt();
            assert!(diff <= 0.02 * size && size > 0.0, "rows {rows:?}: linear {s} vs recalibrated {fd}");
        }
        // Its covariance adds to the statistical one once, however often it is set.
        let mut c2 = c.clone();
        let bias = CornerBias { mode: "test", sigma_px: 0.03, sensitivity_per_px: s };
        c2.set_corner_bias(vec![bias]);
        c2.set_corner_bias(vec![bias]);
        assert!((c2.covariance - c.covariance - bias.covariance()).norm() <= 1e-9 * c2.covariance.norm());
        assert!((c2.statistical_covariance() - c.covariance).norm() <= 1e-9 * c.covariance.norm());
        assert!((c2.sigmas()[0].powi(2) - c.sigmas()[0].powi(2) - (0.03 * s[0]).powi(2)).abs() <= 1e-9 * c2.sigmas()[0].powi(2));
        assert!((c2.systematic_sigmas()[0] - 0.03 * s[0].abs()).abs() <= 1e-12 * s[0].abs());
        c2.set_corner_bias(Vec::new());
        assert!((c2.covariance - c.covariance).norm() <= 1e-9 * c.covariance.norm());
        // A pattern of the wrong shape is refused.
        assert!(bias_sensitivity(&c, &views[1..], &o, &pattern).is_none());
    }

    #[test]
    fn normal_equations_match_finite_differences() {
        let k = truth();
        let views = synthetic(&k, 0.5, 3);
        let mut k0 = k;
        k0.fx += 3.0;
        k0.dist[0] += 0.01;
        let poses: Vec<Pose> = views.iter().map(|v| view_pose(&k0, v).unwrap()).collect();
        let b = basis(&SolveOptions::default(), 1.0);
        let (_, g) = normal_equations(&k0, &poses, &views, &b).unwrap();
        // Gradient of ½ SSR is Jᵀr: compare with central differences of the cost.
        let m = b.ncols();
        for i in 0..(m + 6) {
            let h = if i < 4 { 1e-4 } else { 1e-7 };
            let mut d = DVector::zeros(m + 6 * views.len());
            d[i] = h;
            let plus = |d: &DVector<f64>| {
                let dtheta = &b * d.rows(0, m).into_owned();
                let th = to_vector(&k0) + SMatrix::<f64, 9, 1>::from_iterator(dtheta.iter().copied());
                let k2 = from_vector(&th, 800, 600);
                let p2: Vec<Pose> = poses
                    .iter()
                    .enumerate()
                    .map(|(j, p)| retract(p, &Vector6::from_iterator(d.rows(m + 6 * j, 6).iter().copied())))
                    .collect();
                cost(&k2, &p2, &views).unwrap()
            };
            let fd = (plus(&d) - plus(&(-d.clone()))) / (2.0 * h) * 0.5;
            assert!((fd - g[i]).abs() < 1e-4 * (1.0 + g[i].abs()), "param {i}: fd {fd} vs {}", g[i]);
        }
    }
}
