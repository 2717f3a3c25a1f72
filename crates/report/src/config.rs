//! The report's section of the config: `[report]` (what `run` writes at its end), checked
//! against the specimen's geometry (`[specimen.beam]`, [`BeamConfig`]) when the config is
//! loaded ([`validate_report`]).

use serde::{Deserialize, Serialize};
use std::path::PathBuf;

use super::Standard;

pub use tagdeflect_core::beam::BeamConfig;
use tagdeflect_core::Problem;

/// `[report]`: `run` writes the test report at its end (SPEC "Report").
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ReportConfig {
    /// The standard the report follows.
    pub standard: Standard,
    /// Folder that receives one timestamped sub-folder per run (relative paths are
    /// relative to the config file's folder).
    pub out: PathBuf,
    /// Gauge used as the net deflection (default: the feed's `net_deflection_mm`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub deflection_gauge: Option<String>,
    /// Gauge used as the CMOD for EN 14651 (default: the gauge named `cmod`, else the only
    /// gauge in mm whose name contains "cmod" or "opening").
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cmod_gauge: Option<String>,
    /// Points of the moving local-linear smoothing of deflection/CMOD over time (odd, ≥ 1;
    /// 1 = no smoothing).
    #[serde(default = "default_smooth", skip_serializing_if = "is_default_smooth")]
    pub smooth_points: usize,
    /// Resolution of the load reading, kN (adds `resolution/√12` to every load's σ).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub load_resolution_kn: Option<f64>,
}

/// Default smoothing window (points).
pub fn default_smooth() -> usize {
    5
}

fn is_default_smooth(n: &usize) -> bool {
    *n == default_smooth()
}

/// Checks `[report]` against the beam it will need.
/// Keys are relative to `[report]`.
pub fn validate_report(r: &ReportConfig, beam: Option<&BeamConfig>) -> Result<(), Problem> {
    let Some(beam) = beam else {
        return Err(Problem::new(
            "standard",
            "a report needs the specimen's geometry: add [specimen.beam] with width_mm, depth_mm, span_mm",
        ));
    };
    if r.standard == Standard::En14651 && beam.notch_mm.is_none() {
        return Err(Problem::new("standard", "EN 14651 tests notched beams: give [specimen.beam] notch_mm"));
    }
    if r.out.as_os_str().is_empty() {
        return Err(Problem::new("out", "must name a folder"));
    }
    if r.smooth_points == 0 || r.smooth_points.is_multiple_of(2) || r.smooth_points > 101 {
        return Err(Problem::new("smooth_points", format!("must be an odd number of points from 1 to 101, got {}", r.smooth_points)));
    }
    if let Some(q) = r.load_resolution_kn {
        if !(q.is_finite() && q >= 0.0) {
            return Err(Problem::new("load_resolution_kn", format!("must be a non-negative load in kN, got {q}")));
        }
    }
    Ok(())
}
