//! Stage 2, pose cameras: each camera's held pose updated from its background tags, a
//! camera that moved, or whose first pose is still undecided, searched whole first.
//!
//! **The first-pose search** (why and its budget): a camera's first pose passes the checks
//! of `held_pose` (several tags that all fit it, or one tag whose corners decide), else
//! nothing is measured from the camera. Full-frame mode searches every frame whole at the
//! configured resolution, so it sees every background tag that could decide; tracking mode
//! starts from a decimated search and then follows what it found. So that both modes give
//! the same answer, a frame whose background tags do not give a first pose that passes is
//! searched whole at the configured resolution in the frame set before the camera is posed
//! from it — within a budget: at most one camera's first-pose search per frame set (the
//! cameras take turns, starting at the set's number), and only during the first
//! [`FIRST_POSE_SEARCH_WINDOW_NS`] of frame time of the run (a live run's start-up, where a
//! lost set is allowed). After that an undecided camera costs no frame set: the detector's
//! periodic sweep (the whole frame once per `full_search_interval_s`) looks for the tag that
//! decides, beside the measurement. A camera not posed yet whose frame lost tags it followed
//! (it moved before its first pose) is searched whole when its followed tags do decide the
//! first pose, so that pose and the tags measured in that set are what full-frame mode sees
//! (once per camera: it is posed then; within the one-camera-per-set budget, at any time).
//! A posed camera that loses background tags keeps its held pose and costs no search either
//! (see [`search_whole`]).

use std::collections::HashMap;
use std::time::Instant;

use nalgebra::Vector3;
use tagdeflect_core::feed::{round_mm, CameraHealth};
use tagdeflect_core::frame::FrameSet;
use tagdeflect_detect::plan::BackgroundCheck;
use tagdeflect_detect::{CameraDetections, DetectReport};

use super::detect::Detected;
use super::Measurement;
use crate::{BackgroundTagObservation, HeldCameraPose, HeldPoseStatus};

/// What the pose stage made of the cameras: each camera's health for the feed line, in
/// config order (the poses themselves are held by the cameras).
pub(super) struct CameraPoses {
    /// Per camera, in config order.
    pub(super) health: Vec<CameraHealth>,
}

impl Measurement {
    /// Poses every camera from its detections; a camera that moved has its frame searched
    /// whole first, and `detected` then holds what that search found.
    pub(super) fn pose_cameras(&mut self, set: &FrameSet, detected: &mut Detected) -> CameraPoses {
        let n = self.cameras.len();
        let t0 = *self.first_set_t_ns.get_or_insert(set.t_ns);
        // One first-pose search per set, the cameras taking turns (see the module docs).
        let mut budget = FirstPoseBudget { searches: 1, undecided: set.t_ns.saturating_sub(t0) < FIRST_POSE_SEARCH_WINDOW_NS };
        let mut health: Vec<Option<CameraHealth>> = vec![None; n];
        for k in 0..n {
            let ci = (set.seq as usize + k) % n;
            health[ci] = Some(self.pose_camera(set, ci, detected, &mut budget));
        }
        CameraPoses { health: health.into_iter().flatten().collect() }
    }

    /// Camera `ci`'s pose from this set, and its health (`first_pose_budget`: first-pose
    /// searches left in this set).
    fn pose_camera(&mut self, set: &FrameSet, ci: usize, detected: &mut Detected, first_pose_budget: &mut FirstPoseBudget) -> CameraHealth {
        // The frame's observations are made once and posed from, unless a search replaced them.
        let frame_obs = self.search_if_moved(set, ci, detected, first_pose_budget);
        let det = detected.of(ci);
        let mut h = CameraHealth {
            name: self.cameras[ci].name.clone(),
            frame: det.is_some(),
            background_tags: 0,
            specimen_tags: 0,
            pose_reproj_px: None,
            posed: self.cameras[ci].pose.pose().is_some(),
            ..CameraHealth::default()
        };
        let checked = det.is_some_and(|d| self.update_pose(set, ci, d, frame_obs, &mut h));
        // A held pose that no background tag confirmed in this set is reported as stale.
        self.pose_age_sets[ci] = if checked { 0 } else { self.pose_age_sets[ci] + 1 };
        if h.posed && h.frame && !checked {
            (h.stale_pose, h.pose_age_sets) = (true, Some(self.pose_age_sets[ci]));
        }
        h
    }

