//! The report's section of the config: `[report]` (what `run` writes at its end), checked
//! against the specimen's geometry (`[specimen.beam]`, [`BeamConfig`]) when the config is
//! loaded ([`ReportConfig::validate_with`]).

use serde::{Deserialize, Serialize};
use std::path::PathBuf;

use crate::standard::Standard;

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
    /// The specimen's response as the lab states it (ASTM C1609/C1856): `softening` (the
    /// default: the first peak must lie before L/150 and the load fall from it) or
    /// `hardening` (deflection-hardening: the load may rise past the first crack to a peak
    /// beyond L/150, where the first zero slope — and so P1 — then lies).
    #[serde(default, skip_serializing_if = "Response::is_default")]
    pub response: Response,
    /// Resolution of the load reading, kN (adds `resolution/√12` to every load's σ).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub load_resolution_kn: Option<f64>,
    /// Largest |load| a feed or UTM line may carry, kN (beyond: the line is an error).
    #[serde(default = "default_max_load", skip_serializing_if = "is_default_max_load")]
    pub max_load_kn: f64,
    /// Largest |length| a feed line may carry (positions, displacements, gauges, σ), mm.
    #[serde(default = "default_max_length", skip_serializing_if = "is_default_max_length")]
    pub max_length_mm: f64,
    /// Longest time without a feed line or a UTM sample that a valid test may have, s.
    #[serde(default = "default_max_gap", skip_serializing_if = "is_default_max_gap")]
    pub max_gap_s: f64,
    /// Print `report.pdf` with headless Chromium when it is installed.
    #[serde(default = "yes", skip_serializing_if = "is_true")]
    pub pdf: bool,
    /// What the lab files with the values (specimen id, operator, dates, machine, ...).
    #[serde(default, skip_serializing_if = "LabInfo::is_empty")]
    pub lab: LabInfo,
    /// The test's method as its file says (`test.json` `method`, the file of that hash): its
    /// phases' rate windows and its end criterion replace the standard's built-in ones in the
    /// validity. Not a config key: set from a test's record.
    #[serde(skip)]
    pub method: Option<tagdeflect_core::method::Method>,
}

/// `[report] response`: the flexural response the lab states for the specimen.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "snake_case")]
pub enum Response {
    /// Deflection-softening: the load falls after the first peak (most fibre concretes).
    #[default]
    Softening,
    /// Deflection-hardening: the load rises past the first crack (UHPC and high fibre
    /// contents); a first peak beyond L/150 is then the specimen's, not a failed test.
    Hardening,
}

impl Response {
    /// The name in the config and in `report.json`.
    pub fn id(self) -> &'static str {
        match self {
            Response::Softening => "softening",
            Response::Hardening => "hardening",
        }
    }

    fn is_default(&self) -> bool {
        *self == Response::default()
    }
}

/// `[report.lab]`: what identifies the test on the report (each optional; a `test.json`
/// beside the feed fills `specimen` and `operator` when they are not given here).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LabInfo {
    /// Specimen id.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub specimen: Option<String>,
    /// Operator.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub operator: Option<String>,
    /// Cast date, `YYYY-MM-DD`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cast_date: Option<String>,
    /// Test date, `YYYY-MM-DD` (default: the date of the feed's first line, UTC).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub test_date: Option<String>,
    /// Edition of the standard followed, e.g. `C1609/C1609M-19a` or `EN 14651:2005+A1:2007`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub edition: Option<String>,
    /// Testing machine (make, model, serial; load cell).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub machine: Option<String>,
    /// Where the specimen broke (e.g. `within the middle third`, `12 mm left of the notch`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fracture: Option<String>,
    /// Laboratory name.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub laboratory: Option<String>,
}

impl LabInfo {
    /// True when nothing is given.
    pub fn is_empty(&self) -> bool {
        *self == LabInfo::default()
    }

    /// The specimen's age at test, days (from the cast and test dates).
    pub fn age_days(&self) -> Option<i64> {
        let d = |s: &Option<String>| s.as_deref().and_then(|s| chrono::NaiveDate::parse_from_str(s, "%Y-%m-%d").ok());
        Some((d(&self.test_date)? - d(&self.cast_date)?).num_days())
    }

