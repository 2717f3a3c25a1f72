//! What a measurement counts and times.

use tagdeflect_detect::{DetectParts, DetectReport};

/// Wall-clock time spent in each stage of one frame set, seconds.
#[derive(Debug, Clone, Copy, Default)]
pub struct StageTimes {
    /// Tag detection (all cameras, in parallel; wall time).
    pub detect: f64,
    /// Detection time by kind of work.
    pub detect_parts: DetectParts,
    /// Camera pose tracking.
    pub pose: f64,
    /// Specimen tag solving (and their temporal estimate).
    pub solve: f64,
}

/// Counters over a whole run.
#[derive(Debug, Clone, Default)]
pub struct MeasureStats {
    /// Frame sets processed.
    pub sets: u64,
    /// Full-frame detections run.
    pub full_frame_searches: u64,
    /// Window (region-of-interest) and sweep-tile detections run.
    pub window_searches: u64,
    /// Of those, windows searched again at the configured resolution after the decimated
    /// search missed a tag expected there (see `detect::camera_detector`).
    pub window_retries: u64,
    /// Whole-frame searches run in the background (see `detect::camera_detector`).
    pub background_searches: u64,
    /// Tag views confirmed at their predicted place (no search needed).
    pub tracked_tags: u64,
    /// Of those, fitted on pixels selected in an earlier frame.
    pub reused_band_tags: u64,
    /// Specimen tag views rejected as outliers.
    pub rejected_views: u64,
    /// Camera bumps detected.
    pub bumps: u64,
    /// Whole-frame searches of a frame whose background tags were lost or jumped (in
    /// `full_frame_searches` too).
    pub moved_camera_searches: u64,
    /// Whole-frame searches of a frame whose camera's first pose was undecided (in
    /// `full_frame_searches` too; see `measure::pose`).
    pub first_pose_searches: u64,
    /// Frame-set views of cameras left out because their re-pose (or first pose) failed
    /// its checks.
    pub refused_poses: u64,
    /// Tag solutions of partial sets referred to the tag's last full sets (temporal
    /// estimator, `estimate::partial`).
    pub referred_partial_views: u64,
    /// The edge model's error moved since the tags' references, `D`, px² per corner
    /// coordinate (`model_drift`; `None` until enough corners were compared).
    pub model_drift_px2: Option<f64>,
    /// The corners' pixel noise that changes from set to set, px² per coordinate
    /// (`model_drift`; the white part of the pooled corner noise).
    pub white_noise_px2: Option<f64>,
}

impl MeasureStats {
    /// Counts what one camera's detection of one frame did.
    pub(super) fn add_detection(&mut self, report: &DetectReport) {
        self.full_frame_searches += report.full_frame_searches;
        self.window_searches += report.window_searches;
        self.window_retries += report.window_retries;
        self.background_searches += report.background_searches;
        self.tracked_tags += report.confirmed_tags;
        self.reused_band_tags += report.reused_bands;
    }
}
