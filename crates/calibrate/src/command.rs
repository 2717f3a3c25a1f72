//! `tagdeflect calibrate` from start to end: from a folder of images or from a live camera,
//! with the guard rails' verdict.

use std::path::Path;

use crate::error::{CalibrateError, GrabError};
use crate::fit::{calibrate_target_views, CalibrationRun, Rejected};
use crate::options::{check_options, CalibrateOptions};
use crate::outputs::write_outputs;
use crate::solve::View;
use crate::target::{BoardSeen, TargetDetector, TargetSpec};
use crate::views::{detect_views_seen, detect_views_seen_with, image_files};
use crate::{guard, live_views};
use tagdeflect_core::frame::FrameSet;

/// `tagdeflect calibrate`: from a folder of images (`--images`) or live (`--config FILE
/// --camera NAME`), then writes the outputs and prints the report.
///
/// Live mode needs `grab`: the next frame set of that one camera ([`GrabError`] with the message
/// when none arrives in time), which the caller builds from the config's camera and its
/// source; see [`live_views::grab_views`]. With `--images`, `grab` must be `None`.
pub fn run(opts: &CalibrateOptions, grab: Option<&mut dyn FnMut() -> Result<FrameSet, GrabError>>) -> Result<(), CalibrateError> {
    let spec = check_options(opts)?;
    let (run, notes, not_found) = match (&opts.images, &opts.camera, grab) {
        (Some(dir), None, None) => calibrate_folder(dir, &spec, opts)?,
        (None, Some(cam), Some(grab)) => calibrate_live(grab, cam, &spec, opts)?,
        _ => return Err(CalibrateError::BadOption("calibrate takes either --images DIR or --config FILE --camera NAME".into())),
    };
    match write_outputs(&run, &not_found, &spec, opts, &notes) {
        Ok(text) => {
            print!("{text}");
            Ok(())
        }
        Err(CalibrateError::Poor { text, why }) => {
            print!("{text}");
            Err(CalibrateError::Poor { text: String::new(), why })
        }
        Err(e) => Err(e),
    }
}

/// A folder of images calibrated as `calibrate --images DIR` does: detected, calibrated with
/// the guard rails, and — for tag targets — detected again with the tag edges fitted through
/// that first calibration and calibrated again (tag edges are straight only without the lens:
/// the second pass removes the bias of fitting lines to bent edges; module docs). Returns the
/// run, its warnings and the images the target was not found in.
pub fn calibrate_folder(
    dir: &Path,
    spec: &TargetSpec,
    opts: &CalibrateOptions,
) -> Result<(CalibrationRun, Vec<String>, Vec<Rejected>), CalibrateError> {
    let files = image_files(dir)?;
    let d = detect_views_seen(&files, spec)?;
    let (run, notes) = calibrate_guarded(d.views, d.width, d.height, &d.not_found, &d.seen, spec, opts)?;
    if !spec.has_tags() {
        return Ok((run, notes, d.not_found));
    }
    let d = detect_views_seen_with(&files, spec, Some(&run.calibration.intrinsics))?;
    let (run, notes) = calibrate_guarded(d.views, d.width, d.height, &d.not_found, &d.seen, spec, opts)?;
    Ok((run, notes, d.not_found))
}

/// Live calibration (`calibrate --config FILE --camera NAME`): views grabbed while they add
/// coverage ([`live_views::grab_views_kept`]), calibrated with the guard rails, and — for tag
/// targets — the kept frames detected again through that first calibration and calibrated
/// again, exactly as [`calibrate_folder`] does with files (the same frames give the same
/// result either way).
pub fn calibrate_live(
    grab: &mut dyn FnMut() -> Result<FrameSet, GrabError>,
    camera: &str,
    spec: &TargetSpec,
    opts: &CalibrateOptions,
) -> Result<(CalibrationRun, Vec<String>, Vec<Rejected>), CalibrateError> {
    let g = live_views::grab_views_kept(grab, camera, spec, opts.views, opts.duration_s)?;
    let (run, notes) = calibrate_guarded(g.views, g.width, g.height, &g.skipped, &[], spec, opts)?;
    if !spec.has_tags() {
        return Ok((run, notes, g.skipped));
    }
    let mut det = TargetDetector::new(spec.clone())?;
    det.set_intrinsics(Some(run.calibration.intrinsics));
    let mut views = Vec::new();
    let mut skipped = g.skipped;
    for (name, img) in &g.images {
        match det.detect(img, name) {
            Ok(v) => views.push(v),
            Err(reason) => skipped.push(Rejected { name: name.clone(), reason: format!("second pass: {reason}") }),
        }
    }
    let (run, notes) = calibrate_guarded(views, g.width, g.height, &skipped, &[], spec, opts)?;
    Ok((run, notes, skipped))
}

/// The guard rails around [`calibrate_views`] (see [`guard`]): the board check, the minimum
/// number of views, and views of another camera or focus — a minority of them (under a
/// third of the views) rejected and named, a larger group refused unless `--force`. Returns
/// the run and the warnings to print.
pub fn calibrate_guarded(
    views: Vec<View>,
    width: u32,
    height: u32,
    not_found: &[Rejected],
    seen: &[(String, BoardSeen)],
    spec: &TargetSpec,
    opts: &CalibrateOptions,
) -> Result<(CalibrationRun, Vec<String>), CalibrateError> {
    guard::check_board(spec, &opts.target, seen, opts.force)?;
    let need = if opts.force { guard::ABSOLUTE_MIN_VIEWS } else { guard::MIN_VIEWS };
    if views.len() < need {
        return Err(CalibrateError::TooFewViews { found: views.len(), need, forced: opts.force, not_found: not_found.to_vec() });
    }
    let mut notes = Vec::new();
    if views.len() < guard::MIN_VIEWS {
        notes.push(format!("--force: calibrated from {} views, fewer than the {} needed for trustworthy σ", views.len(), guard::MIN_VIEWS));
    }
    let options = opts.solve_options();
    let mut run = calibrate_target_views(views, width, height, spec, &options, opts.keep_outliers)?;
    if let Some(split) = guard::split_views(&run, &options) {
        let what = split.describe(&run.views);
        if 3 * split.minority.len() < run.views.len() {
            let mut keep = Vec::new();
            let mut rejected = std::mem::take(&mut run.rejected);
            for (i, v) in run.views.into_iter().enumerate() {
                if split.minority.contains(&i) {
                    rejected.push(Rejected {
                        name: v.name,
                        reason: "another camera or focus setting: its views fit other intrinsics (see the warning)".into(),
                    });
                } else {
                    keep.push(v);
                }
            }
            let dropped = run.dropped_points;
            run = calibrate_target_views(keep, width, height, spec, &options, opts.keep_outliers)?;
            rejected.append(&mut run.rejected);
            run.rejected = rejected;
            run.dropped_points += dropped;
            notes.push(format!("views of another camera or focus setting rejected: {what}"));
        } else if opts.force {
            notes.push(format!("--force: the views look like two cameras or focus settings, calibrated as one: {what}"));
        } else {
            return Err(CalibrateError::MixedViews(format!(
                "the views look like two cameras or two focus settings: {what}. Calibrate each camera (and focus) from its own \
                 folder; --force calibrates them as one"
            )));
        }
    }
    Ok((run, notes))
}
