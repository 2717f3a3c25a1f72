//! A camera's pose kept across frame sets: still while the camera is static, re-posed when
//! it is bumped.
//!
//! Policy (why): the feed reports displacements against each tag's first solved position,
//! so any change of a camera's pose estimate shows up as a fake displacement. After the
//! first posing the pose is therefore *held* (by default) — its error is a constant that
//! cancels in the displacement — instead of being re-estimated every frame (that noise would
//! leak into every frame) or refined by a running mean (that would drift by the first pose's
//! error over the run). The background corners are still averaged while static, and they
//! carry the measurement across a bump: the camera's motion is measured between the
//! averaged corners before the bump and the running mean after it (refined over
//! [`HeldPoseOptions::average_updates_after_bump`] updates, then held), and applied to the
//! held pose. The held pose's constant error thus carries over, and displacements stay
//! continuous across the bump to the accuracy of averaged corners rather than jumping by
//! a fresh single-frame pose error.
//!
//! Bump test: the median distance, over the corners seen, between the observed background
//! corners and the held pose's projections; a bump when it exceeds
//! `max(bump_floor_px, bump_noise_factor × corner noise)`, the corner noise being the pooled
//! per-axis scatter of each corner around its running mean while static. A median is used so
//! a partially occluded or mis-detected tag cannot fake (or hide) a bump; tags that disagree
//! with the pose are left out of the running means.
//!
//! Checks before a re-pose replaces the held pose (a camera can move far: a tripod knocked
//! over, a camera turned by hand; see `docs/operations.md`): the re-pose must fit its own
//! corners (RMS ≤ max([`REPOSE_MAX_RMS_PX`], bump factor × corner noise)); and a re-pose that
//! rests on one tag — whose corners allow two poses, the tag tilted one way or its mirror
//! ([`super::camera_pose::single_tag_minima`]) — must be decided by its corners (the other
//! minimum's RMS above [`AMBIGUITY_RATIO`] × the best one's and above
//! max([`AMBIGUITY_FLOOR_PX`], 3 × corner noise)) or else by the held pose (exactly one of the
//! minima within [`HELD_CONSISTENT_DEG`] of it: a small bump). A re-pose that fails a check
//! does not replace the held pose: the camera is reported unposed (`pose: None`,
//! [`HeldPoseStatus::refused`] with the reason) until a later update passes the checks (more
//! tags in view) or shows the camera back where it was held (the bump test passes again,
//! against the corner means kept from before the bump); its old pose is never used while
//! refused, so no position is measured from a pose that failed its checks. The first posing
//! has nothing to check a one-tag pose against: it takes the best minimum and says in
//! `message` when the mirror fits as well.
//!
//! Slow drift (see [`super::drift`]): when updates carry their time
//! ([`HeldCameraPose::update_at`]) and [`HeldPoseOptions::drift`] is enabled, each static
//! update also solves the camera from its own background corners and feeds that to a
//! Kalman filter of the camera's motion since the pose was fixed; the pose in use is the
//! held pose moved by the filtered drift. The running means are kept de-drifted (each
//! corner minus the image motion the estimated drift gives it), so they stay the corners of
//! the held pose's moment, and the bump test compares each corner with its mean moved by
//! the predicted drift: slow drift never adds up to a bump, a jump is still caught in the
//! update it happens.

use std::collections::HashMap;

use nalgebra::{Matrix6, Point2, Vector2, Vector3};

use super::camera_pose::{single_tag_minima, solve_camera_pose, BackgroundTagObservation, CameraPoseSolution};
use super::drift::{DriftConfig, DriftEstimate, DriftFilter};
use super::lm::median;
use tagdeflect_core::camera::{CameraIntrinsics, Pose};

/// Tuning of a [`HeldCameraPose`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HeldPoseOptions {
    /// Fewest background corners to pose (or test) the camera in an update (4 = one tag).
    pub min_corners: usize,
    /// Smallest median corner shift (px) taken as a bump.
    pub bump_floor_px: f64,
    /// A bump is a median shift above this many times the corner noise (px, per axis).
    pub bump_noise_factor: f64,
    /// Updates whose corners are averaged into the pose after the first posing (1 = hold
    /// the first pose; see the module docs).
    pub average_updates_initial: usize,
    /// Updates whose corners are averaged into the pose after a bump's re-posing.
    pub average_updates_after_bump: usize,
    /// Slow-drift tracking while the pose is held (only in [`HeldCameraPose::update_at`]).
    pub drift: DriftConfig,
}

impl Default for HeldPoseOptions {
    fn default() -> Self {
        Self {
            min_corners: 4,
            bump_floor_px: 1.0,
            bump_noise_factor: 6.0,
            average_updates_initial: 1,
            average_updates_after_bump: 10,
            drift: DriftConfig::default(),
        }
    }
}

