//! Camera pose (world → camera) from background tags with known world corners.
//!
//! A closed-form start per tag (homography of its four corners, undistorted, plus the mirror
//! solution), ranked by a truncated reprojection cost over every corner, then LM over all
//! corners with the distortion inside the residual. A tag whose residual is an outlier
//! (RMS > max(3 × median tag RMS, 2 px)) is dropped and the pose re-solved.
//!
//! One tag alone has two local minima (the planar "mirror" ambiguity: the tag tilted one way
//! or the other about the line of sight). [`single_tag_minima`] refines both closed-form
//! starts separately so a caller can tell whether the corners decide between them (the
//! other minimum's RMS well above the best one's and above the corner noise) before it
//! trusts a one-tag pose (see `held_pose`).

use nalgebra::{Matrix2x6, Matrix6, Point2, Vector2, Vector3};

use super::init::{homography, mirrored, pose_from_homography};
use super::lm::{median, minimize, CornerGroups, Evaluation, LmOptions, PoseProblem};
use super::SolveError;
use tagdeflect_core::camera::{skew, CameraIntrinsics, Pose};

/// One background tag seen by a camera: its four detected corners and their known world
/// positions, both in SPEC corner order.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BackgroundTagObservation {
    /// Background tag id.
    pub id: u32,
    /// Detected corners, pixels (OpenCV convention).
    pub pixels: [Point2<f64>; 4],
    /// World corners, mm (from the config).
    pub world: [Vector3<f64>; 4],
}

/// A solved camera pose.
#[derive(Debug, Clone, PartialEq)]
pub struct CameraPoseSolution {
    /// World → camera.
    pub pose: Pose,
    /// Reprojection RMS over the corners used, pixels (per axis: √(SSR / (2 n))).
    pub rms_px: f64,
    /// Corners used.
    pub corners: usize,
    /// 6×6 covariance of the pose in the LM step parameters `(ω rad, v mm)` with
    /// `R ← exp(ω) R`, `t ← t + v`: `s² (JᵀJ)⁻¹`, `s² = SSR / (2n − 6)`.
    pub covariance: Matrix6<f64>,
    /// Ids of tags dropped as outliers.
    pub rejected_tags: Vec<u32>,
    /// Reprojection RMS per tag used, pixels.
    pub tag_rms_px: Vec<(u32, f64)>,
    /// LM iterations spent (all starts).
    pub iterations: usize,
}

/// Residual (projection − observation) of one world point and its Jacobian with respect to
/// the camera pose step `(ω, v)`. `None` behind the camera.
pub fn camera_point_terms(
    intrinsics: &CameraIntrinsics,
    pose: &Pose,
    world: &Vector3<f64>,
    pixel: &Point2<f64>,
) -> Option<(Vector2<f64>, Matrix2x6<f64>)> {
    let rx = pose.rotation * world;
    let pc = rx + pose.translation;
    let (proj, jp) = intrinsics.project_with_jacobian(&pc)?;
    let mut j = Matrix2x6::zeros();
    j.fixed_view_mut::<2, 3>(0, 0).copy_from(&(jp * -skew(&rx)));
    j.fixed_view_mut::<2, 3>(0, 3).copy_from(&jp);
    Some((proj - pixel, j))
}

/// The least-squares problem: all corners of the tags in use.
struct CameraProblem<'a> {
    intrinsics: &'a CameraIntrinsics,
    tags: Vec<&'a BackgroundTagObservation>,
}

impl PoseProblem for CameraProblem<'_> {
    fn evaluate(&self, pose: &Pose, with_jacobian: bool) -> Option<Evaluation> {
        let mut e = Evaluation::zero();
        for tag in &self.tags {
            for k in 0..4 {
                let (r, j) = camera_point_terms(self.intrinsics, pose, &tag.world[k], &tag.pixels[k])?;
                e.add(&r, &j, with_jacobian);
            }
        }
        Some(e)
    }
}

impl CornerGroups for CameraProblem<'_> {
    fn groups(&self) -> usize {
        self.tags.len()
    }
    fn corner_sq_error(&self, pose: &Pose, g: usize, k: usize) -> Option<f64> {
        let tag = self.tags[g];
        let p = self.intrinsics.project(&pose.transform(&tag.world[k]))?;
        Some((p - tag.pixels[k]).norm_squared())
    }
}

