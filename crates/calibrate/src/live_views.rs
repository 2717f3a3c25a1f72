//! Live calibration: views grabbed from a configured camera while the target is moved,
//! keeping only frames that add coverage.
//!
//! Frames come from the caller: the command line builds [`grab_views`]'s `grab` from the
//! product's own sources on its config reduced to the one camera, so every source the config
//! supports (V4L2, Aravis, `sim`) works here. A frame is kept when the target is found and at
//! least three (`MIN_NEW_CELLS`) cells of a fine grid (16 columns) that no kept view has
//! touched yet hold its points; the first view is always kept. The loop ends after the
//! requested number of views or the time limit.

use std::sync::Arc;
use std::time::Instant;

use super::solve::View;
use super::target::{TargetDetector, TargetSpec};
use crate::error::{CalibrateError, GrabError};
use crate::fit::Rejected;
use tagdeflect_core::frame::{FrameSet, GrayImage};

/// New fine-grid cells a frame must cover to be kept.
pub const MIN_NEW_CELLS: usize = 3;

/// Columns of the fine grid that decides whether a frame adds coverage.
const FINE_COLS: usize = 16;

/// Tracks which fine-grid cells the kept views cover.
#[derive(Debug, Clone)]
pub struct CoverageTracker {
    width: u32,
    height: u32,
    rows: usize,
    seen: Vec<bool>,
}

impl CoverageTracker {
    /// An empty tracker for a `width` × `height` image.
    pub fn new(width: u32, height: u32) -> Self {
        let rows = ((FINE_COLS as f64 * height as f64 / width.max(1) as f64).round() as usize).max(4);
        Self { width, height, rows, seen: vec![false; FINE_COLS * rows] }
    }

    fn cells(&self, view: &View) -> Vec<usize> {
        let mut c: Vec<usize> = view
            .image
            .iter()
            .filter_map(|p| {
                let x = ((p.x + 0.5) / self.width as f64 * FINE_COLS as f64).floor();
                let y = ((p.y + 0.5) / self.height as f64 * self.rows as f64).floor();
                (x >= 0.0 && y >= 0.0 && (x as usize) < FINE_COLS && (y as usize) < self.rows).then(|| y as usize * FINE_COLS + x as usize)
            })
            .collect();
        c.sort_unstable();
        c.dedup();
        c
    }

    /// Cells of `view` not covered yet.
    pub fn new_cells(&self, view: &View) -> usize {
        self.cells(view).into_iter().filter(|&i| !self.seen[i]).count()
    }

    /// Marks the view's cells as covered.
    pub fn add(&mut self, view: &View) {
        for i in self.cells(view) {
            self.seen[i] = true;
        }
    }

    /// Fraction of fine cells covered.
    pub(crate) fn fraction(&self) -> f64 {
        self.seen.iter().filter(|s| **s).count() as f64 / self.seen.len() as f64
    }
}

/// Grabs views of `spec` from camera `camera`: at most `views` frames that add coverage,
/// within `duration_s`. `grab` returns the next frame set of that one camera (its first frame
/// is used; the command line grabs through its sources with a 5 s timeout), or a
/// [`GrabError`] with the message of why none came, which ends the grab with [`CalibrateError::Grab`] (`camera <camera>:
/// <message>`). `camera` names the camera in messages and logs. Returns the views, the image
/// size and the frames not used (with the reason) — the last only summarised, frames arrive
/// continuously.
pub fn grab_views(
    grab: &mut dyn FnMut() -> Result<FrameSet, GrabError>,
    camera: &str,
    spec: &TargetSpec,
    views: usize,
    duration_s: f64,
) -> Result<(Vec<View>, u32, u32, Vec<Rejected>), CalibrateError> {
    grab_views_kept(grab, camera, spec, views, duration_s).map(|g| (g.views, g.width, g.height, g.skipped))
}

/// What [`grab_views_kept`] grabbed.
#[derive(Debug, Clone)]
pub struct Grabbed {
    /// The views kept.
    pub views: Vec<View>,
    /// Image width, px.
    pub width: u32,
    /// Image height, px.
    pub height: u32,
    /// The frames not used, summarised.
    pub skipped: Vec<Rejected>,
    /// Each kept view's frame (same order and names as `views`): a tag target is detected
    /// again on them through the first calibration's intrinsics (`crate::run`).
    pub images: Vec<(String, Arc<GrayImage>)>,
}