/// What one [`HeldCameraPose::update`] found.
#[derive(Debug, Clone, PartialEq)]
pub struct HeldPoseStatus {
    /// The pose to use for this frame set (world → camera); `None` while the camera has
    /// never been posed, or after a bump it could not be re-posed from.
    pub pose: Option<Pose>,
    /// Covariance of `pose` in the step parameters `(ω, v)`; `None` for a fixed pose.
    pub covariance: Option<Matrix6<f64>>,
    /// The camera moved in this update (detected and, if `pose` is `Some`, re-posed).
    pub bumped: bool,
    /// Too few background corners this update: the pose was kept from before, unchecked.
    pub stale: bool,
    /// The pose is the configured one (never estimated).
    pub fixed: bool,
    /// True in the update that first posed the camera.
    pub first_pose: bool,
    /// Reprojection RMS (px, per axis) of this update's background corners against `pose`.
    pub rms_px: Option<f64>,
    /// Median distance (px) between this update's corners and the previous pose's
    /// projections: the bump statistic.
    pub shift_px: Option<f64>,
    /// The bump threshold in force, px.
    pub bump_threshold_px: f64,
    /// Background corners observed in this update.
    pub corners: usize,
    /// Background tags left out this update (outliers against the pose).
    pub rejected_tags: Vec<u32>,
    /// Pooled corner noise (px, per axis) while static; `None` until measured.
    pub noise_px: Option<f64>,
    /// A human-readable note on anything unusual (too few tags, failed re-pose).
    pub message: Option<String>,
    /// The camera moved and no re-pose passed the checks (see the module docs): why. `pose`
    /// is `None`; nothing is to be measured from this camera in this update.
    pub refused: Option<String>,
    /// The camera's estimated slow drift since its pose was last fixed (first posing or
    /// re-posing after a bump); `None` while not tracked (configured pose, no times, disabled).
    pub drift: Option<DriftEstimate>,
}

/// Static updates after which a held pose is checked once against the averaged corners.
const SANITY_CHECK_UPDATES: usize = 10;
/// Largest reprojection RMS (px, per axis) of a re-pose's own corners (or the bump factor ×
/// the corner noise, if larger) for it to replace the held pose.
pub const REPOSE_MAX_RMS_PX: f64 = 3.0;
/// A one-tag pose is decided by its corners when the other minimum's RMS is above this many
/// times the best one's...
pub const AMBIGUITY_RATIO: f64 = 4.0;
/// ...and above this (px) and 3 × the corner noise.
pub const AMBIGUITY_FLOOR_PX: f64 = 1.0;
/// An undecided one-tag pose is taken when exactly one of its minima is within this angle
/// of the held pose (a small bump; the mirror solution is tens of degrees away).
pub const HELD_CONSISTENT_DEG: f64 = 3.0;

#[derive(Debug, Clone, Copy)]
struct CornerStats {
    world: Vector3<f64>,
    n: f64,
    mean: Vector2<f64>,
    m2: f64,
}

/// Keeps one camera's pose across frame sets. See the module docs for the policy.
#[derive(Debug, Clone)]
pub struct HeldCameraPose {
    intrinsics: CameraIntrinsics,
    options: HeldPoseOptions,
    fixed: bool,
    /// The pose that fits the images (held after settling); reported pose = `raw ∘ fix`.
    raw: Option<Pose>,
    /// World → world correction keeping the reported pose continuous across bumps.
    fix: Pose,
    /// Updates accumulated into the running means since the last (re-)posing.
    period_updates: usize,
    covariance: Option<Matrix6<f64>>,
    corners: HashMap<(u32, usize), CornerStats>,
    archived_m2: f64,
    archived_dof: f64,
    averaged_updates: usize,
    average_limit: usize,
    /// The drift filter of the held `raw` pose (see the module docs).
    drift: Option<DriftFilter>,
    /// Time of the update in progress (from [`HeldCameraPose::update_at`]).
    now_ns: Option<i64>,
    /// The camera moved away from the held `raw` pose and no re-pose passed the checks:
    /// why (the pose is not reported while set; see the module docs).
    refused: Option<String>,
}

impl HeldCameraPose {
    /// A tracker for a camera; `fixed_pose` (from the config's rvec/tvec) disables estimation.
    pub fn new(intrinsics: CameraIntrinsics, fixed_pose: Option<Pose>) -> Self {
        Self::with_options(intrinsics, fixed_pose, HeldPoseOptions::default())
    }

    /// As [`new`](Self::new) with explicit tuning.
    pub fn with_options(intrinsics: CameraIntrinsics, fixed_pose: Option<Pose>, options: HeldPoseOptions) -> Self {
        Self {
            intrinsics,
            options,
            fixed: fixed_pose.is_some(),
            raw: fixed_pose,
            fix: Pose::identity(),
            period_updates: 0,
            covariance: None,
            corners: HashMap::new(),
            archived_m2: 0.0,
            archived_dof: 0.0,
            averaged_updates: 0,
            average_limit: options.average_updates_initial.max(1),
            drift: None,
            now_ns: None,
            refused: None,
        }
    }

