//! Specimen tag pose: a rigid square of known edge, 6-DOF tag → world, solved by LM over
//! every view at once with the cameras fixed; σ of the centre from the covariance.
//!
//! Starts: the tag's previous solution (warm start) when given, otherwise closed-form
//! candidates (homography + mirror solution per view), ranked over all views. Outlier views
//! (a wrong decode, a corner pulled by blur) are dropped and reported, not averaged in.
//!
//! Covariance: `s² (JᵀJ)⁻¹`, with `s²` the pooled pixel noise (a per-tag estimate from 8
//! residuals per view alone is too noisy to be trusted) combined with the tag's own residual
//! as `(12 s_pooled² + SSR) / (12 + dof)`, plus the camera poses' uncertainty propagated
//! through the solve: `Σ += A_v Σ_v A_vᵀ`, `A_v = (JᵀJ)⁻¹ J_vᵀ J_cam,v`.

use nalgebra::{Matrix2x6, Matrix3, Matrix4x6, Matrix6, Point2, Vector2, Vector3};

use super::init::{homography, mirrored, pose_from_homography};
use super::lm::{minimize, CornerGroups, Evaluation, LmOptions, LmOutcome, PoseProblem};
use super::SolveError;
use tagdeflect_core::camera::{skew, CameraIntrinsics, Pose};
use tagdeflect_core::tags::tag_corners;

mod shift;
pub use shift::{common_shift_covariance, edge_normals, ViewShift};

/// One camera's view of a specimen tag.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TagView {
    /// The camera's intrinsics.
    pub intrinsics: CameraIntrinsics,
    /// The camera's pose, world → camera (held fixed in the solve).
    pub camera_pose: Pose,
    /// Covariance of `camera_pose` in the step parameters `(ω, v)` (as
    /// [`CameraPoseSolution::covariance`](super::CameraPoseSolution::covariance)); `None`
    /// treats the pose as exact.
    pub camera_pose_covariance: Option<Matrix6<f64>>,
    /// Detected corners, pixels, SPEC order (BL, BR, TR, TL as printed).
    pub corners: [Point2<f64>; 4],
    /// The corners' σ in this view relative to the pooled corner noise (≥ 1; 1: as pooled):
    /// the camera's edge fits' model error widens it (`tagdeflect_detect`'s
    /// `CameraDetector::corner_sigma_factor`). It widens the solution's covariance, never
    /// moves the solution.
    pub corner_sigma_factor: f64,
}

/// A solved specimen tag.
#[derive(Debug, Clone, PartialEq)]
pub struct TagSolution {
    /// Tag frame → world (tag frame: centre of the black square, x right, y up, z out).
    pub tag_to_world: Pose,
    /// Centre of the black square, world mm (`tag_to_world.translation`).
    pub centre_mm: Vector3<f64>,
    /// 1-σ uncertainty of `centre_mm` along world x, y, z, mm.
    pub sigma_mm: Vector3<f64>,
    /// 3×3 covariance of `centre_mm`, mm².
    pub centre_covariance: Matrix3<f64>,
    /// Full 6×6 covariance of the pose step `(ω, v)` (rad, mm; see [`retract`](super::lm::retract)),
    /// camera poses' uncertainty included (`centre_covariance` is its `v` block).
    pub covariance: Matrix6<f64>,
    /// The part of `covariance` from the corners' pixel noise alone (without the camera
    /// poses' uncertainty, which is common to every frame set while a camera is held still
    /// and so cancels from displacements).
    pub noise_covariance: Matrix6<f64>,
    /// The camera poses' part of `centre_covariance` per view used: (index into the input
    /// slice, mm²). A displacement across a re-pose keeps the re-posed camera's part alone.
    pub camera_pose_parts: Vec<(usize, Matrix3<f64>)>,
    /// Per view used: what offsets of its four edge lines do to the solve (the edge model's
    /// error shared by an edge's two corners, `measure`'s model error; see [`ViewShift`]).
    /// Empty unless [`corners_correlated`]: only that model error reads them, and their edge
    /// Jacobians cost a solve's hot path for nothing otherwise.
    pub view_shifts: Vec<ViewShift>,
    /// Reprojection RMS over the views used, pixels (per axis).
    pub rms_px: f64,
    /// Views used.
    pub views: usize,
    /// Indices (into the input slice) of views dropped as outliers.
    pub rejected_views: Vec<usize>,
    /// Sum of squared residuals of the views used, px² (feed it to a [`PixelNoisePool`]).
    pub ssr_px2: f64,
    /// Degrees of freedom of the residual (8 × views − 6).
    pub dof: usize,
    /// LM iterations spent (all starts).
    pub iterations: usize,
    /// True when the warm start was used for the final solution.
    pub warm_started: bool,
}

