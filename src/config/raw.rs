//! The file as written: every section in the form its component reads (`…Section` types
//! where a section is resolved — cameras, tag sets, gauges —, the clean type elsewhere), and
//! the TOML parse that locates a syntax or type error by line and key.

use serde::Deserialize;
use std::path::Path;

use tagdeflect_core::camera_config::CameraSection;
use tagdeflect_core::rig::{BackgroundSection, SpecimenSection, WorldConfig};
use tagdeflect_core::verification::VerificationConfig;
use tagdeflect_estimate::clock_offset::ClockCheckConfig;
use tagdeflect_estimate::gauges::GaugeSection;
use tagdeflect_estimate::measure_config::MeasureConfig;
use tagdeflect_io::sync::SyncConfig;
use tagdeflect_io::utm::config::UtmConfig;
use tagdeflect_report::ReportConfig;
use tagdeflect_sinks::output::OutputConfig;

use super::{ConfigError, SimSection};

/// The whole file as written.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawConfig {
    #[serde(default)]
    pub(super) world: Option<WorldConfig>,
    #[serde(default)]
    pub(super) sync: Option<SyncConfig>,
    #[serde(default)]
    pub(super) camera: Vec<CameraSection>,
    pub(super) background: Option<BackgroundSection>,
    pub(super) specimen: Option<SpecimenSection>,
    #[serde(default)]
    pub(super) utm: Option<UtmConfig>,
    #[serde(default)]
    pub(super) output: Option<OutputConfig>,
    #[serde(default)]
    pub(super) report: Option<ReportConfig>,
    #[serde(default)]
    pub(super) measure: Option<MeasureConfig>,
    #[serde(default)]
    pub(super) sim: Option<SimSection>,
    #[serde(default)]
    pub(super) gauge: Vec<GaugeSection>,
    #[serde(default)]
    pub(super) clock_check: Option<ClockCheckConfig>,
    #[serde(default)]
    pub(super) verification: Option<VerificationConfig>,
}

/// Parses the text into its raw form; a TOML syntax or type error is located by line and key.
pub(super) fn parse(text: &str, path: &Path) -> Result<RawConfig, ConfigError> {
    toml::from_str(text).map_err(|e| toml_error(text, path, &e))
}

fn line_of(text: &str, at: usize) -> usize {
    let end = at.min(text.len());
    text[..end].bytes().filter(|&b| b == b'\n').count() + 1
}

fn toml_error(text: &str, path: &Path, e: &toml::de::Error) -> ConfigError {
    // toml's message already says what is wrong; add the location and the key.
    let msg = e.message().trim().to_string();
    let key = field_in_message(&msg).or_else(|| e.span().and_then(|s| key_on_line(text, s.start)));
    ConfigError { file: path.to_path_buf(), line: e.span().map(|s| line_of(text, s.start)), key, message: msg }
}
/// The field named by serde's "unknown field `x`" / "missing field `x`" / "duplicate field `x`".
fn field_in_message(msg: &str) -> Option<String> {
    let rest = ["unknown field `", "missing field `", "duplicate field `"].iter().find_map(|p| msg.find(p).map(|i| &msg[i + p.len()..]))?;
    Some(rest[..rest.find('`')?].to_string())
}

/// The `key` of a `key = value` line holding byte offset `at`.
fn key_on_line(text: &str, at: usize) -> Option<String> {
    let at = at.min(text.len());
    let start = text[..at].rfind('\n').map_or(0, |i| i + 1);
    let line = text[start..].lines().next()?;
    let (k, _) = line.split_once('=')?;
    let k = k.trim().trim_matches('"');
    (!k.is_empty() && k.chars().all(|c| c.is_ascii_alphanumeric() || "_-.".contains(c))).then(|| k.to_string())
}