    /// The current pose (world → camera) to measure with, if any (`None` while a re-pose
    /// is refused: see the module docs).
    pub fn pose(&self) -> Option<Pose> {
        if self.refused.is_some() {
            return None;
        }
        self.current_raw().map(|r| r.compose(&self.fix))
    }

    /// True when the pose is estimated from background tags (not configured).
    pub fn estimated(&self) -> bool {
        !self.fixed
    }

    /// Why the camera is unposed after it moved (a re-pose refused by the checks), if so.
    pub fn refused(&self) -> Option<&str> {
        self.refused.as_deref()
    }

    /// The bump statistic these background tags would give against the held pose, without
    /// taking them in: the median corner shift (px; infinite when the held pose cannot
    /// project them), `None` when there is nothing to test (fixed or never posed, too few
    /// corners). The measurement uses it to search a frame whole before posing from it.
    pub fn preview_shift_px(&self, t_ns: i64, tags: &[BackgroundTagObservation]) -> Option<f64> {
        let pose = self.raw.filter(|_| !self.fixed)?;
        let tags: Vec<&BackgroundTagObservation> = tags.iter().filter(|t| valid_observation(t)).collect();
        if tags.len() * 4 < self.options.min_corners.max(4) {
            return None;
        }
        let predicted = match &self.drift {
            Some(f) if self.now_ns.is_some() => f.predicted_pose(t_ns),
            _ => pose,
        };
        let shifts: Vec<f64> =
            tags.iter().flat_map(|t| (0..4).map(move |k| (*t, k))).map(|(t, k)| self.corner_shift(&pose, &predicted, t, k)).collect();
        median(&shifts)
    }

    /// The image-fitted pose now: `raw` moved by the estimated drift.
    fn current_raw(&self) -> Option<Pose> {
        match &self.drift {
            Some(f) if self.raw.is_some() => Some(f.pose()),
            _ => self.raw,
        }
    }

    /// The estimated drift since the pose was last fixed, if tracked.
    pub fn drift(&self) -> Option<DriftEstimate> {
        self.drift.as_ref().filter(|_| self.raw.is_some()).map(|f| f.estimate())
    }

    /// (Re)starts the drift filter on the current `raw` pose (called whenever `raw` is set).
    fn hold(&mut self) {
        self.drift = match (self.raw, self.now_ns) {
            (Some(raw), Some(t)) if self.options.drift.enabled && !self.fixed => {
                Some(DriftFilter::new(self.options.drift, raw, self.covariance.as_ref(), t))
            }
            _ => None,
        };
    }

    /// The current pose's covariance (step parameters `(ω, v)`), if estimated.
    pub fn covariance(&self) -> Option<Matrix6<f64>> {
        self.covariance
    }

    /// Pooled per-axis scatter (px) of the background corners around their running means.
    pub fn noise_px(&self) -> Option<f64> {
        let (m2, dof) = self.corners.values().fold((self.archived_m2, self.archived_dof), |(m, d), c| (m + c.m2, d + (c.n - 1.0).max(0.0)));
        (dof >= 10.0).then(|| (m2 / (2.0 * dof)).sqrt())
    }

    /// The bump threshold now in force, px.
    pub fn bump_threshold_px(&self) -> f64 {
        let noise = self.noise_px().unwrap_or(0.0);
        self.options.bump_floor_px.max(self.options.bump_noise_factor * noise)
    }

    /// Feeds one frame set's background tags seen by this camera (possibly none). Without
    /// a time no drift is tracked: the pose is held exactly while static.
    pub fn update(&mut self, tags: &[BackgroundTagObservation]) -> HeldPoseStatus {
        self.now_ns = None;
        self.drift = None;
        self.update_inner(tags)
    }

    /// As [`update`](Self::update) for a frame set taken at `t_ns` (ns): with
    /// [`HeldPoseOptions::drift`] enabled the held pose follows slow drift.
    pub fn update_at(&mut self, t_ns: i64, tags: &[BackgroundTagObservation]) -> HeldPoseStatus {
        self.now_ns = Some(t_ns);
        self.update_inner(tags)
    }

