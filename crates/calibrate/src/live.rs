//! Live calibration: views grabbed from a configured camera while the target is moved,
//! keeping only frames that add coverage.
//!
//! Frames come through the product's own sources ([`crate::pipeline::live::grab_frame_set`]
//! on the config reduced to the one camera), so every source the config supports (V4L2,
//! Aravis, `sim`) works here. A frame is kept when the target is found and at least
//! [`MIN_NEW_CELLS`] cells of a fine grid (16 columns) that no kept view has touched yet
//! hold its points; the first view is always kept. The loop ends after the requested number
//! of views or the time limit.

use std::path::Path;
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};

use super::solve::View;
use super::target::{TargetDetector, TargetSpec};
use super::Rejected;
use crate::config::Config;

/// New fine-grid cells a frame must cover to be kept.
pub const MIN_NEW_CELLS: usize = 3;

/// Columns of the fine grid that decides whether a frame adds coverage.
pub const FINE_COLS: usize = 16;

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
    pub fn fraction(&self) -> f64 {
        self.seen.iter().filter(|s| **s).count() as f64 / self.seen.len() as f64
    }
}

/// Grabs views of `spec` from camera `camera` of the config at `config_path`: at most `views`
/// frames that add coverage, within `duration_s`. Returns the views, the image size and the
/// frames not used (with the reason) — the last only summarised, frames arrive continuously.
pub fn grab_views(
    config_path: &Path,
    camera: &str,
    spec: &TargetSpec,
    views: usize,
    duration_s: f64,
) -> Result<(Vec<View>, u32, u32, Vec<Rejected>)> {
    let mut cfg = Config::load(config_path)?;
    let Some(i) = cfg.cameras.iter().position(|c| c.name == camera) else {
        let names: Vec<&str> = cfg.cameras.iter().map(|c| c.name.as_str()).collect();
        bail!("{}: no camera named {camera:?} (cameras: {})", config_path.display(), names.join(", "));
    };
    let cam = cfg.cameras.remove(i);
    cfg.cameras = vec![cam];
    let mut det = TargetDetector::new(spec.clone())?;
    let t0 = Instant::now();
    let mut kept: Vec<View> = Vec::new();
    let mut tracker: Option<CoverageTracker> = None;
    let (mut frames, mut no_target, mut no_gain) = (0usize, 0usize, 0usize);
    let mut last_reason = String::new();
    let mut size = (0, 0);
    while kept.len() < views && t0.elapsed().as_secs_f64() < duration_s {
        let set = crate::pipeline::live::grab_frame_set(&cfg, Duration::from_secs(5)).with_context(|| format!("camera {camera}"))?;
        let Some(frame) = set.frames.first() else { continue };
        frames += 1;
        let img = &frame.image;
        size = (img.width, img.height);
        let tr = tracker.get_or_insert_with(|| CoverageTracker::new(img.width, img.height));
        match det.detect(img, &format!("frame {}", frame.seq)) {
            Ok(v) => {
                let gain = tr.new_cells(&v);
                if kept.is_empty() || gain >= MIN_NEW_CELLS {
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
                last_reason = reason;
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
    Ok((kept, size.0, size.1, skipped))
}