    /// Checks the dates; keys relative to `[report.lab]`.
    pub fn validate(&self) -> Result<(), Problem> {
        for (k, v) in [("cast_date", &self.cast_date), ("test_date", &self.test_date)] {
            if let Some(v) = v {
                if chrono::NaiveDate::parse_from_str(v, "%Y-%m-%d").is_err() {
                    return Err(Problem::new(k, format!("must be a date YYYY-MM-DD, got {v:?}")));
                }
            }
        }
        if let Some(a) = self.age_days() {
            if a < 0 {
                return Err(Problem::new("test_date", format!("is {} day(s) before the cast date", -a)));
            }
        }
        Ok(())
    }
}

fn yes() -> bool {
    true
}
fn is_true(v: &bool) -> bool {
    *v
}

/// Default `max_load_kn`.
pub fn default_max_load() -> f64 {
    crate::feed_reader::DEFAULT_MAX_LOAD_KN
}
fn is_default_max_load(v: &f64) -> bool {
    *v == default_max_load()
}
/// Default `max_length_mm`.
pub fn default_max_length() -> f64 {
    crate::feed_reader::DEFAULT_MAX_LENGTH_MM
}
fn is_default_max_length(v: &f64) -> bool {
    *v == default_max_length()
}
/// Default `max_gap_s`.
pub fn default_max_gap() -> f64 {
    2.0
}
fn is_default_max_gap(v: &f64) -> bool {
    *v == default_max_gap()
}

impl ReportConfig {
    /// A report of `standard` into `out` with every other option at its default.
    pub fn new(standard: Standard, out: PathBuf) -> ReportConfig {
        ReportConfig {
            standard,
            out,
            deflection_gauge: None,
            cmod_gauge: None,
            smooth_points: default_smooth(),
            response: Response::default(),
            load_resolution_kn: None,
            max_load_kn: default_max_load(),
            max_length_mm: default_max_length(),
            max_gap_s: default_max_gap(),
            pdf: true,
            lab: LabInfo::default(),
            method: None,
        }
    }

    /// The physical ranges of the feed's values.
    pub fn limits(&self) -> crate::feed_reader::Limits {
        crate::feed_reader::Limits { max_load_kn: self.max_load_kn, max_length_mm: self.max_length_mm }
    }

    /// Checks `[report]` (keys relative to it) against the specimen's geometry. It needs the
    /// beam because a report computes stresses from `[specimen.beam]`, which lives outside
    /// `[report]`: without it there is no report, and EN 14651 needs the beam's notch.
    pub fn validate_with(&self, beam: Option<&BeamConfig>) -> Result<(), Problem> {
        let Some(beam) = beam else {
            return Err(Problem::new(
                "standard",
                "a report needs the specimen's geometry: add [specimen.beam] with width_mm, depth_mm, span_mm",
            ));
        };
        if self.standard == Standard::En14651 && beam.notch_mm.is_none() {
            return Err(Problem::new("standard", "EN 14651 tests notched beams: give [specimen.beam] notch_mm"));
        }
        self.validate_options()
    }

    /// Checks `[report]`'s own options (keys relative to it), the geometry aside: a test
    /// folder's report checks the geometry once the test's measured dimensions are in.
    pub fn validate_options(&self) -> Result<(), Problem> {
        if self.out.as_os_str().is_empty() {
            return Err(Problem::new("out", "must name a folder"));
        }
        if self.smooth_points == 0 || self.smooth_points.is_multiple_of(2) || self.smooth_points > 101 {
            return Err(Problem::new(
                "smooth_points",
                format!("must be an odd number of points from 1 to 101, got {}", self.smooth_points),
            ));
        }
        if let Some(q) = self.load_resolution_kn {
            if !(q.is_finite() && q >= 0.0) {
                return Err(Problem::new("load_resolution_kn", format!("must be a non-negative load in kN, got {q}")));
            }
        }
        for (k, v) in [("max_load_kn", self.max_load_kn), ("max_length_mm", self.max_length_mm), ("max_gap_s", self.max_gap_s)] {
            if !(v.is_finite() && v > 0.0 && v <= 1e9) {
                return Err(Problem::new(k, format!("must be a positive number up to 1e9, got {v}")));
            }
        }
        self.lab.validate().map_err(|p| p.within("lab"))?;
        Ok(())
    }
}

/// Default smoothing window (points).
pub fn default_smooth() -> usize {
    5
}

fn is_default_smooth(n: &usize) -> bool {
    *n == default_smooth()
}