/// Residual of one tag corner in one view and its Jacobians with respect to the tag pose
/// step and the camera pose step (both `(ω, v)`, see [`retract`](super::lm::retract)).
/// `None` behind the camera.
pub(crate) fn tag_corner_terms(
    view: &TagView,
    tag_to_world: &Pose,
    corner_tag: &Vector3<f64>,
    pixel: &Point2<f64>,
) -> Option<(Vector2<f64>, Matrix2x6<f64>, Matrix2x6<f64>)> {
    let rc = tag_to_world.rotation * corner_tag;
    let pw = rc + tag_to_world.translation;
    let rcam = view.camera_pose.rotation * pw;
    let pc = rcam + view.camera_pose.translation;
    let (proj, jp) = view.intrinsics.project_with_jacobian(&pc)?;
    let jr = jp * view.camera_pose.rotation.matrix();
    let mut jt = Matrix2x6::zeros();
    jt.fixed_view_mut::<2, 3>(0, 0).copy_from(&(jr * -skew(&rc)));
    jt.fixed_view_mut::<2, 3>(0, 3).copy_from(&jr);
    let mut jc = Matrix2x6::zeros();
    jc.fixed_view_mut::<2, 3>(0, 0).copy_from(&(jp * -skew(&rcam)));
    jc.fixed_view_mut::<2, 3>(0, 3).copy_from(&jp);
    Some((proj - pixel, jt, jc))
}

/// The reprojection residuals (projected − detected, px) of a view's four corners for a tag
/// of edge `size_mm` at `tag_to_world`; `None` when a corner is behind the camera.
pub fn corner_residuals_px(view: &TagView, tag_to_world: &Pose, size_mm: f64) -> Option<[Vector2<f64>; 4]> {
    let corners = tag_corners(size_mm);
    let mut out = [Vector2::zeros(); 4];
    for (k, r) in out.iter_mut().enumerate() {
        *r = tag_corner_terms(view, tag_to_world, &corners[k], &view.corners[k])?.0;
    }
    Some(out)
}

struct TagProblem<'a> {
    views: Vec<(usize, &'a TagView)>,
    corners: [Vector3<f64>; 4],
}

impl PoseProblem for TagProblem<'_> {
    fn evaluate(&self, pose: &Pose, with_jacobian: bool) -> Option<Evaluation> {
        let mut e = Evaluation::zero();
        for (_, view) in &self.views {
            for k in 0..4 {
                let (r, j, _) = tag_corner_terms(view, pose, &self.corners[k], &view.corners[k])?;
                e.add(&r, &j, with_jacobian);
            }
        }
        Some(e)
    }
}

impl CornerGroups for TagProblem<'_> {
    fn groups(&self) -> usize {
        self.views.len()
    }
    fn corner_sq_error(&self, pose: &Pose, g: usize, k: usize) -> Option<f64> {
        let v = self.views[g].1;
        let p = v.intrinsics.project(&v.camera_pose.transform(&pose.transform(&self.corners[k])))?;
        Some((p - v.corners[k]).norm_squared())
    }
}

