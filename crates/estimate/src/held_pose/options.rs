//! A held pose's tuning, what one update found, and the checks' constants.

use nalgebra::Matrix6;

use crate::drift::{DriftConfig, DriftEstimate};
use tagdeflect_core::camera::Pose;

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
pub(super) const SANITY_CHECK_UPDATES: usize = 10;
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