/// Closed-form pose candidates from one tag: its homography pose and the mirror solution.
fn tag_candidates(intrinsics: &CameraIntrinsics, tag: &BackgroundTagObservation) -> Vec<Pose> {
    let w = &tag.world;
    let origin = (w[0] + w[1] + w[2] + w[3]) / 4.0;
    let Some(e1) = (w[1] - w[0]).try_normalize(1e-12) else { return Vec::new() };
    let Some(n) = (w[1] - w[0]).cross(&(w[3] - w[0])).try_normalize(1e-12) else { return Vec::new() };
    let e2 = n.cross(&e1);
    let plane: Vec<Vector2<f64>> = w.iter().map(|p| Vector2::new((p - origin).dot(&e1), (p - origin).dot(&e2))).collect();
    let image: Vec<Vector2<f64>> = tag.pixels.iter().map(|p| intrinsics.undistort(p)).collect();
    let Some(h) = homography(&plane, &image) else { return Vec::new() };
    let Some((r, t)) = pose_from_homography(&h) else { return Vec::new() };
    // plane frame → world: x_w = P [u v w] + origin, P = [e1 e2 n].
    let p = nalgebra::Matrix3::from_columns(&[e1, e2, n]);
    let to_pose = |rot: nalgebra::Rotation3<f64>| {
        let rc = rot.matrix() * p.transpose();
        let rot_cw = nalgebra::Rotation3::from_matrix_unchecked(rc);
        Pose { rotation: rot_cw, translation: t - rot_cw * origin }
    };
    vec![to_pose(r), to_pose(mirrored(&r, &t))]
}

/// The two local minima of a one-tag pose (see the module docs): LM over the tag's four
/// corners from each closed-form start (homography pose and its mirror), as
/// `(pose, rms_px)` sorted by RMS; when both starts end in the same minimum (within 0.5°
/// and 1 mm of camera centre) only one is returned: the corners decide the pose.
pub fn single_tag_minima(intrinsics: &CameraIntrinsics, tag: &BackgroundTagObservation) -> Vec<(Pose, f64)> {
    let problem = CameraProblem { intrinsics, tags: vec![tag] };
    let options = LmOptions::default();
    let mut out: Vec<(Pose, f64)> = Vec::new();
    for start in tag_candidates(intrinsics, tag) {
        let Some(sol) = minimize(&problem, &start, &options) else { continue };
        let rms = (sol.evaluation.ssr / sol.evaluation.residuals.max(1) as f64).sqrt();
        let same = out.iter().any(|(p, _)| p.angle_to(&sol.pose) < 0.5f64.to_radians() && (p.centre() - sol.pose.centre()).norm() < 1.0);
        if !same && rms.is_finite() {
            out.push((sol.pose, rms));
        }
    }
    out.sort_by(|a, b| a.1.total_cmp(&b.1));
    out
}