    fn update_inner(&mut self, tags: &[BackgroundTagObservation]) -> HeldPoseStatus {
        let tags: Vec<BackgroundTagObservation> = tags.iter().filter(|t| valid_observation(t)).copied().collect();
        let corners = tags.len() * 4;
        let threshold = self.bump_threshold_px();
        let mut status = HeldPoseStatus {
            pose: self.pose(),
            covariance: self.covariance,
            bumped: false,
            stale: false,
            fixed: self.fixed,
            first_pose: false,
            rms_px: None,
            shift_px: None,
            bump_threshold_px: threshold,
            corners,
            rejected_tags: Vec::new(),
            noise_px: self.noise_px(),
            message: None,
            refused: self.refused.clone(),
            drift: self.drift(),
        };
        if self.fixed {
            status.rms_px = self.raw.and_then(|p| self.rms(&p, &tags));
            return status;
        }
        if corners < self.options.min_corners.max(4) {
            let msg = format!("{} background corners seen, {} needed: pose kept from before", corners, self.options.min_corners.max(4));
            tracing::debug!("{msg}");
            status.stale = self.raw.is_some();
            status.message = Some(msg);
            return status;
        }
        let Some(pose) = self.raw else {
            return self.first_posing(tags, status);
        };
        // The held pose moved by the drift predicted for now (= `pose` when not tracked).
        let predicted = match (&self.drift, self.now_ns) {
            (Some(f), Some(t)) => f.predicted_pose(t),
            _ => pose,
        };

        // Bump test: each corner against its running mean while static (immune to model
        // errors such as an imperfect calibration), or the held pose's projection for a
        // corner not yet averaged.
        let shifts: Vec<f64> =
            tags.iter().flat_map(|t| (0..4).map(move |k| (t, k))).map(|(t, k)| self.corner_shift(&pose, &predicted, t, k)).collect();
        let shift = median(&shifts).unwrap_or(0.0);
        status.shift_px = Some(shift);
        if shift > threshold {
            tracing::warn!(
                shift_px = shift,
                threshold_px = threshold,
                corners,
                "camera bumped: background tags moved in the image; re-posing"
            );
            status.bumped = true;
            return match self.checked_repose(&tags, &pose) {
                Ok(sol) => {
                    // Keep the reported pose continuous: the camera's motion is measured
                    // between the averaged corners before the bump and those after it, so the
                    // held pose's own error carries over instead of a new single-frame error
                    // replacing it.
                    if self.period_updates >= 2 {
                        if let Ok(before) = solve_camera_pose(&self.intrinsics, &self.averaged_observations(), Some(&pose)) {
                            self.fix = before.pose.inverse().compose(&pose).compose(&self.fix);
                        }
                    }
                    self.archive_noise();
                    self.corners.clear();
                    self.period_updates = 0;
                    self.refused = None;
                    self.raw = Some(sol.pose);
                    self.covariance = Some(sol.covariance);
                    self.hold();
                    self.averaged_updates = 1;
                    self.average_limit = self.options.average_updates_after_bump.max(1);
                    self.accumulate(&tags, &sol.rejected_tags);
                    status.pose = self.pose();
                    status.covariance = Some(sol.covariance);
                    status.rms_px = Some(sol.rms_px);
                    status.rejected_tags = sol.rejected_tags;
                    status.refused = None;
                    status.drift = self.drift();
                    status
                }
                Err(why) => {
                    let why = why.to_string();
                    // The held pose stays the reference (with its corner means) but is not
                    // used: the camera is unposed until a re-pose passes or it is back.
                    tracing::warn!(reason = %why, "camera moved and its re-pose failed the checks: not posed (its views are left out)");
                    self.refused = Some(why.clone());
                    status.pose = None;
                    status.covariance = None;
                    status.rms_px = None;
                    status.drift = None;
                    status.message = Some(format!("moved, re-pose refused: {why}"));
                    status.refused = Some(why);
                    status
                }
            };
        }
        if let Some(why) = self.refused.take() {
            tracing::info!(shift_px = shift, "camera back at its held pose: posed again");
            status.message = Some(format!("back at the held pose (was refused: {why})"));
            status.refused = None;
        }

        // Static: tags that disagree with the pose stay out of the running means.
        let mut rejected = Vec::new();
        for t in &tags {
            let d: Vec<f64> = (0..4).map(|k| self.corner_shift(&pose, &predicted, t, k)).collect();
            if median(&d).unwrap_or(f64::INFINITY) > threshold {
                tracing::debug!(tag = t.id, "background tag disagrees with the held pose; left out");
                rejected.push(t.id);
            }
        }
        let averaging = self.averaged_updates < self.average_limit;
        if !averaging {
            self.measure_drift(&tags, &rejected, &predicted);
        }
        self.accumulate(&tags, &rejected);
        if averaging {
            self.averaged_updates += 1;
            let averaged = self.averaged_observations();
            match solve_camera_pose(&self.intrinsics, &averaged, Some(&pose)) {
                Ok(sol) => {
                    self.raw = Some(sol.pose);
                    self.covariance = Some(sol.covariance);
                    self.hold();
                }
                Err(e) => tracing::debug!(error = %e, "pose refinement from averaged corners failed; pose kept"),
            }
        } else if self.period_updates == SANITY_CHECK_UPDATES {
            // Safety net: a held pose from a poor first frame (blur) that does not fit the
            // averaged corners is re-fitted to them once.
            let averaged = self.averaged_observations();
            let misfit: Vec<f64> = averaged
                .iter()
                .flat_map(|t| (0..4).map(move |k| (t, k)))
                .map(|(t, k)| self.intrinsics.project(&pose.transform(&t.world[k])).map_or(f64::INFINITY, |p| (p - t.pixels[k]).norm()))
                .collect();
            let misfit = median(&misfit).unwrap_or(0.0);
            if misfit > threshold {
                let refit = solve_camera_pose(&self.intrinsics, &averaged, Some(&pose)).ok().filter(|sol| {
                    let d: Vec<f64> = averaged
                        .iter()
                        .flat_map(|t| (0..4).map(move |k| (t, k)))
                        .map(|(t, k)| {
                            self.intrinsics.project(&sol.pose.transform(&t.world[k])).map_or(f64::INFINITY, |p| (p - t.pixels[k]).norm())
                        })
                        .collect();
                    // Only when the re-fit really explains the corners better (a calibration
                    // error would misfit any pose alike).
                    median(&d).unwrap_or(f64::INFINITY) < 0.5 * misfit
                });
                if let Some(sol) = refit {
                    let msg = format!("held pose misfit the averaged background corners by {misfit:.2} px; re-fitted");
                    tracing::warn!("{msg}");
                    self.raw = Some(sol.pose);
                    self.covariance = Some(sol.covariance);
                    // The re-fit is of the held pose's moment (de-drifted means): the drift
                    // so far stays, only the held pose's own error is new.
                    if let Some(f) = self.drift.as_mut() {
                        f.rebase(sol.pose, Some(&sol.covariance));
                    }
                    status.bumped = true;
                    status.message = Some(msg);
                }
            }
        }
        status.pose = self.pose();
        status.covariance = self.covariance;
        status.rms_px = self.raw.and_then(|p| self.rms(&p, &tags));
        status.rejected_tags = rejected;
        status.noise_px = self.noise_px();
        status.drift = self.drift();
        status
    }