impl TagProblem<'_> {
    /// Closed-form starts: per view, the homography pose and its mirror, in world.
    fn cold_starts(&self) -> Vec<Pose> {
        let plane: Vec<Vector2<f64>> = self.corners.iter().map(|c| Vector2::new(c.x, c.y)).collect();
        let mut out = Vec::new();
        for (_, v) in &self.views {
            let image: Vec<Vector2<f64>> = v.corners.iter().map(|p| v.intrinsics.undistort(p)).collect();
            let Some(h) = homography(&plane, &image) else { continue };
            let Some((r, t)) = pose_from_homography(&h) else { continue };
            let cam_to_world = v.camera_pose.inverse();
            for rot in [r, mirrored(&r, &t)] {
                out.push(cam_to_world.compose(&Pose { rotation: rot, translation: t }));
            }
        }
        out
    }

    /// Best LM solution over the `n` best-ranked starts.
    fn solve_from(&self, starts: &[Pose], n: usize, iterations: &mut usize) -> Option<LmOutcome> {
        let mut ranked: Vec<(f64, &Pose)> = starts.iter().map(|p| (self.robust_cost(p), p)).collect();
        ranked.sort_by(|a, b| a.0.total_cmp(&b.0));
        let mut best: Option<LmOutcome> = None;
        for (_, start) in ranked.into_iter().take(n) {
            if let Some(out) = minimize(self, start, &LmOptions::default()) {
                *iterations += out.iterations;
                if best.as_ref().is_none_or(|b| out.evaluation.ssr < b.evaluation.ssr) {
                    best = Some(out);
                }
            }
        }
        best
    }
}

/// Weight (in residual degrees of freedom) of the pooled pixel noise against a tag's own
/// residual when estimating its residual variance.
const POOLED_PRIOR_DOF: f64 = 12.0;

/// Without a pooled noise estimate, a view is rejected only above this residual (px).
const NO_NOISE_REJECT_FLOOR_PX: f64 = 0.25;

/// Solves one specimen tag from its views.
///
/// * `views`: one per camera that saw the tag (≥ 1; a single view is solved monocularly from
///   the tag's size).
/// * `size_mm`: edge of the black square.
/// * `warm`: the tag's previous solution (tag → world), tried first; closed-form starts are
///   used when it is absent or fits badly.
/// * `pooled_sigma_px`: the pixel noise pooled over many tags/frames (see
///   [`PixelNoisePool`]); used for outlier tests, and for σ as a prior combined with this
///   tag's own residual. `None` uses the tag's own residual alone (noisy with few views).
pub fn solve_tag(views: &[TagView], size_mm: f64, warm: Option<&Pose>, pooled_sigma_px: Option<f64>) -> Result<TagSolution, SolveError> {
    if !size_mm.is_finite() || size_mm <= 0.0 {
        return Err(SolveError::InvalidInput { what: format!("tag size {size_mm} mm must be a positive number") });
    }
    let pooled = pooled_sigma_px.filter(|s| s.is_finite() && *s > 0.0);
    let usable: Vec<(usize, &TagView)> =
        views.iter().enumerate().filter(|(_, v)| v.corners.iter().all(|p| p.x.is_finite() && p.y.is_finite())).collect();
    if usable.is_empty() {
        return Err(SolveError::TooFewCorners { what: "specimen tag".into(), needed: 4, got: 0 });
    }
    let mut problem = TagProblem { views: usable, corners: tag_corners(size_mm) };
    let mut iterations = 0;
    let (best, warm_started) = first_fit(&problem, warm, pooled, &mut iterations)?;
    let (best, rejected) = reject_outlier_views(&mut problem, best, warm, pooled, &mut iterations)?;
    // A view left out: the solution is no longer the warm start's.
    let warm_started = warm_started && rejected.is_empty();
    tag_solution(&problem, best, pooled, rejected, iterations, warm_started)
}

