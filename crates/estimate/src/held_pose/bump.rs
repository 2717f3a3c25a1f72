//! A camera that moved: a re-pose from this update's corners, accepted only when it passes
//! the checks of the module docs ([`super`]), else the camera is refused (unposed).

use super::{HeldCameraPose, HeldPoseStatus, AMBIGUITY_FLOOR_PX, AMBIGUITY_RATIO, HELD_CONSISTENT_DEG, REPOSE_MAX_RMS_PX};
use crate::camera_pose::{single_tag_minima, solve_camera_pose, BackgroundTagObservation, CameraPoseSolution};
use tagdeflect_core::camera::Pose;

impl HeldCameraPose {
    /// The update in which the camera was seen to move (held pose `pose`): re-posed, or
    /// refused with the reason.
    pub(super) fn on_bump(&mut self, tags: &[BackgroundTagObservation], pose: Pose, mut status: HeldPoseStatus) -> HeldPoseStatus {
        status.bumped = true;
        match self.checked_repose(tags, &pose) {
            Ok(sol) => self.take_repose(tags, pose, sol, status),
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
        }
    }

    /// The checked re-pose `sol` replaces the held pose `pose`.
    fn take_repose(
        &mut self,
        tags: &[BackgroundTagObservation],
        pose: Pose,
        sol: CameraPoseSolution,
        mut status: HeldPoseStatus,
    ) -> HeldPoseStatus {
        // Keep the reported pose continuous: the camera's motion is measured between the
        // averaged corners before the bump and those after it, so the held pose's own error
        // carries over instead of a new single-frame error replacing it.
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
        self.accumulate(tags, &sol.rejected_tags);
        status.pose = self.pose();
        status.covariance = Some(sol.covariance);
        status.rms_px = Some(sol.rms_px);
        status.rejected_tags = sol.rejected_tags;
        status.refused = None;
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
    pub(super) fn one_tag_ambiguity(&self, tags: &[BackgroundTagObservation], sol: &CameraPoseSolution) -> Option<String> {
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