/// Solves a camera's pose from background tags. Needs at least one tag (4 corners); two or
/// more (ideally not coplanar) give a well-conditioned pose. `initial` (e.g. the last pose)
/// is tried as an extra start.
pub fn solve_camera_pose(
    intrinsics: &CameraIntrinsics,
    tags: &[BackgroundTagObservation],
    initial: Option<&Pose>,
) -> Result<CameraPoseSolution, SolveError> {
    let valid: Vec<&BackgroundTagObservation> = tags
        .iter()
        .filter(|t| t.pixels.iter().all(|p| p.x.is_finite() && p.y.is_finite()) && t.world.iter().all(|w| w.iter().all(|v| v.is_finite())))
        .collect();
    if valid.is_empty() {
        return Err(SolveError::TooFewCorners { what: "camera pose".into(), needed: 4, got: 0 });
    }
    let mut problem = CameraProblem { intrinsics, tags: valid };
    let options = LmOptions::default();

    // Rank closed-form starts by the capped cost over every corner.
    let mut starts: Vec<Pose> = problem.tags.iter().flat_map(|t| tag_candidates(intrinsics, t)).collect();
    if let Some(p) = initial {
        starts.push(*p);
    }
    if starts.is_empty() {
        return Err(SolveError::Degenerate { what: "camera pose: no tag gives a closed-form start (degenerate corners?)".into() });
    }
    let mut ranked: Vec<(f64, Pose)> = starts.iter().map(|p| (problem.robust_cost(p), *p)).collect();
    ranked.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut iterations = 0;
    let mut best: Option<super::lm::LmOutcome> = None;
    for (_, start) in ranked.iter().take(3) {
        if let Some(out) = minimize(&problem, start, &options) {
            iterations += out.iterations;
            if best.as_ref().is_none_or(|b| out.evaluation.ssr < b.evaluation.ssr) {
                best = Some(out);
            }
        }
    }
    let mut best =
        best.ok_or_else(|| SolveError::Degenerate { what: "camera pose: least squares did not converge from any start".into() })?;

    // Outlier tags: drop the worst while it is far above the others, re-solve.
    let mut rejected = Vec::new();
    loop {
        if problem.tags.len() < 2 {
            break;
        }
        let Some(rms) = problem.group_rms(&best.pose) else { break };
        let med = median(&rms).unwrap_or(0.0);
        let (worst, &worst_rms) = rms.iter().enumerate().max_by(|a, b| a.1.total_cmp(b.1)).expect("non-empty");
        let limit = (3.0 * med).max(2.0);
        if worst_rms <= limit {
            break;
        }
        let id = problem.tags[worst].id;
        tracing::warn!(
            tag = id,
            rms_px = worst_rms,
            median_px = med,
            limit_px = limit,
            "camera pose: background tag rejected as an outlier"
        );
        rejected.push(id);
        problem.tags.remove(worst);
        let mut next: Option<super::lm::LmOutcome> = None;
        let mut restarts: Vec<Pose> = vec![best.pose];
        restarts.extend(problem.tags.iter().flat_map(|t| tag_candidates(intrinsics, t)));
        let mut ranked: Vec<(f64, Pose)> = restarts.iter().map(|p| (problem.robust_cost(p), *p)).collect();
        ranked.sort_by(|a, b| a.0.total_cmp(&b.0));
        for (_, start) in ranked.iter().take(2) {
            if let Some(out) = minimize(&problem, start, &options) {
                iterations += out.iterations;
                if next.as_ref().is_none_or(|b| out.evaluation.ssr < b.evaluation.ssr) {
                    next = Some(out);
                }
            }
        }
        best = next.ok_or_else(|| SolveError::Degenerate { what: "camera pose: re-solve after rejecting a tag failed".into() })?;
    }

    let n = best.evaluation.residuals;
    let ssr = best.evaluation.ssr;
    let dof = n.saturating_sub(6).max(1) as f64;
    let inv = best
        .evaluation
        .jtj
        .try_inverse()
        .ok_or_else(|| SolveError::Degenerate { what: "camera pose: singular normal equations".into() })?;
    let tag_rms = problem.group_rms(&best.pose).unwrap_or_default();
    Ok(CameraPoseSolution {
        pose: best.pose,
        rms_px: (ssr / n as f64).sqrt(),
        corners: n / 2,
        covariance: inv * (ssr / dof),
        rejected_tags: rejected,
        tag_rms_px: problem.tags.iter().map(|t| t.id).zip(tag_rms).collect(),
        iterations,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lm::retract;
    use nalgebra::Vector6;

    fn cam() -> CameraIntrinsics {
        CameraIntrinsics {
            width: 1280,
            height: 960,
            fx: 1400.0,
            fy: 1405.0,
            cx: 639.5,
            cy: 479.5,
            dist: [-0.25, 0.1, 0.001, -0.0005, -0.02],
        }
    }

    #[test]
    fn jacobian_matches_finite_differences() {
        let c = cam();
        let pose = Pose::from_rvec_tvec([1.3, 0.2, -0.1], [30.0, -40.0, 1500.0]);
        let world = Vector3::new(-200.0, 150.0, 80.0);
        let px = Point2::new(400.0, 300.0);
        let (_, j) = camera_point_terms(&c, &pose, &world, &px).expect("in front");
        for k in 0..6 {
            let h = if k < 3 { 1e-7 } else { 1e-4 };
            let mut d = Vector6::zeros();
            d[k] = h;
            let (a, _) = camera_point_terms(&c, &retract(&pose, &d), &world, &px).unwrap();
            let (b, _) = camera_point_terms(&c, &retract(&pose, &-d), &world, &px).unwrap();
            let fd = (a - b) / (2.0 * h);
            let scale = j.column(k).norm().max(1.0);
            assert!((fd - j.column(k)).norm() < 1e-5 * scale, "column {k}: fd {fd} vs analytic {}", j.column(k));
        }
    }

    #[test]
    fn one_tag_noise_free_pose_is_exact() {
        let c = cam();
        let truth = Pose::from_rvec_tvec([0.2, -0.3, 0.05], [-50.0, 20.0, 1800.0]);
        let world = [
            Vector3::new(-150.0, -150.0, 0.0),
            Vector3::new(150.0, -150.0, 0.0),
            Vector3::new(150.0, 150.0, 0.0),
            Vector3::new(-150.0, 150.0, 0.0),
        ];
        let pixels = world.map(|w| c.project(&truth.transform(&w)).unwrap());
        let sol = solve_camera_pose(&c, &[BackgroundTagObservation { id: 3, pixels, world }], None).expect("solves");
        assert!(sol.pose.angle_to(&truth) < 1e-8, "angle {}", sol.pose.angle_to(&truth));
        assert!((sol.pose.centre() - truth.centre()).norm() < 1e-5);
        assert!(sol.rms_px < 1e-8 && sol.corners == 4 && sol.rejected_tags.is_empty());
    }

    #[test]
    fn rejects_garbage_input() {
        let c = cam();
        assert!(solve_camera_pose(&c, &[], None).is_err());
        let nan = BackgroundTagObservation { id: 0, pixels: [Point2::new(f64::NAN, 0.0); 4], world: [Vector3::zeros(); 4] };
        assert!(solve_camera_pose(&c, &[nan], None).is_err());
        let collapsed = BackgroundTagObservation { id: 0, pixels: [Point2::new(10.0, 10.0); 4], world: [Vector3::zeros(); 4] };
        assert!(solve_camera_pose(&c, &[collapsed], None).is_err());
    }
}