/// The fit over every view: from the warm start when it fits (RMS within 4 × the pooled
/// noise, at least 0.5 px; 1 px without a pooled noise), else the best of the warm and the
/// closed-form starts; and whether the warm start won.
fn first_fit(
    problem: &TagProblem<'_>,
    warm: Option<&Pose>,
    pooled: Option<f64>,
    iterations: &mut usize,
) -> Result<(LmOutcome, bool), SolveError> {
    let mut warm_started = false;
    let mut best: Option<LmOutcome> = None;
    if let Some(w) = warm {
        if let Some(out) = minimize(problem, w, &LmOptions::default()) {
            *iterations += out.iterations;
            let rms = (out.evaluation.ssr / out.evaluation.residuals as f64).sqrt();
            let good = rms <= pooled.map_or(1.0, |s| (4.0 * s).max(0.5));
            if good {
                warm_started = true;
            }
            best = Some(out);
        }
    }
    if !warm_started {
        let starts = problem.cold_starts();
        if let Some(cold) = problem.solve_from(&starts, 4, iterations) {
            if best.as_ref().is_none_or(|b| cold.evaluation.ssr < b.evaluation.ssr) {
                best = Some(cold);
            } else {
                warm_started = true;
            }
        }
    }
    let best = best.ok_or_else(|| SolveError::Degenerate {
        what: "specimen tag: no start converged (corners degenerate or behind a camera)".into(),
    })?;
    Ok((best, warm_started))
}

/// Outlier views. Suspicious when the joint residual is too large for the pooled noise (χ²
/// test) — or, without a pooled noise, always with ≥ 3 views. The culprit is found by leaving
/// each view out in turn (a bad view drags the joint fit, so its own residual in the joint fit
/// understates it): the view whose removal leaves the most consistent remainder is dropped if
/// its residual against that remainder is far above it. Returns the fit over the views kept
/// and the (sorted) indices of those dropped.
fn reject_outlier_views(
    problem: &mut TagProblem<'_>,
    mut best: LmOutcome,
    warm: Option<&Pose>,
    pooled: Option<f64>,
    iterations: &mut usize,
) -> Result<(LmOutcome, Vec<usize>), SolveError> {
    let mut rejected = Vec::new();
    while problem.views.len() >= 2 && suspicious(&best, problem.views.len(), pooled) {
        let joint_rms = (best.evaluation.ssr / best.evaluation.residuals as f64).sqrt();
        let (victim, remainder) = if problem.views.len() >= 3 {
            let Some((v, out)) = worst_of_many(problem, &best, pooled, iterations) else { break };
            (v, Some(out))
        } else {
            (pick_two_view_outlier(problem, warm, iterations), None)
        };
        let (index, _) = problem.views[victim];
        tracing::debug!(view = index, joint_rms_px = joint_rms, views = problem.views.len(), "specimen tag: view rejected as an outlier");
        rejected.push(index);
        problem.views.remove(victim);
        best = match remainder {
            Some(out) => out,
            None => {
                let mut starts = problem.cold_starts();
                if let Some(w) = warm {
                    starts.push(*w);
                }
                problem
                    .solve_from(&starts, 3, iterations)
                    .ok_or_else(|| SolveError::Degenerate { what: "specimen tag: re-solve after rejecting a view failed".into() })?
            }
        };
    }
    rejected.sort_unstable();
    Ok((best, rejected))
}

/// Whether the joint fit over `views` views is too poor for the pooled noise (see
/// [`reject_outlier_views`]).
fn suspicious(best: &LmOutcome, views: usize, pooled: Option<f64>) -> bool {
    let dof_now = best.evaluation.residuals.saturating_sub(6) as f64;
    let joint_rms = (best.evaluation.ssr / best.evaluation.residuals as f64).sqrt();
    match pooled {
        Some(s) => best.evaluation.ssr / (s * s) > dof_now + 4.0 * (2.0 * dof_now).sqrt() + 4.0 && (views >= 3 || joint_rms > 2.5 * s),
        None => views >= 3 || joint_rms > 1.0,
    }
}

