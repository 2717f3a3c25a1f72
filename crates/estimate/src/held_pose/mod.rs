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
//! refused, so no position is measured from a pose that failed its checks.
//!
//! The first posing has no held pose to decide a one-tag pose by, so it passes the same
//! checks without it ([`HeldCameraPose::first_pose_check`]): a pose from several tags must
//! fit every one of them (each tag's RMS ≤ [`REPOSE_MAX_RMS_PX`]: a spurious detection — a
//! misread id, a tag printed twice — fits no pose together with the real ones, and a tag
//! the outlier test drops leaves a one-tag pose); a pose resting on one tag must be decided
//! by its corners. Otherwise the camera stays unposed ([`HeldPoseStatus::refused`], no
//! pose, nothing measured from it) until an update brings a tag that decides — the same
//! rule whether the frame was tracked or searched whole, so both modes publish the same
//! positions. The measurement searches a camera's frame whole for such a tag while the
//! first pose is undecided (see `measure::pose`).
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

mod bump;
mod corners;
mod options;
mod still;

use std::collections::HashMap;

use nalgebra::Matrix6;

use crate::camera_pose::{solve_camera_pose, BackgroundTagObservation, CameraPoseSolution};
use crate::drift::{DriftEstimate, DriftFilter};
use crate::lm::median;
use corners::CornerStats;
use options::SANITY_CHECK_UPDATES;
pub use options::{HeldPoseOptions, HeldPoseStatus, AMBIGUITY_FLOOR_PX, AMBIGUITY_RATIO, HELD_CONSISTENT_DEG, REPOSE_MAX_RMS_PX};
use tagdeflect_core::camera::{CameraIntrinsics, Pose};

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
        let threshold = self.bump_threshold_px();
        let mut status = self.status_before(tags.len() * 4, threshold);
        if self.fixed {
            status.rms_px = self.raw.and_then(|p| self.rms(&p, &tags));
            return status;
        }
        if status.corners < self.options.min_corners.max(4) {
            let msg =
                format!("{} background corners seen, {} needed: pose kept from before", status.corners, self.options.min_corners.max(4));
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
                corners = status.corners,
                "camera bumped: background tags moved in the image; re-posing"
            );
            return self.on_bump(&tags, pose, status);
        }
        if let Some(why) = self.refused.take() {
            tracing::info!(shift_px = shift, "camera back at its held pose: posed again");
            status.message = Some(format!("back at the held pose (was refused: {why})"));
            status.refused = None;
        }
        self.on_still(&tags, pose, predicted, threshold, status)
    }

    /// An update's status before it is looked at: the pose and figures as they stand.
    fn status_before(&self, corners: usize, threshold_px: f64) -> HeldPoseStatus {
        HeldPoseStatus {
            pose: self.pose(),
            covariance: self.covariance,
            bumped: false,
            stale: false,
            fixed: self.fixed,
            first_pose: false,
            rms_px: None,
            shift_px: None,
            bump_threshold_px: threshold_px,
            corners,
            rejected_tags: Vec::new(),
            noise_px: self.noise_px(),
            message: None,
            refused: self.refused.clone(),
            drift: self.drift(),
        }
    }

    fn first_posing(&mut self, tags: Vec<BackgroundTagObservation>, mut status: HeldPoseStatus) -> HeldPoseStatus {
        let sol = match self.first_pose_check(&tags) {
            Ok(sol) => sol,
            Err(why) => {
                tracing::debug!(reason = %why, "first pose refused: waiting for a background tag that decides");
                status.message = Some(format!("first pose refused: {why}"));
                status.refused = Some(why.to_string());
                return status;
            }
        };
        tracing::info!(rms_px = sol.rms_px, corners = sol.corners, "camera posed from background tags");
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
        status.refused = None;
        status.drift = self.drift();
        status
    }

    /// The first pose these background tags give when it passes the checks of the module
    /// docs (every tag used fits it; one tag alone decides by its corners), or why not. Changes
    /// nothing: the measurement also asks it before posing, to know whether to search the
    /// frame whole for a tag that decides.
    pub fn first_pose_check(&self, tags: &[BackgroundTagObservation]) -> Result<CameraPoseSolution, FirstPoseRefused> {
        let tags: Vec<BackgroundTagObservation> = tags.iter().filter(|t| valid_observation(t)).copied().collect();
        if tags.len() * 4 < self.options.min_corners.max(4) {
            return Err(FirstPoseRefused::TooFewTags { corners: tags.len() * 4 });
        }
        let sol = solve_camera_pose(&self.intrinsics, &tags, None).map_err(FirstPoseRefused::NoPose)?;
        if let Some(&(id, rms_px)) = sol.tag_rms_px.iter().find(|(_, rms)| !(*rms <= REPOSE_MAX_RMS_PX)) {
            return Err(FirstPoseRefused::Misfit { id, rms_px });
        }
        if let Some(why) = self.one_tag_ambiguity(&tags, &sol) {
            return Err(FirstPoseRefused::Ambiguous(why));
        }
        Ok(sol)
    }

    /// True once the camera has had a pose (configured, or a first pose that passed).
    pub fn ever_posed(&self) -> bool {
        self.raw.is_some()
    }
}

