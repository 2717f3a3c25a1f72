//! The report's part of the config: `[specimen.beam]` (the specimen's geometry; the type is
//! `config::BeamConfig`, read here with the span of every value for located errors) and
//! `[report]` (what `run` writes at its end). Validated when the config is loaded
//! (`config::Config::from_toml_str` calls `RawBeam::resolve` and [`validate_report`]).

use serde::{Deserialize, Serialize};
use std::path::PathBuf;

use super::Standard;

pub use crate::config::BeamConfig;

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

/// A problem with `[specimen.beam]` or `[report]`: the key (below the table) and the message.
pub type Problem = (&'static str, String);

/// `[specimen.beam]` as written, with the span of every value (for located errors).
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct RawBeam {
    width_mm: toml::Spanned<f64>,
    depth_mm: toml::Spanned<f64>,
    span_mm: toml::Spanned<f64>,
    #[serde(default)]
    notch_mm: Option<toml::Spanned<f64>>,
}

impl RawBeam {
    /// The validated beam, or the byte span, key and message of the first problem.
    pub(crate) fn resolve(&self) -> Result<BeamConfig, (std::ops::Range<usize>, &'static str, String)> {
        let b = BeamConfig {
            width_mm: *self.width_mm.get_ref(),
            depth_mm: *self.depth_mm.get_ref(),
            span_mm: *self.span_mm.get_ref(),
            notch_mm: self.notch_mm.as_ref().map(|n| *n.get_ref()),
        };
        validate_beam(&b).map_err(|(key, msg)| {
            let span = match key {
                "width_mm" => self.width_mm.span(),
                "depth_mm" => self.depth_mm.span(),
                "notch_mm" => self.notch_mm.as_ref().map_or(self.depth_mm.span(), |n| n.span()),
                _ => self.span_mm.span(),
            };
            (span, key, msg)
        })?;
        Ok(b)
    }
}

/// Checks `[specimen.beam]` (the value checks of `BeamConfig::validate`, and a span that is
/// longer than the depth).
pub fn validate_beam(b: &BeamConfig) -> Result<(), Problem> {
    b.validate()?;
    if b.span_mm < b.depth_mm {
        return Err(("span_mm", format!("span {} mm is shorter than the depth {} mm: not a beam in bending", b.span_mm, b.depth_mm)));
    }
    Ok(())
}

/// Checks `[report]` against the beam it will need.
pub fn validate_report(r: &ReportConfig, beam: Option<&BeamConfig>) -> Result<(), Problem> {
    let Some(beam) = beam else {
        return Err(("standard", "a report needs the specimen's geometry: add [specimen.beam] with width_mm, depth_mm, span_mm".into()));
    };
    if r.standard == Standard::En14651 && beam.notch_mm.is_none() {
        return Err(("standard", "EN 14651 tests notched beams: give [specimen.beam] notch_mm".into()));
    }
    if r.out.as_os_str().is_empty() {
        return Err(("out", "must name a folder".into()));
    }
    if r.smooth_points == 0 || r.smooth_points.is_multiple_of(2) || r.smooth_points > 101 {
        return Err(("smooth_points", format!("must be an odd number of points from 1 to 101, got {}", r.smooth_points)));
    }
    if let Some(q) = r.load_resolution_kn {
        if !(q.is_finite() && q >= 0.0) {
            return Err(("load_resolution_kn", format!("must be a non-negative load in kN, got {q}")));
        }
    }
    Ok(())
}
