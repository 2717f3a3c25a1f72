//! One camera of the rig as the measurement runs it: its held pose and its detection.

use nalgebra::Point2;
use tagdeflect_core::camera::{CameraIntrinsics, Pose};
use tagdeflect_core::camera_config::CameraConfig;
use tagdeflect_detect::CameraDetector;

use crate::measure_config::MeasureConfig;
use crate::{DriftConfig, HeldCameraPose, HeldPoseOptions, TagView};

/// One camera of the rig as the measurement runs it.
pub(super) struct RigCamera {
    /// The camera's name (`[[camera]] name`).
    pub(super) name: String,
    /// Its intrinsics.
    pub(super) intrinsics: CameraIntrinsics,
    /// The camera's pose, held while static, re-posed after a bump.
    pub(super) pose: HeldCameraPose,
    /// The camera's detection (plan, confirmation, searches, per-tag state).
    pub(super) detector: CameraDetector,
}

impl RigCamera {
    /// The camera `cam` of the rig, the `phase`-th (its periodic full-frame searches are
    /// staggered by it); `roi_tracking = false` forces full-frame detection.
    pub(super) fn new(cam: &CameraConfig, measure: &MeasureConfig, roi_tracking: bool, phase: u32) -> RigCamera {
        let intrinsics = cam.intrinsics();
        let fixed = cam.rvec.zip(cam.tvec_mm).map(|(r, t)| Pose::from_rvec_tvec(r, t));
        let options = HeldPoseOptions { drift: DriftConfig::from_measure(measure), ..Default::default() };
        RigCamera {
            name: cam.name.clone(),
            intrinsics,
            pose: HeldCameraPose::with_options(intrinsics, fixed, options),
            detector: CameraDetector::new(intrinsics, roi_tracking && measure.roi_tracking, measure.full_search_interval_s, phase),
        }
    }

    /// A specimen tag's view from this camera at its current pose, its corners' σ widened by
    /// the camera's edge fits' model error; `None` while unposed.
    pub(super) fn view(&self, corners: [Point2<f64>; 4]) -> Option<TagView> {
        let camera_pose = self.pose.pose()?;
        Some(TagView {
            intrinsics: self.intrinsics,
            camera_pose,
            camera_pose_covariance: self.pose.covariance(),
            corners,
            corner_sigma_factor: self.detector.corner_sigma_factor(),
        })
    }
}