/// With three or more views: the view whose removal leaves the most consistent remainder,
/// and the remainder's fit — `None` when no remainder converges or the view's residual
/// against it is not far above the remainder's own.
fn worst_of_many(problem: &TagProblem<'_>, best: &LmOutcome, pooled: Option<f64>, iterations: &mut usize) -> Option<(usize, LmOutcome)> {
    let mut pick: Option<(usize, LmOutcome, f64)> = None;
    for v in 0..problem.views.len() {
        let sub = TagProblem {
            views: problem.views.iter().enumerate().filter(|(i, _)| *i != v).map(|(_, x)| *x).collect(),
            corners: problem.corners,
        };
        let Some(out) = minimize(&sub, &best.pose, &LmOptions::default()) else { continue };
        *iterations += out.iterations;
        let score = out.evaluation.ssr / out.evaluation.residuals.saturating_sub(6).max(1) as f64;
        if pick.as_ref().is_none_or(|p| score < p.2) {
            pick = Some((v, out, score));
        }
    }
    let (v, out, _) = pick?;
    let single = TagProblem { views: vec![problem.views[v]], corners: problem.corners };
    let out_rms = single.group_rms(&out.pose).and_then(|r| r.first().copied()).unwrap_or(f64::INFINITY);
    let rest_rms = (out.evaluation.ssr / out.evaluation.residuals as f64).sqrt();
    // Without a noise estimate only the ratio is known, and a ratio of small numbers is
    // noisy: demand more, and an absolute floor.
    let limit = match pooled {
        Some(s) => (3.0 * rest_rms).max(3.0 * s),
        None => (4.0 * rest_rms).max(NO_NOISE_REJECT_FLOOR_PX),
    };
    (out_rms > limit).then_some((v, out))
}

/// The solution of the fit `best` over the views kept: its σ from the residual variance and
/// the camera poses' covariances.
fn tag_solution(
    problem: &TagProblem<'_>,
    best: LmOutcome,
    pooled: Option<f64>,
    rejected: Vec<usize>,
    iterations: usize,
    warm_started: bool,
) -> Result<TagSolution, SolveError> {
    let n = best.evaluation.residuals;
    let ssr = best.evaluation.ssr;
    let dof = n.saturating_sub(6);
    // Residual variance: the pooled noise as a prior worth POOLED_PRIOR_DOF degrees of
    // freedom, combined with this tag's own residual (so a view set that is noisier than
    // usual — blur — gets a larger σ, while a 2-dof monocular residual barely moves it).
    let s2 = match pooled {
        Some(s) => (POOLED_PRIOR_DOF * s * s + ssr) / (POOLED_PRIOR_DOF + dof as f64),
        None => ssr / dof.max(1) as f64,
    };
    let h_inv = best
        .evaluation
        .jtj
        .try_inverse()
        .ok_or_else(|| SolveError::Degenerate { what: "specimen tag: singular normal equations".into() })?;
    let noise_cov = widened(h_inv * s2, problem, &best.pose, &h_inv, (s2, corners_correlated()));
    let (cov, camera_pose_parts) = with_camera_poses(noise_cov, problem, &best.pose, &h_inv);
    let centre_cov: Matrix3<f64> = cov.fixed_view::<3, 3>(3, 3).into_owned();
    let sigma = Vector3::new(centre_cov[(0, 0)].max(0.0).sqrt(), centre_cov[(1, 1)].max(0.0).sqrt(), centre_cov[(2, 2)].max(0.0).sqrt());
    Ok(TagSolution {
        tag_to_world: best.pose,
        centre_mm: best.pose.translation,
        sigma_mm: sigma,
        centre_covariance: centre_cov,
        covariance: cov,
        noise_covariance: noise_cov,
        camera_pose_parts,
        view_shifts: if corners_correlated() { shift::view_shifts(&edge_jacobians(problem, &best.pose), &h_inv) } else { Vec::new() },
        rms_px: (ssr / n as f64).sqrt(),
        views: problem.views.len(),
        rejected_views: rejected,
        ssr_px2: ssr,
        dof,
        iterations,
        warm_started,
    })
}

/// Each view's [`ViewShift`] for a tag of edge `size_mm` at `pose` seen in every one of
/// `views` (none rejected), whatever [`corners_correlated`] says: what a solve at `pose`
/// would hand over with the switch on. `None` when a corner is behind a camera or the normal
/// equations are singular. For tests of the model error.
#[cfg(test)]
pub(crate) fn view_shifts_at(views: &[TagView], size_mm: f64, pose: &Pose) -> Option<Vec<ViewShift>> {
    let problem = TagProblem { views: views.iter().enumerate().collect(), corners: tag_corners(size_mm) };
    let h_inv = problem.evaluate(pose, true)?.jtj.try_inverse()?;
    Some(shift::view_shifts(&edge_jacobians(&problem, pose), &h_inv))
}

