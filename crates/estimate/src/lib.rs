//! Estimation: from the tags detected in a frame set to the feed line. The measurement
//! ([`measure::Measurement`]) runs a frame set through its stages — detect (the `detect`
//! crate) → pose cameras → solve specimen tags → temporal estimate → gauges → line — and
//! holds what carries over between sets; the modules below are its parts, pure maths on
//! observations (pixels) and known geometry (no images, no I/O).
//!
//! * [`measure`]: the measurement, one file per stage; what it is built from
//!   ([`measure::MeasurementRig`]); [`measure_config`]: its `[measure]` section.
//! * [`camera_pose`]: one camera's pose from background tags (closed-form start + LM with
//!   the distortion model in the residual, outlier tags rejected, 6×6 covariance).
//! * [`held_pose`]: a camera's pose kept across frame sets ([`HeldCameraPose`]): held still
//!   while the camera is static so per-frame noise does not leak into the measurement,
//!   re-posed when the camera is bumped, a re-pose refused when it fails its checks.
//! * [`drift`]: slow drift of a held camera estimated from the background tags
//!   ([`DriftFilter`], a Kalman filter on the pose since it was fixed).
//! * [`tag_pose`]: a specimen tag's 6-DOF pose over all views at once ([`solve_tag`]),
//!   warm-started, outlier views rejected, σ from the covariance.
//! * [`temporal`]: each specimen tag's centre and rate carried over frame sets
//!   ([`temporal::TagFilter`], two Kalman filters mixed as an interacting multiple model,
//!   steady and changing motion, each with adaptive process noise; RTS smoother).
//! * [`partial`]: a partial frame set's solve referred to the tag's last full sets, so that
//!   the subset's camera-pose errors do not throw it; [`motion`]: the per-set estimator's
//!   depth of a monocular view from the recent multi-view motion.
//! * [`smooth`]: a fixed-lag RTS smoother over the temporal estimate's lines (replay).
//! * [`temporal_response`]: the temporal estimate's gain, phase lag and step response (the
//!   control signal's dynamics, docs/control.md).
//! * [`gauges`]: the virtual gauges (`[[gauge]]`) with their σ;
//!   [`clock_offset`]: the clock check of the UTM's clock against the cameras'
//!   (`[clock_check]`).
//! * [`lm`]: the small Levenberg–Marquardt the solves use; [`init`]: closed-form starts.
//!
//! Pose step convention (for every Jacobian and covariance here): a 6-vector `(ω, v)`
//! updates a pose `(R, t)` to `(exp(ω) R, t + v)`; ω in radians, v in mm.

pub mod camera_pose;
pub mod clock_offset;
pub mod drift;
mod error;
pub mod gauges;
pub mod held_pose;
pub mod init;
pub mod lm;
pub mod measure;
pub mod measure_config;
pub mod motion;
pub mod partial;
pub mod smooth;
pub mod tag_pose;
pub mod temporal;
pub mod temporal_response;

pub use camera_pose::{solve_camera_pose, BackgroundTagObservation, CameraPoseSolution};
pub use drift::{DriftConfig, DriftEstimate, DriftFilter};
pub use error::SolveError;
pub use held_pose::{FirstPoseRefused, HeldCameraPose, HeldPoseOptions, HeldPoseStatus};
pub use motion::TagMotion;
pub use tag_pose::{corner_residuals_px, solve_tag, PixelNoisePool, TagSolution, TagView};