    /// A re-pose from this update's corners that passes the checks of the module docs, or
    /// why not.
    fn checked_repose(&self, tags: &[BackgroundTagObservation], held: &Pose) -> Result<CameraPoseSolution, RefusedRepose> {
        let sol = solve_camera_pose(&self.intrinsics, tags, Some(held)).map_err(RefusedRepose::NoPose)?;
        let noise = self.noise_px().unwrap_or(0.0);
        let limit = REPOSE_MAX_RMS_PX.max(self.options.bump_noise_factor * noise);
        if sol.rms_px.is_nan() || sol.rms_px > limit {
            return Err(RefusedRepose::Misfit { rms_px: sol.rms_px, limit_px: limit });
        }
        if let Some(why) = self.one_tag_ambiguity(tags, &sol) {
            let consistent = self.one_tag_minima(tags, &sol).map(|m| {
                let near: Vec<&(Pose, f64)> = m.iter().filter(|(p, _)| p.angle_to(held) < HELD_CONSISTENT_DEG.to_radians()).collect();
                near.len() == 1 && near[0].0.angle_to(&sol.pose) < 0.5f64.to_radians()
            });
            if consistent != Some(true) {
                return Err(RefusedRepose::Ambiguous(why));
            }
            tracing::info!("one-tag re-pose undecided by its corners ({why}); the minimum next to the held pose is taken");
        }
        Ok(sol)
    }

    /// The minima of `sol`'s pose when it rests on one tag, else `None`.
    fn one_tag_minima(&self, tags: &[BackgroundTagObservation], sol: &CameraPoseSolution) -> Option<Vec<(Pose, f64)>> {
        let used: Vec<&BackgroundTagObservation> = tags.iter().filter(|t| !sol.rejected_tags.contains(&t.id)).collect();
        (used.len() == 1).then(|| single_tag_minima(&self.intrinsics, used[0]))
    }

    /// When `sol` rests on one tag whose corners do not decide between its two minima (see
    /// the module docs), a description of the two fits.
    fn one_tag_ambiguity(&self, tags: &[BackgroundTagObservation], sol: &CameraPoseSolution) -> Option<String> {
        let minima = self.one_tag_minima(tags, sol)?;
        if minima.len() < 2 {
            return None;
        }
        let (best, other) = (minima[0].1, minima[1].1);
        let floor = AMBIGUITY_FLOOR_PX.max(3.0 * self.noise_px().unwrap_or(0.0));
        let decided = other > AMBIGUITY_RATIO * best && other > floor;
        (!decided).then(|| {
            format!(
                "its mirror pose fits with RMS {other:.2} px against {best:.2} px, {:.1}° away",
                minima[0].0.angle_to(&minima[1].0).to_degrees()
            )
        })
    }

    fn first_posing(&mut self, tags: Vec<BackgroundTagObservation>, mut status: HeldPoseStatus) -> HeldPoseStatus {
        match solve_camera_pose(&self.intrinsics, &tags, None) {
            Ok(sol) => {
                tracing::info!(rms_px = sol.rms_px, corners = sol.corners, "camera posed from background tags");
                if let Some(why) = self.one_tag_ambiguity(&tags, &sol) {
                    tracing::warn!(
                        "first pose rests on one tag whose mirror pose fits as well ({why}); taken (nothing to check it against)"
                    );
                    status.message = Some(format!("first pose from one ambiguous tag: {why}"));
                }
                // `fix` is kept: identity at start, the last correction after a failed re-pose.
                self.raw = Some(sol.pose);
                self.covariance = Some(sol.covariance);
                self.hold();
                self.averaged_updates = 1;
                self.average_limit = self.options.average_updates_initial.max(1);
                self.accumulate(&tags, &sol.rejected_tags);
                status.pose = self.pose();
                status.covariance = Some(sol.covariance);
                status.first_pose = true;
                status.rms_px = Some(sol.rms_px);
                status.rejected_tags = sol.rejected_tags;
                status.drift = self.drift();
            }
            Err(e) => {
                tracing::warn!(error = %e, "camera could not be posed from background tags");
                status.message = Some(format!("could not be posed: {e}"));
            }
        }
        status
    }