/// Each view's edges' Jacobians (tag pose step), by input index: row `i` the edge's normal
/// times its two corners' Jacobians summed ([`ViewShift`]).
fn edge_jacobians(problem: &TagProblem<'_>, pose: &Pose) -> Vec<(usize, Matrix4x6<f64>)> {
    let rows = |view: &TagView| -> Matrix4x6<f64> {
        let j: Vec<Matrix2x6<f64>> = (0..4)
            .map(|k| tag_corner_terms(view, pose, &problem.corners[k], &view.corners[k]).map_or(Matrix2x6::zeros(), |t| t.1))
            .collect();
        let normals = edge_normals(&view.corners);
        let mut e = Matrix4x6::zeros();
        for (i, n) in normals.iter().enumerate() {
            e.set_row(i, &(n.transpose() * (j[i] + j[(i + 1) % 4])));
        }
        e
    };
    problem.views.iter().map(|(index, view)| (*index, rows(view))).collect()
}

/// The pixel noise's covariance `s² H⁻¹` (`plain`) with each view's corners' σ widened by its
/// [`TagView::corner_sigma_factor`] `f_v`: the covariance of the same (unweighted) fit when
/// view `v`'s corners have variance `f_v² s²`, `s² H⁻¹ (Σ_v f_v² H_v) H⁻¹`, `H_v` the view's
/// share of the normal matrix. `plain` itself while every factor is 1 — unless `correlated`:
/// then the corners that share an edge are correlated along its normal
/// ([`EDGE_CORNER_CORRELATION`]).
fn widened(
    plain: Matrix6<f64>,
    problem: &TagProblem<'_>,
    pose: &Pose,
    h_inv: &Matrix6<f64>,
    (s2, correlated): (f64, bool),
) -> Matrix6<f64> {
    let factor = |v: &TagView| if v.corner_sigma_factor.is_finite() { v.corner_sigma_factor.max(1.0) } else { 1.0 };
    if !correlated && problem.views.iter().all(|(_, v)| factor(v) == 1.0) {
        return plain;
    }
    let mut middle = Matrix6::zeros();
    for (_, view) in &problem.views {
        let f2 = factor(view).powi(2);
        let j: Vec<Option<Matrix2x6<f64>>> =
            (0..4).map(|k| tag_corner_terms(view, pose, &problem.corners[k], &view.corners[k]).map(|t| t.1)).collect();
        for jt in j.iter().flatten() {
            middle += f2 * jt.transpose() * jt;
        }
        if !correlated {
            continue;
        }
        // Corners a and b share the edge between them: along its normal n their errors are
        // correlated at EDGE_CORNER_CORRELATION (the line's angle error moves them apart).
        for a in 0..4 {
            let b = (a + 1) % 4;
            let (Some(ja), Some(jb)) = (j[a], j[b]) else { continue };
            let u = view.corners[b] - view.corners[a];
            let n = Vector2::new(-u.y, u.x).normalize();
            let nn = n * n.transpose();
            middle += f2 * EDGE_CORNER_CORRELATION * (ja.transpose() * nn * jb + jb.transpose() * nn * ja);
        }
    }
    h_inv * middle * h_inv * s2
}

/// The correlation, along their edge's normal, of the errors of the two corners an edge line
/// joins: a line fitted to samples spread evenly along it has an angle error that moves its
/// ends by `√3` times its offset error, in opposite directions: `(1 − 3) / (1 + 3)`.
const EDGE_CORNER_CORRELATION: f64 = -0.5;

/// Whether the pixel noise's covariance takes the corners' errors as correlated through their
/// shared edge lines: `TAGDEFLECT_CORNER_CORRELATION=edges` (a measurement, not the default;
/// docs/accuracy.md, "The displacement σ's terms against the real error"; with it the
/// measurement adds each view's edge offsets, "A tag's edge offsets as a model-error term"). Read once.
pub fn corners_correlated() -> bool {
    static ON: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *ON.get_or_init(|| std::env::var("TAGDEFLECT_CORNER_CORRELATION").is_ok_and(|v| v == "edges"))
}

/// Each view's camera poses' part of a centre's covariance, by input index, mm².
type CameraParts = Vec<(usize, Matrix3<f64>)>;