/// Why a camera's first pose was refused (see the module docs).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FirstPoseRefused {
    /// Fewer background corners than the pose needs.
    #[error("{corners} background corners seen")]
    TooFewTags {
        /// Corners seen.
        corners: usize,
    },
    /// The corners gave no pose.
    #[error("no pose: {0}")]
    NoPose(crate::SolveError),
    /// A tag the pose rests on does not fit it (a spurious detection or a moved tag).
    #[error("background tag {id} misfits the pose from the tags seen: RMS {rms_px:.2} px > {REPOSE_MAX_RMS_PX} px")]
    Misfit {
        /// The tag.
        id: u32,
        /// Its reprojection RMS against the pose, px.
        rms_px: f64,
    },
    /// One tag whose corners do not decide between its two minima (the fits described).
    #[error("one-tag pose is ambiguous ({0}); waiting for a background tag that decides")]
    Ambiguous(String),
}

/// Finite pixels and world corners.
fn valid_observation(t: &BackgroundTagObservation) -> bool {
    t.pixels.iter().all(|p| p.x.is_finite() && p.y.is_finite()) && t.world.iter().all(|w| w.iter().all(|v| v.is_finite()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera_pose::single_tag_minima;
    use nalgebra::{Point2, Vector3};

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
    fn an_ambiguous_one_tag_first_pose_is_refused_until_a_tag_decides() {
        let (intr, pose, tags) = setup();
        let mut t = HeldCameraPose::new(intr, None);
        let one = observe(&intr, &pose, &[far_tag()], 0.1, 0);
        let minima = single_tag_minima(&intr, &one[0]);
        assert!(minima.len() == 2 && minima[1].1 < AMBIGUITY_FLOOR_PX, "ambiguous scenario: {minima:?}");
        for step in 0..3 {
            let st = t.update(&observe(&intr, &pose, &[far_tag()], 0.1, step));
            assert!(st.pose.is_none() && t.pose().is_none() && !t.ever_posed(), "an ambiguous first pose is never published");
            assert!(st.refused.as_deref().is_some_and(|m| m.contains("ambiguous")), "{:?}", st.refused);
        }
        // A second tag decides: posed, near the truth, nothing refused.
        let st = t.update(&observe(&intr, &pose, &tags[..2], 0.1, 3));
        assert!(st.first_pose && st.refused.is_none(), "{st:?}");
        let got = st.pose.expect("posed from two tags");
        assert!(got.angle_to(&pose).to_degrees() < 0.2, "{:.3}°", got.angle_to(&pose).to_degrees());
    }

    #[test]
    fn a_spurious_second_tag_does_not_decide_a_first_pose() {
        let (intr, pose, tags) = setup();
        let mut t = HeldCameraPose::new(intr, None);
        // The far tag seen where it is, and a misread "tag 1" at a place the layout does
        // not put it (a misdecoded patch of the scene).
        let mut obs = observe(&intr, &pose, &[far_tag(), tags[1]], 0.1, 0);
        for p in obs[1].pixels.iter_mut() {
            p.x -= 230.0;
            p.y += 140.0;
        }
        let why = t.first_pose_check(&obs).expect_err("a spurious tag decides nothing");
        println!("refused: {why}");
        let st = t.update(&obs);
        assert!(st.pose.is_none() && st.refused.is_some() && !t.ever_posed(), "{st:?}");
        // The real second tag where the layout puts it decides.
        let st = t.update(&observe(&intr, &pose, &[far_tag(), tags[1]], 0.1, 1));
        let got = st.pose.expect("posed");
        assert!(got.angle_to(&pose).to_degrees() < 0.2, "{:.3}°", got.angle_to(&pose).to_degrees());
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
