//! `tagdeflect calibrate`: camera intrinsics from views of a target, with their
//! uncertainty and what it means for a measurement.
//!
//! [`target`] parses `--target` and finds the target in an image; [`solve`] runs Zhang's
//! closed-form start and the Levenberg–Marquardt fit over all views with the product's camera
//! model; [`calibrate_views`] adds the outlier policy, [`calibrate_target_views`] the tag
//! corners' systematic bias to the σ; [`spread`] the spread of the intrinsics across the views
//! (each left out in turn) beside that σ; [`report`] makes the coverage map, the
//! uncertainty at a distance and the OpenCV FileStorage file; [`live_views`] grabs views from a
//! camera whose frames the caller supplies; [`render`] renders targets with known intrinsics
//! for tests. Errors are [`CalibrateError`]s, which tell bad input from runtime failures.
//!
//! **Outliers.** After a fit, single points whose residual exceeds
//! `max(5 s, 1 px)` (`s` the residual scatter per axis) are dropped, then whole views whose
//! RMS exceeds `max(3 × median view RMS, 0.5 px)` are rejected and named with their RMS, and
//! the fit is repeated until nothing more is dropped (at least three views stay).
//!
//! **Guard rails** ([`guard`]): too few views, a `--target` that is not the board in the
//! images, and views of another camera or focus are refused or named; every calibration ends
//! with a verdict (good / usable / poor) with its reasons and hints.
//!
//! The files: `options` (the command line), `views` (images to views), `fit` (the outlier
//! policy), `outputs` (the report and the files), `command` (a run from start to end).

mod command;
mod error;
mod fit;
pub mod guard;
pub mod live_views;
mod options;
mod outputs;
pub mod render;
pub mod report;
pub mod solve;
pub mod spread;
pub mod target;
mod views;

pub use command::{calibrate_folder, calibrate_guarded, calibrate_live, run};
pub use error::{CalibrateError, GrabError};
pub use fit::{calibrate_target_views, calibrate_views, tag_corner_bias, CalibrationRun, Rejected};
pub use options::{check_options, CalibrateOptions};
pub use spread::{view_spread, ViewSpread};
pub use views::{detect_views, detect_views_seen, detect_views_seen_with, image_files, Detected};
