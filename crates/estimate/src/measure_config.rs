//! `[measure]` (extension): options of the measurement pipeline.

use serde::{Deserialize, Serialize};

/// `[measure]` (extension): options of the measurement pipeline.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MeasureConfig {
    /// AprilTag `quad_decimate` for full-frame searches (1 = full resolution).
    pub quad_decimate: f32,
    /// AprilTag searches (full frames, windows, sweep tiles) that may run side by side, each
    /// single-threaded, on C workers sharing one set of family tables.
    pub detector_threads: u32,
    /// Refine detector corners against the image gradient (see `detect`).
    pub refine_corners: bool,
    /// Region-of-interest tracking between full-frame searches.
    pub roi_tracking: bool,
    /// Seconds between periodic full-frame searches when tracking.
    pub full_search_interval_s: f64,
    /// Track slow camera drift while poses are held (see `solve::drift`).
    #[serde(skip_serializing_if = "is_true")]
    pub drift_tracking: bool,
    /// Expected size (1 σ) of a camera's turning rate, degrees per hour.
    #[serde(skip_serializing_if = "is_0_1")]
    pub drift_rate_deg_per_h: f64,
    /// Expected size (1 σ) of the creep rate of a camera's centre, mm per hour.
    #[serde(skip_serializing_if = "is_1")]
    pub drift_rate_mm_per_h: f64,
    /// Time over which the drift rate may change by about its σ, hours.
    #[serde(skip_serializing_if = "is_1")]
    pub drift_rate_change_h: f64,
}

// Defaults are not written back, so a recording's config reads as before these options.
fn is_true(v: &bool) -> bool {
    *v
}
fn is_0_1(v: &f64) -> bool {
    *v == 0.1
}
fn is_1(v: &f64) -> bool {
    *v == 1.0
}

impl Default for MeasureConfig {
    fn default() -> Self {
        Self {
            quad_decimate: 1.0,
            detector_threads: 2,
            refine_corners: true,
            roi_tracking: true,
            full_search_interval_s: 1.0,
            drift_tracking: true,
            drift_rate_deg_per_h: 0.1,
            drift_rate_mm_per_h: 1.0,
            drift_rate_change_h: 1.0,
        }
    }
}