    /// The camera moved (background tags mostly lost or jumped): the same frame searched whole
    /// before the camera is posed from it. The frame's background observations when they
    /// are still what the camera is posed from, `None` when a search replaced them (or the
    /// camera has no frame).
    fn search_if_moved(
        &mut self,
        set: &FrameSet,
        ci: usize,
        detected: &mut Detected,
        first_pose_budget: &mut FirstPoseBudget,
    ) -> Option<Vec<BackgroundTagObservation>> {
        let report = detected.reports[ci]?;
        let slot = detected.cameras.iter_mut().find(|(i, _)| *i == ci)?;
        let cam = &mut self.cameras[ci];
        let threshold = cam.pose.bump_threshold_px();
        let above = |s: f64| s.is_nan() || s > threshold;
        let obs = background_observations(&self.background_world, &slot.1);
        let first = first_pose_budget.searches > 0 && first_pose_search(&cam.pose, &report, &obs, first_pose_budget.undecided);
        let jumped = cam.pose.preview_shift_px(set.t_ns, &obs).is_some_and(above);
        let moved_again = report.background.shift_px.is_some_and(above);
        let search = first || search_whole(&cam.pose, &report, jumped, moved_again);
        let Some(frame) = set.frames.iter().find(|f| f.camera == ci).filter(|_| search) else { return Some(obs) };
        let c0 = Instant::now();
        let (again, r) = cam.detector.search_again(frame.t_ns, &frame.image, &self.rig);
        if first {
            first_pose_budget.searches -= 1;
            self.stats.first_pose_searches += 1;
            tracing::info!(
                camera = %cam.name,
                seq = set.seq,
                background_tags = again.background.len(),
                "first pose undecided by the background tags followed: the frame searched whole for one that decides"
            );
        } else {
            self.stats.moved_camera_searches += 1;
            tracing::warn!(
                camera = %cam.name,
                seq = set.seq,
                lost = report.background.lost,
                jumped,
                background_tags = again.background.len(),
                "background tags mostly lost or jumped: the frame searched whole before posing"
            );
        }
        self.stats.full_frame_searches += r.full_frame_searches;
        detected.parts.full_frame += c0.elapsed().as_secs_f64();
        slot.1 = again;
        None
    }

    /// Updates camera `ci`'s held pose from its detections `d` (`obs`: their background
    /// observations when already made) and fills its health; true when a background tag
    /// checked the pose in this set.
    fn update_pose(
        &mut self,
        set: &FrameSet,
        ci: usize,
        d: &CameraDetections,
        obs: Option<Vec<BackgroundTagObservation>>,
        h: &mut CameraHealth,
    ) -> bool {
        h.background_tags = d.background.len();
        h.specimen_tags = d.specimen.len();
        let obs = obs.unwrap_or_else(|| background_observations(&self.background_world, d));
        let cam = &mut self.cameras[ci];
        // Every line the held pose logs names its camera (the span's field).
        let status = tracing::info_span!("pose", camera = %cam.name).in_scope(|| cam.pose.update_at(set.t_ns, &obs));
        if let Some(d) = status.drift {
            h.drift_deg = Some((d.angle_deg() * 1e6).round() / 1e6);
            h.drift_mm = Some(round_mm(d.shift_mm()));
        }
        h.posed = status.pose.is_some();
        h.pose_reproj_px = status.rms_px;
        h.bumped = status.bumped;
        self.note_pose_change(ci, set.seq, &status);
        status.fixed || !status.stale
    }

    /// Counts and logs a camera's re-pose or refused pose; either starts a new pose epoch.
    fn note_pose_change(&mut self, ci: usize, seq: u64, status: &HeldPoseStatus) {
        if status.refused.is_some() || status.bumped {
            self.pose_epochs[ci] += 1;
        }
        let camera = &self.cameras[ci].name;
        if let Some(why) = &status.refused {
            self.stats.refused_poses += 1;
            if self.cameras[ci].pose.ever_posed() {
                tracing::warn!(camera = %camera, seq, reason = %why, "camera moved and its pose failed the checks: the frame set is solved without it");
            } else {
                tracing::debug!(camera = %camera, seq, reason = %why, "camera not posed yet: its first pose failed the checks");
            }
        } else if status.bumped {
            self.stats.bumps += 1;
            tracing::warn!(camera = %camera, seq, "camera moved: background tags shifted in the image; re-posed");
        }
    }
}