    /// Distance (px) of an observed corner from its running mean moved by the drift
    /// (`held` → `now`; when averaged over ≥ 3 updates) or else from `now`'s projection.
    fn corner_shift(&self, held: &Pose, now: &Pose, tag: &BackgroundTagObservation, k: usize) -> f64 {
        let px = tag.pixels[k];
        match self.corners.get(&(tag.id, k)) {
            Some(c) if c.n >= 3.0 && (c.world - tag.world[k]).norm() < 1e-9 => {
                (Vector2::new(px.x, px.y) - c.mean - self.drift_motion(held, now, &tag.world[k])).norm()
            }
            _ => self.intrinsics.project(&now.transform(&tag.world[k])).map_or(f64::INFINITY, |p| (p - px).norm()),
        }
    }

    /// Image motion (px) of a world point between poses `held` and `now` (zero when equal).
    fn drift_motion(&self, held: &Pose, now: &Pose, world: &Vector3<f64>) -> Vector2<f64> {
        if held == now {
            return Vector2::zeros();
        }
        match (self.intrinsics.project(&now.transform(world)), self.intrinsics.project(&held.transform(world))) {
            (Some(a), Some(b)) => a - b,
            _ => Vector2::zeros(),
        }
    }

    /// Solves this update's pose from its own corners (warm-started at the predicted
    /// pose) and feeds it to the drift filter.
    fn measure_drift(&mut self, tags: &[BackgroundTagObservation], skip: &[u32], predicted: &Pose) {
        let (Some(t), Some(_)) = (self.now_ns, self.drift.as_ref()) else { return };
        let used: Vec<BackgroundTagObservation> = tags.iter().filter(|t| !skip.contains(&t.id)).copied().collect();
        if used.len() * 4 < self.options.min_corners.max(4) {
            return;
        }
        match solve_camera_pose(&self.intrinsics, &used, Some(predicted)) {
            Ok(sol) => {
                if let Some(f) = self.drift.as_mut() {
                    if let Some(m2) = f.update(t, &sol.pose, &sol.covariance) {
                        tracing::trace!(m2, "drift filter updated");
                    }
                }
            }
            Err(e) => tracing::debug!(error = %e, "drift measurement failed; drift predicted only"),
        }
    }

    fn rms(&self, pose: &Pose, tags: &[BackgroundTagObservation]) -> Option<f64> {
        let mut s = 0.0;
        let mut n = 0;
        for t in tags {
            for k in 0..4 {
                let p = self.intrinsics.project(&pose.transform(&t.world[k]))?;
                s += (p - t.pixels[k]).norm_squared();
                n += 2;
            }
        }
        (n > 0).then(|| (s / n as f64).sqrt())
    }

    fn accumulate(&mut self, tags: &[BackgroundTagObservation], skip: &[u32]) {
        self.period_updates += 1;
        // De-drifted: each corner as it would be seen from the held pose.
        let (held, now) = match (self.raw, self.current_raw()) {
            (Some(h), Some(n)) => (h, n),
            _ => (Pose::identity(), Pose::identity()),
        };
        for t in tags.iter().filter(|t| !skip.contains(&t.id)) {
            for k in 0..4 {
                let px = Vector2::new(t.pixels[k].x, t.pixels[k].y) - self.drift_motion(&held, &now, &t.world[k]);
                let c = self.corners.entry((t.id, k)).or_insert(CornerStats { world: t.world[k], n: 0.0, mean: px, m2: 0.0 });
                c.world = t.world[k];
                c.n += 1.0;
                let d = px - c.mean;
                c.mean += d / c.n;
                c.m2 += d.dot(&(px - c.mean));
            }
        }
    }

    fn archive_noise(&mut self) {
        for c in self.corners.values() {
            self.archived_m2 += c.m2;
            self.archived_dof += (c.n - 1.0).max(0.0);
        }
    }

    fn averaged_observations(&self) -> Vec<BackgroundTagObservation> {
        let mut ids: Vec<u32> = self.corners.keys().map(|(id, _)| *id).collect();
        ids.sort_unstable();
        ids.dedup();
        ids.into_iter()
            .filter_map(|id| {
                let c: Vec<&CornerStats> = (0..4).map(|k| self.corners.get(&(id, k))).collect::<Option<_>>()?;
                Some(BackgroundTagObservation {
                    id,
                    pixels: [0, 1, 2, 3].map(|k| Point2::new(c[k].mean.x, c[k].mean.y)),
                    world: [0, 1, 2, 3].map(|k| c[k].world),
                })
            })
            .collect()
    }
}