/// [`grab_views`], keeping the kept views' frames too.
pub fn grab_views_kept(
    grab: &mut dyn FnMut() -> Result<FrameSet, GrabError>,
    camera: &str,
    spec: &TargetSpec,
    views: usize,
    duration_s: f64,
) -> Result<Grabbed, CalibrateError> {
    let mut det = TargetDetector::new(spec.clone())?;
    let t0 = Instant::now();
    let mut kept: Vec<View> = Vec::new();
    let mut images: Vec<(String, Arc<GrayImage>)> = Vec::new();
    let mut tracker: Option<CoverageTracker> = None;
    let (mut frames, mut no_target, mut no_gain) = (0usize, 0usize, 0usize);
    let mut last_reason = String::new();
    let mut size = (0, 0);
    while kept.len() < views && t0.elapsed().as_secs_f64() < duration_s {
        let set = grab().map_err(|e| CalibrateError::Grab { camera: camera.to_string(), message: e.message })?;
        let Some(frame) = set.frames.first() else { continue };
        frames += 1;
        let img = &frame.image;
        size = (img.width, img.height);
        let tr = tracker.get_or_insert_with(|| CoverageTracker::new(img.width, img.height));
        let name = format!("frame {}", frame.seq);
        match det.detect(img, &name) {
            Ok(v) => {
                let gain = tr.new_cells(&v);
                if kept.is_empty() || gain >= MIN_NEW_CELLS {
                    images.push((name, frame.image.clone()));
                    tr.add(&v);
                    tracing::info!(
                        camera,
                        views = kept.len() + 1,
                        points = v.object.len(),
                        coverage = format!("{:.0} %", 100.0 * tr.fraction()),
                        "view kept"
                    );
                    kept.push(v);
                } else {
                    no_gain += 1;
                }
            }
            Err(reason) => {
                no_target += 1;
                last_reason = reason.to_string();
            }
        }
    }
    let mut skipped = Vec::new();
    if no_target > 0 {
        skipped
            .push(Rejected { name: format!("{no_target} of {frames} frames"), reason: format!("target not found (last: {last_reason})") });
    }
    if no_gain > 0 {
        skipped.push(Rejected { name: format!("{no_gain} of {frames} frames"), reason: "added no coverage".into() });
    }
    Ok(Grabbed { views: kept, width: size.0, height: size.1, skipped, images })
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use super::*;
    use crate::render::{render_target, RenderOptions};
    use tagdeflect_core::camera::{CameraIntrinsics, Pose};
    use tagdeflect_core::frame::Frame;

    #[test]
    fn keeps_frames_that_add_coverage_and_names_the_camera_when_frames_stop() {
        let k = CameraIntrinsics { width: 640, height: 480, fx: 600.0, fy: 600.0, cx: 319.5, cy: 239.5, dist: [0.0; 5] };
        let spec: TargetSpec = "checkerboard:9x6:30".parse().unwrap();
        // The board's centre (120, 75) mm placed left of, again left of, then right of the middle.
        let frame = |seq: u64, dx: f64| {
            let pose = Pose::from_rvec_tvec([0.1, -0.1, 0.0], [-120.0 + dx, -75.0, 600.0]);
            let image = render_target(&spec, &k, &pose, &RenderOptions { seed: seq, ..RenderOptions::default() });
            FrameSet::new(seq, vec![Frame { camera: 0, seq, t_ns: 0, image: Arc::new(image) }])
        };
        let mut frames = vec![frame(0, -110.0), frame(1, -110.0), frame(2, 110.0)].into_iter();
        let mut grab = || frames.next().ok_or_else(|| GrabError { message: "no more frames".to_string() });
        let (views, w, h, skipped) = grab_views(&mut grab, "left", &spec, 2, 60.0).unwrap();
        assert_eq!((w, h), (640, 480));
        assert_eq!(views.len(), 2, "{skipped:?}");
        assert_eq!(views[0].name, "frame 0");
        assert_eq!(views[1].name, "frame 2");
        assert_eq!(skipped, vec![Rejected { name: "1 of 3 frames".into(), reason: "added no coverage".into() }]);

        // No frame at all: the camera is named with the source's message, a runtime failure.
        let mut grab = || Err::<FrameSet, _>(GrabError { message: "no camera delivered a frame within 5 s".to_string() });
        let e = grab_views(&mut grab, "left", &spec, 2, 60.0).unwrap_err();
        assert_eq!(e.to_string(), "camera left: no camera delivered a frame within 5 s");
        assert!(!e.is_bad_input());
    }
}