/// The tag's covariance: the pixel noise's `noise_cov` plus each view's camera pose
/// covariance carried through the fit (`A Σ_cam Aᵀ`, `A = H⁻¹ Σ_k J_tagᵀ J_cam`), and each
/// view's part of the centre's covariance (by input index).
fn with_camera_poses(noise_cov: Matrix6<f64>, problem: &TagProblem<'_>, pose: &Pose, h_inv: &Matrix6<f64>) -> (Matrix6<f64>, CameraParts) {
    let mut cov = noise_cov;
    let mut parts = Vec::with_capacity(problem.views.len());
    for (index, view) in &problem.views {
        let Some(cam_cov) = view.camera_pose_covariance else { continue };
        let mut b = Matrix6::zeros();
        for k in 0..4 {
            if let Some((_, jt, jc)) = tag_corner_terms(view, pose, &problem.corners[k], &view.corners[k]) {
                b += jt.transpose() * jc;
            }
        }
        let a = h_inv * b;
        let part = a * cam_cov * a.transpose();
        cov += part;
        parts.push((*index, part.fixed_view::<3, 3>(3, 3).into_owned()));
    }
    (cov, parts)
}

/// With two inconsistent views, which one to drop: each view is solved alone; with a warm
/// start the view whose solution lies farther from it goes, otherwise the view that fits a
/// square of the known size worse.
fn pick_two_view_outlier(problem: &TagProblem<'_>, warm: Option<&Pose>, iterations: &mut usize) -> usize {
    let mut scores = [f64::INFINITY; 2];
    for (i, score) in scores.iter_mut().enumerate() {
        let single = TagProblem { views: vec![problem.views[i]], corners: problem.corners };
        let mut starts = single.cold_starts();
        if let Some(w) = warm {
            starts.push(*w);
        }
        if let Some(out) = single.solve_from(&starts, 3, iterations) {
            *score = match warm {
                Some(w) => (out.pose.translation - w.translation).norm(),
                None => out.evaluation.ssr,
            };
        }
    }
    if scores[0] > scores[1] {
        0
    } else {
        1
    }
}

/// A running estimate of the detector's pixel noise (per axis), pooled over many tag
/// solutions, with exponential forgetting so it follows slow changes (light, blur).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PixelNoisePool {
    ssr: f64,
    dof: f64,
    keep: f64,
    min_dof: f64,
}

impl Default for PixelNoisePool {
    fn default() -> Self {
        Self::new(0.995, 20.0)
    }
}

impl PixelNoisePool {
    /// `keep`: fraction of the past kept per added solution (e.g. 0.995: memory of ~200
    /// tags); `min_dof`: residual degrees of freedom needed before [`sigma_px`](Self::sigma_px)
    /// answers.
    pub fn new(keep: f64, min_dof: f64) -> Self {
        Self { ssr: 0.0, dof: 0.0, keep: keep.clamp(0.0, 1.0), min_dof: min_dof.max(1.0) }
    }

    /// Adds a residual sum of squares with its degrees of freedom.
    pub fn add(&mut self, ssr_px2: f64, dof: usize) {
        if dof == 0 || !ssr_px2.is_finite() || ssr_px2 < 0.0 {
            return;
        }
        // Winsorised at 2.5 σ RMS so a few blurred or outlying views do not inflate the
        // noise of all the others (under Gaussian noise this trims < 0.3 %).
        let ssr = match self.sigma_px() {
            Some(s) => ssr_px2.min(dof as f64 * 6.25 * s * s),
            None => ssr_px2,
        };
        self.ssr = self.ssr * self.keep + ssr;
        self.dof = self.dof * self.keep + dof as f64;
    }

    /// Adds a solved tag's residual.
    pub fn add_solution(&mut self, solution: &TagSolution) {
        self.add(solution.ssr_px2, solution.dof);
    }

    /// The pooled noise (px, per axis), once enough residuals are in.
    pub fn sigma_px(&self) -> Option<f64> {
        (self.dof >= self.min_dof).then(|| (self.ssr / self.dof).sqrt())
    }
}

#[cfg(test)]
mod tests;