/// Finite pixels and world corners.
fn valid_observation(t: &BackgroundTagObservation) -> bool {
    t.pixels.iter().all(|p| p.x.is_finite() && p.y.is_finite()) && t.world.iter().all(|w| w.iter().all(|v| v.is_finite()))
}

/// Why the re-pose of a camera that moved failed its checks (the module docs).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
enum RefusedRepose {
    /// The corners gave no pose.
    #[error("no pose: {0}")]
    NoPose(crate::SolveError),
    /// The re-pose misfits its own corners.
    #[error("re-pose misfits its corners: RMS {rms_px:.2} px > {limit_px:.2} px")]
    Misfit {
        /// The re-pose's RMS reprojection error, px.
        rms_px: f64,
        /// The most it may be, px.
        limit_px: f64,
    },
    /// A one-tag pose whose corners do not decide between its two minima, neither of them
    /// the held pose's (the two fits described).
    #[error("one-tag pose is ambiguous ({0}) and neither minimum is the held pose's")]
    Ambiguous(String),
}

#[cfg(test)]
mod tests {
    use super::*;

    fn setup() -> (CameraIntrinsics, Pose, Vec<[Vector3<f64>; 4]>) {
        let intr =
            CameraIntrinsics { width: 1280, height: 960, fx: 1400.0, fy: 1400.0, cx: 639.5, cy: 479.5, dist: [-0.2, 0.05, 0.0, 0.0, 0.0] };
        let pose = Pose::from_rvec_tvec([0.05, -0.1, 0.02], [0.0, 0.0, 2000.0]);
        let tags = [(-400.0, -250.0, 0.0), (400.0, -250.0, 0.0), (0.0, 250.0, 150.0)]
            .iter()
            .map(|&(x, y, z)| {
                let c = Vector3::new(x, y, z);
                [
                    c + Vector3::new(-100.0, -100.0, 0.0),
                    c + Vector3::new(100.0, -100.0, 0.0),
                    c + Vector3::new(100.0, 100.0, 0.0),
                    c + Vector3::new(-100.0, 100.0, 0.0),
                ]
            })
            .collect();
        (intr, pose, tags)
    }

    /// Observations with a deterministic ±`d` px jitter pattern that flips every update.
    fn observe(intr: &CameraIntrinsics, pose: &Pose, tags: &[[Vector3<f64>; 4]], d: f64, step: usize) -> Vec<BackgroundTagObservation> {
        let sign = if step.is_multiple_of(2) { 1.0 } else { -1.0 };
        tags.iter()
            .enumerate()
            .map(|(i, w)| BackgroundTagObservation {
                id: i as u32,
                pixels: [0, 1, 2, 3].map(|k| {
                    let p = intr.project(&pose.transform(&w[k])).unwrap();
                    let s = if (i + k) % 2 == 0 { sign } else { -sign };
                    Point2::new(p.x + s * d, p.y - s * d)
                }),
                world: *w,
            })
            .collect()
    }

    #[test]
    fn holds_the_pose_and_measures_the_corner_noise() {
        let (intr, pose, tags) = setup();
        let mut t = HeldCameraPose::new(intr, None);
        let first = t.update(&observe(&intr, &pose, &tags, 0.2, 0));
        assert!(first.first_pose && !first.bumped);
        for step in 1..40 {
            let st = t.update(&observe(&intr, &pose, &tags, 0.2, step));
            assert!(!st.bumped && st.pose == first.pose, "held while static (update {step})");
        }
        // Each corner alternates ±0.2 px per axis around its mean: per-axis scatter 0.2 px.
        let noise = t.noise_px().expect("measured");
        assert!((noise - 0.2).abs() < 0.01, "noise {noise}");
        assert!((t.bump_threshold_px() - 1.2).abs() < 0.06, "6 × noise above the 1 px floor");
    }

    #[test]
    fn one_moved_tag_is_not_a_bump() {
        let (intr, pose, tags) = setup();
        let mut t = HeldCameraPose::new(intr, None);
        for step in 0..5 {
            t.update(&observe(&intr, &pose, &tags, 0.05, step));
        }
        let mut obs = observe(&intr, &pose, &tags, 0.05, 5);
        for p in obs[0].pixels.iter_mut() {
            p.x += 5.0;
        }
        let st = t.update(&obs);
        assert!(!st.bumped, "the median ignores one displaced tag");
        assert_eq!(st.rejected_tags, vec![0], "and that tag is kept out of the running means");
    }

    /// One tag of 200 mm seen nearly frontally from 2 m (~140 px): its corners hardly
    /// decide between the pose and its mirror.
    fn far_tag() -> [Vector3<f64>; 4] {
        let c = Vector3::new(0.0, 250.0, 150.0);
        [(-100.0, -100.0), (100.0, -100.0), (100.0, 100.0), (-100.0, 100.0)].map(|(x, y)| c + Vector3::new(x, y, 0.0))
    }

