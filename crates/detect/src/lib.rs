//! Tag detection: the AprilTag library behind a safe wrapper, converted to the product's
//! pixel convention (OpenCV: pixel centres at integers) and SPEC corner order; sub-pixel
//! refinement; and one camera's detection from frame to frame ([`CameraDetector`]: what to
//! look for, confirming followed tags, window and sweep searches).

pub mod apriltag;
mod camera_detector;
mod confirm;
mod detect_report;
mod detection;
mod error;
mod family;
mod learned;
pub mod plan;
mod rect;
pub mod refine;

pub use self::apriltag::{Detector, DetectorOptions, RawDetection, SearchOptions};
pub use self::camera_detector::{CameraDetections, CameraDetector, RigDetectors, TagRoles};
pub use self::confirm::{ConfirmMiss, ConfirmOptions, ConfirmedTag, Prediction, TagConfirmer};
pub use self::detect_report::{DetectParts, DetectReport};
pub use self::detection::Detection;
pub use self::error::DetectError;
pub use self::family::tag_bitmap;
pub use self::rect::Rect;
pub use self::refine::{
    refine_corners, refine_corners_warm, refine_corners_with, EdgeLevels, EdgeMemory, EdgeProfile, ProfileLearner, RefineOptions,
    RefineReport, RefineStats,
};
