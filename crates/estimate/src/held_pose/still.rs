//! A static update: the running means grow, the pose is refined from them while averaging,
//! then held (following the drift when tracked) and checked once against the averaged
//! corners (see the module docs, [`super`]).

use super::{HeldCameraPose, HeldPoseStatus, SANITY_CHECK_UPDATES};
use crate::camera_pose::{solve_camera_pose, BackgroundTagObservation};
use crate::lm::median;
use tagdeflect_core::camera::Pose;

impl HeldCameraPose {
    /// A static update against the held pose `pose` (`predicted`: moved by the drift
    /// predicted for now): tags that disagree stay out of the running means; while averaging
    /// the pose is refined from the means, after that the drift is measured and, once, the
    /// held pose is checked against the averaged corners.
    pub(super) fn on_still(
        &mut self,
        tags: &[BackgroundTagObservation],
        pose: Pose,
        predicted: Pose,
        threshold_px: f64,
        mut status: HeldPoseStatus,
    ) -> HeldPoseStatus {
        let rejected = self.disagreeing_tags(tags, &pose, &predicted, threshold_px);
        let averaging = self.averaged_updates < self.average_limit;
        if !averaging {
            self.measure_drift(tags, &rejected, &predicted);
        }
        self.accumulate(tags, &rejected);
        if averaging {
            self.refine_from_means(&pose);
        } else if self.period_updates == SANITY_CHECK_UPDATES {
            self.check_against_means(&pose, threshold_px, &mut status);
        }
        status.pose = self.pose();
        status.covariance = self.covariance;
        status.rms_px = self.raw.and_then(|p| self.rms(&p, tags));
        status.rejected_tags = rejected;
        status.noise_px = self.noise_px();
        status.drift = self.drift();
        status
    }

    /// The tags whose corners disagree with the pose (median shift above the threshold).
    fn disagreeing_tags(&self, tags: &[BackgroundTagObservation], pose: &Pose, predicted: &Pose, threshold_px: f64) -> Vec<u32> {
        let mut rejected = Vec::new();
        for t in tags {
            let d: Vec<f64> = (0..4).map(|k| self.corner_shift(pose, predicted, t, k)).collect();
            if median(&d).unwrap_or(f64::INFINITY) > threshold_px {
                tracing::debug!(tag = t.id, "background tag disagrees with the held pose; left out");
                rejected.push(t.id);
            }
        }
        rejected
    }

    /// While averaging: the pose re-solved from the averaged corners (kept if that fails).
    fn refine_from_means(&mut self, pose: &Pose) {
        self.averaged_updates += 1;
        let averaged = self.averaged_observations();
        match solve_camera_pose(&self.intrinsics, &averaged, Some(pose)) {
            Ok(sol) => {
                self.raw = Some(sol.pose);
                self.covariance = Some(sol.covariance);
                self.hold();
            }
            Err(e) => tracing::debug!(error = %e, "pose refinement from averaged corners failed; pose kept"),
        }
    }

    /// Safety net: a held pose from a poor first frame (blur) that does not fit the
    /// averaged corners is re-fitted to them once.
    fn check_against_means(&mut self, pose: &Pose, threshold_px: f64, status: &mut HeldPoseStatus) {
        let averaged = self.averaged_observations();
        let misfit = self.median_misfit_px(pose, &averaged).unwrap_or(0.0);
        if misfit <= threshold_px {
            return;
        }
        let refit = solve_camera_pose(&self.intrinsics, &averaged, Some(pose)).ok().filter(|sol| {
            // Only when the re-fit really explains the corners better (a calibration error
            // would misfit any pose alike).
            self.median_misfit_px(&sol.pose, &averaged).unwrap_or(f64::INFINITY) < 0.5 * misfit
        });
        if let Some(sol) = refit {
            let msg = format!("held pose misfit the averaged background corners by {misfit:.2} px; re-fitted");
            tracing::warn!("{msg}");
            self.raw = Some(sol.pose);
            self.covariance = Some(sol.covariance);
            // The re-fit is of the held pose's moment (de-drifted means): the drift so far
            // stays, only the held pose's own error is new.
            if let Some(f) = self.drift.as_mut() {
                f.rebase(sol.pose, Some(&sol.covariance));
            }
            status.bumped = true;
            status.message = Some(msg);
        }
    }

    /// Median distance (px) between the corners and `pose`'s projections (infinite for a
    /// corner it cannot project); `None` without corners.
    fn median_misfit_px(&self, pose: &Pose, tags: &[BackgroundTagObservation]) -> Option<f64> {
        let d: Vec<f64> = tags
            .iter()
            .flat_map(|t| (0..4).map(move |k| (t, k)))
            .map(|(t, k)| self.intrinsics.project(&pose.transform(&t.world[k])).map_or(f64::INFINITY, |p| (p - t.pixels[k]).norm()))
            .collect();
        median(&d)
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
}