    /// Turns `pose`'s camera by `deg` about an oblique axis through its centre.
    fn turned(pose: &Pose, deg: f64) -> Pose {
        let axis = nalgebra::Unit::new_normalize(Vector3::new(0.3, 1.0, 0.2));
        let rot = nalgebra::Rotation3::from_axis_angle(&axis, deg.to_radians()) * pose.rotation;
        Pose { rotation: rot, translation: -(rot * pose.centre()) }
    }

    #[test]
    fn an_ambiguous_one_tag_re_pose_is_refused_and_the_held_pose_kept() {
        let (intr, pose, tags) = setup();
        let mut t = HeldCameraPose::new(intr, None);
        for step in 0..12 {
            let st = t.update(&observe(&intr, &pose, &tags, 0.1, step));
            assert!(st.pose.is_some() && st.refused.is_none());
        }
        let held = t.pose().expect("posed");
        // The camera turns by 6° and only one tag stays in view.
        let moved = turned(&pose, 6.0);
        let one = [far_tag()];
        let obs = observe(&intr, &moved, &one, 0.1, 0);
        // The scenario is what it says: two minima, the mirror fitting within the noise and
        // far from the truth (taking it would be wrong by degrees).
        let minima = single_tag_minima(&intr, &obs[0]);
        assert_eq!(minima.len(), 2, "{minima:?}");
        let (truth_near, mirror_far) = (
            minima.iter().map(|m| m.0.angle_to(&moved)).fold(f64::MAX, f64::min),
            minima.iter().map(|m| m.0.angle_to(&moved)).fold(0.0, f64::max),
        );
        println!(
            "minima RMS {:.3} / {:.3} px; nearest {:.3}°, other {:.1}° from the truth",
            minima[0].1,
            minima[1].1,
            truth_near.to_degrees(),
            mirror_far.to_degrees()
        );
        assert!(minima[1].1 < AMBIGUITY_FLOOR_PX && mirror_far.to_degrees() > 5.0, "ambiguous scenario");
        let st = t.update(&obs);
        assert!(st.bumped, "the move is caught");
        assert!(st.pose.is_none() && t.pose().is_none(), "the ambiguous pose replaces nothing and the held one is not used");
        assert!(st.refused.as_deref().is_some_and(|m| m.contains("ambiguous")), "{:?}", st.refused);
        // Still one ambiguous tag: still refused.
        let st = t.update(&observe(&intr, &moved, &one, 0.1, 1));
        assert!(st.pose.is_none() && st.refused.is_some());
        // Back where it was held: posed again with the held pose, unchanged.
        let st = t.update(&observe(&intr, &pose, &tags, 0.1, 2));
        assert!(!st.bumped && st.refused.is_none(), "{st:?}");
        assert_eq!(st.pose, Some(held));
    }

    #[test]
    fn a_one_tag_re_pose_is_taken_when_decided_by_its_corners_or_by_the_held_pose() {
        let (intr, pose, tags) = setup();
        // A small bump (0.4°) seen by one ambiguous tag: the minimum next to the held pose.
        let mut t = HeldCameraPose::new(intr, None);
        for step in 0..12 {
            t.update(&observe(&intr, &pose, &tags, 0.1, step));
        }
        let bumped = turned(&pose, 0.4);
        let st = t.update(&observe(&intr, &bumped, &[far_tag()], 0.1, 0));
        assert!(st.bumped && st.refused.is_none(), "{st:?}");
        let got = st.pose.expect("re-posed");
        // The minimum next to the truth (one noisy tag: ~0.3°), not its mirror (~17° away).
        assert!(got.angle_to(&bumped).to_degrees() < 1.0, "re-posed {:.3}° from the truth", got.angle_to(&bumped).to_degrees());
        // A far move seen by one big, steeply tilted tag: its corners decide.
        let mut t = HeldCameraPose::new(intr, None);
        for step in 0..12 {
            t.update(&observe(&intr, &pose, &tags, 0.1, step));
        }
        let moved = turned(&pose, 6.0);
        let c = Vector3::new(0.0, 0.0, 1000.0);
        let (e1, e2) = (Vector3::new(0.5f64.sqrt(), 0.0, -(0.5f64.sqrt())), Vector3::y());
        let tilted = [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)].map(|(a, b): (f64, f64)| c + e1 * (150.0 * a) + e2 * (150.0 * b));
        let obs = observe(&intr, &moved, &[tilted], 0.1, 0);
        let minima = single_tag_minima(&intr, &obs[0]);
        println!("tilted tag minima {:?}", minima.iter().map(|m| m.1).collect::<Vec<_>>());
        let st = t.update(&obs);
        assert!(st.bumped && st.refused.is_none(), "{st:?}");
        let got = st.pose.expect("re-posed");
        assert!(got.angle_to(&moved).to_degrees() < 1.0, "re-posed {:.3}° from the truth", got.angle_to(&moved).to_degrees());
    }
}
