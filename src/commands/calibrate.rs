//! `tagdeflect calibrate`: the command line of the calibration (`tagdeflect_calibrate` detects
//! the target and solves); in live mode this module opens the config's camera through the
//! program's own sources.

use std::path::Path;
use std::time::Duration;

use anyhow::Result;
use tagdeflect_calibrate::solve::View;
use tagdeflect_calibrate::target::TargetSpec;
use tagdeflect_calibrate::{CalibrateError, CalibrateOptions, GrabError, Rejected};

use crate::config::Config;
use tagdeflect_core::frame::FrameSet;

/// A calibration error with its exit code: bad input (a bad option, target or image; too
/// few views) exits 2, a failure of the machine (a camera that delivers nothing, an output
/// that cannot be written) exits 1, a calibration written with a POOR verdict exits 3.
fn with_exit_code(e: CalibrateError) -> anyhow::Error {
    if matches!(e, CalibrateError::Poor { .. }) {
        return anyhow::Error::new(tagdeflect_core::NotFit::new(e.to_string()));
    }
    if e.is_bad_input() {
        anyhow::Error::new(tagdeflect_core::BadInput::new(e.to_string()))
    } else {
        anyhow::Error::new(tagdeflect_core::RuntimeFailure::new(e.to_string()))
    }
}

/// The config's camera `camera` alone, and a grab of its next frame set.
fn one_camera(config_path: &Path, camera: &str) -> Result<Config> {
    let mut cfg = Config::load(config_path)?;
    let Some(i) = cfg.cameras.iter().position(|c| c.name == camera) else {
        let names: Vec<&str> = cfg.cameras.iter().map(|c| c.name.as_str()).collect();
        return Err(tagdeflect_core::BadInput::new(format!(
            "{}: no camera named {camera:?} (cameras: {})",
            config_path.display(),
            names.join(", ")
        ))
        .into());
    };
    let cam = cfg.cameras.remove(i);
    cfg.cameras = vec![cam];
    Ok(cfg)
}

fn grabber(cfg: Config) -> impl FnMut() -> Result<FrameSet, GrabError> {
    move || crate::graph::entry::grab_frame_set(&cfg, Duration::from_secs(5)).map_err(|e| GrabError { message: format!("{e:#}") })
}

/// Live mode: views of the target from the config's camera `camera`, kept when they add
/// coverage (see `tagdeflect_calibrate::live_views::grab_views`).
pub fn grab_views(
    config_path: &Path,
    camera: &str,
    spec: &TargetSpec,
    views: usize,
    duration_s: f64,
) -> Result<(Vec<View>, u32, u32, Vec<Rejected>)> {
    let mut grab = grabber(one_camera(config_path, camera)?);
    tagdeflect_calibrate::live_views::grab_views(&mut grab, camera, spec, views, duration_s).map_err(with_exit_code)
}

/// `tagdeflect calibrate`.
pub fn run(opts: &CalibrateOptions) -> Result<()> {
    // Option and target errors first, as before the config is read.
    tagdeflect_calibrate::check_options(opts).map_err(with_exit_code)?;
    match (&opts.config, &opts.camera) {
        (Some(path), Some(camera)) => {
            let mut grab = grabber(one_camera(path, camera)?);
            tagdeflect_calibrate::run(opts, Some(&mut grab)).map_err(with_exit_code)
        }
        _ => tagdeflect_calibrate::run(opts, None).map_err(with_exit_code),
    }
}