/// Frame time from the run's first frame set during which an undecided first pose is
/// searched for in the frame set (see the module docs): the first second, a live run's
/// start-up.
pub const FIRST_POSE_SEARCH_WINDOW_NS: i64 = 1_000_000_000;

/// The first-pose searches a frame set allows: how many are left, and whether a camera whose
/// followed tags give no first pose may still be searched (the run's first second).
struct FirstPoseBudget {
    /// Searches left in this set.
    searches: u32,
    /// Undecided first poses are searched for (the run's first second).
    undecided: bool,
}

/// Whether a camera never posed has its frame searched whole before its first pose: an
/// estimated pose, no search of the whole frame at the configured resolution in the frame
/// yet, and either the tags followed give no first pose that passes (while `undecided`
/// searches are allowed) or they give one but tags the camera followed were lost in the frame
/// — it moved before it was posed, and its first pose and the tags measured in that set are
/// taken from what a whole-frame search sees, as in full-frame mode (once per camera: it is
/// posed then).
fn first_pose_search(pose: &HeldCameraPose, report: &DetectReport, obs: &[BackgroundTagObservation], undecided: bool) -> bool {
    if !pose.estimated() || pose.ever_posed() || report.searched_whole {
        return false;
    }
    match pose.first_pose_check(obs) {
        Err(_) => undecided,
        Ok(_) => report.background.followed_lost > 0,
    }
}

/// Background tags a camera keeps its held pose on when others are lost: fewer left (or
/// fewer left than lost) and the loss may be the camera's own move.
const MIN_BACKGROUND_TAGS_LEFT: usize = 2;

/// Whether a camera's frame is searched whole before the camera is posed from it: an
/// estimated pose (held or refused), no full-frame search in the frame yet, and its
/// background tags jumped (while a re-pose is refused, only when they moved again) or
/// mostly lost. A background tag lost while the others stay where they were (occluded,
/// blurred, a person walking past) costs no search in the frame: the camera keeps its held
/// pose, checked by the tags left, and the planner's sweeps and background searches look
/// for the missing tag (see [`tagdeflect_detect::CameraDetector`]).
fn search_whole(pose: &HeldCameraPose, report: &DetectReport, jumped: bool, moved_again: bool) -> bool {
    pose.estimated()
        && (pose.pose().is_some() || pose.refused().is_some())
        && report.full_frame_searches == 0
        && (mostly_lost(&report.background) || (jumped && (pose.refused().is_none() || moved_again)))
}

/// A background tag was lost in the frame and too few are left to tell a lost tag from a
/// moved camera: fewer than [`MIN_BACKGROUND_TAGS_LEFT`], or fewer seen than missing.
fn mostly_lost(check: &BackgroundCheck) -> bool {
    check.lost && (check.seen < MIN_BACKGROUND_TAGS_LEFT || check.seen < check.missing)
}

/// The background tags of one camera's detections with their known world corners. An id
/// detected more than once in the frame is left out (the layout has it once: at most one of
/// them is the tag, and nothing tells which), whichever way the frame was searched.
fn background_observations(world: &HashMap<u32, [Vector3<f64>; 4]>, d: &CameraDetections) -> Vec<BackgroundTagObservation> {
    let once = |id: u32| d.background.iter().filter(|x| x.id == id).count() == 1;
    d.background
        .iter()
        .filter(|det| once(det.id))
        .filter_map(|det| world.get(&det.id).map(|w| BackgroundTagObservation { id: det.id, pixels: det.corners, world: *w }))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn check(lost: bool, seen: usize, missing: usize) -> BackgroundCheck {
        BackgroundCheck { lost, seen, missing, shift_px: None, followed_lost: usize::from(lost) }
    }

    #[test]
    fn one_tag_lost_among_several_is_no_move() {
        assert!(!mostly_lost(&check(true, 3, 1)));
        assert!(!mostly_lost(&check(true, 2, 2)));
        assert!(!mostly_lost(&check(false, 0, 4)), "a tag already missing is not lost again");
    }

    #[test]
    fn most_or_all_tags_lost_is_searched() {
        assert!(mostly_lost(&check(true, 0, 4)));
        assert!(mostly_lost(&check(true, 1, 1)), "one tag left cannot tell a lost tag from a moved camera");
        assert!(mostly_lost(&check(true, 2, 3)));
    }
}
