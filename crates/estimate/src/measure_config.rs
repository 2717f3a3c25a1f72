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
    /// How frame sets become positions: `"temporal"` (each tag's state carried over sets,
    /// see `estimate::temporal`) or `"per_set"` (every set solved on its own).
    #[serde(skip_serializing_if = "is_default_estimator")]
    pub estimator: crate::temporal::Estimator,
    /// Temporal estimator: expected size (1 σ) of the unmodelled change of a tag's rate,
    /// mm/s per √s (the process noise; it adapts upward to the innovations).
    #[serde(skip_serializing_if = "is_default_accel")]
    pub temporal_accel_mm_s2: f64,
}

fn is_default_estimator(e: &crate::temporal::Estimator) -> bool {
    *e == crate::temporal::Estimator::default()
}
fn is_default_accel(v: &f64) -> bool {
    *v == crate::temporal::DEFAULT_ACCEL_MM_S2
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
            estimator: crate::temporal::Estimator::Temporal,
            temporal_accel_mm_s2: crate::temporal::DEFAULT_ACCEL_MM_S2,
        }
    }
}

impl MeasureConfig {
    /// Checks `[measure]` with the detector's and the drift model's own limits (so nothing
    /// fails after `tagdeflect check`); keys relative to `[measure]`.
    pub fn validate(&self) -> Result<(), tagdeflect_core::Problem> {
        use tagdeflect_core::Problem;
        if !(self.quad_decimate.is_finite() && self.quad_decimate >= 1.0) {
            return Err(Problem::new("quad_decimate", "must be >= 1.0 (1 = full resolution)"));
        }
        if self.detector_threads == 0 {
            return Err(Problem::new("detector_threads", "must be >= 1"));
        }
        let opts = tagdeflect_detect::DetectorOptions {
            quad_decimate: self.quad_decimate,
            nthreads: self.detector_threads,
            ..tagdeflect_detect::DetectorOptions::default()
        };
        if let Err(tagdeflect_detect::DetectError::BadOption { name, value, expected }) = opts.validate() {
            let key = match name {
                "nthreads" => "detector_threads",
                "quad_decimate" => "quad_decimate",
                _ => "",
            };
            return Err(Problem::new(key, format!("{value} is out of range: {expected}")));
        }
        if !(self.full_search_interval_s.is_finite() && self.full_search_interval_s > 0.0 && self.full_search_interval_s <= 3600.0) {
            return Err(Problem::new(
                "full_search_interval_s",
                format!("must be in (0, 3600] seconds, got {}", self.full_search_interval_s),
            ));
        }
        if !(self.temporal_accel_mm_s2.is_finite() && self.temporal_accel_mm_s2 > 0.0 && self.temporal_accel_mm_s2 <= 1e3) {
            return Err(Problem::new(
                "temporal_accel_mm_s2",
                format!("{}: expected a positive number of mm/s per √s (at most 1000)", self.temporal_accel_mm_s2),
            ));
        }
        crate::DriftConfig::from_measure(self).validate()
    }

    /// The temporal estimator's options.
    pub fn temporal(&self) -> crate::temporal::TemporalConfig {
        crate::temporal::TemporalConfig { accel_mm_s2: self.temporal_accel_mm_s2, ..Default::default() }
    }
}
