//! Raw values with their locations: reading the file (at most [`MAX_CONFIG_BYTES`]), the TOML
//! parse into *raw* structs that keep the source span of every value validation may complain
//! about, and the [`Locator`] that turns spans into `file:line: `key`` errors
//! ([`ConfigError`]).

use serde::Deserialize;
use std::fmt;
use std::ops::Range;
use std::path::{Path, PathBuf};
use toml::Spanned;

use super::sim::SimParams;
use super::{MeasureConfig, OutputConfig, TagRole, UtmConfig};

/// Largest config or calibration file read, bytes (real ones are a few kB).
pub const MAX_CONFIG_BYTES: u64 = 16 << 20;

/// Reads a text file of at most [`MAX_CONFIG_BYTES`].
pub(crate) fn read_text_limited(path: &Path) -> std::io::Result<String> {
    use std::io::Read;
    let f = std::fs::File::open(path)?;
    let mut text = String::new();
    f.take(MAX_CONFIG_BYTES + 1).read_to_string(&mut text)?;
    if text.len() as u64 > MAX_CONFIG_BYTES {
        return Err(std::io::Error::other(format!("larger than {MAX_CONFIG_BYTES} bytes: not a config file")));
    }
    Ok(text)
}

/// Reads a config file; the error names the file.
pub(super) fn read(path: &Path) -> Result<String, ConfigError> {
    read_text_limited(path).map_err(|e| ConfigError {
        file: path.to_path_buf(),
        line: None,
        key: None,
        message: format!("cannot read the config file: {e}"),
    })
}

/// A configuration problem, located in its file.
#[derive(Debug, thiserror::Error)]
pub struct ConfigError {
    /// The file the problem is in.
    pub file: PathBuf,
    /// 1-based line, when known.
    pub line: Option<usize>,
    /// Dotted key path, e.g. `camera[1].name`.
    pub key: Option<String>,
    /// What is wrong and what is expected.
    pub message: String,
}

impl fmt::Display for ConfigError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}", self.file.display())?;
        if let Some(line) = self.line {
            write!(f, ":{line}")?;
        }
        if let Some(key) = &self.key {
            write!(f, ": `{key}`")?;
        }
        write!(f, ": {}", self.message)
    }
}

fn default_source() -> String {
    "sim".to_string()
}

/// The whole file as written: every table, spans kept where validation reports them.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawConfig {
    #[serde(default)]
    pub(super) world: Option<Spanned<RawWorld>>,
    #[serde(default)]
    pub(super) sync: Option<RawSync>,
    #[serde(default)]
    pub(super) camera: Vec<Spanned<RawCamera>>,
    pub(super) background: Option<Spanned<RawTagSet<RawBackgroundTag>>>,
    pub(super) specimen: Option<Spanned<RawTagSet<SpecimenTagRaw>>>,
    #[serde(default)]
    pub(super) utm: Option<Spanned<UtmConfig>>,
    #[serde(default)]
    pub(super) output: Option<OutputConfig>,
    #[serde(default)]
    pub(super) report: Option<Spanned<crate::report::ReportConfig>>,
    #[serde(default)]
    pub(super) measure: Option<Spanned<MeasureConfig>>,
    #[serde(default)]
    pub(super) sim: Option<SimParams>,
    #[serde(default)]
    pub(super) gauge: Vec<Spanned<crate::solve::gauges::RawGauge>>,
    #[serde(default)]
    pub(super) clock_check: Option<Spanned<crate::solve::clock_offset::ClockCheckConfig>>,
}

/// `[world]` as written.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawWorld {
    pub(super) up: Spanned<[f64; 3]>,
}

/// `[sync]` as written.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawSync {
    pub(super) tolerance_ms: Spanned<f64>,
}

/// One `[[camera]]` as written: inline intrinsics or a calibration file, checked later.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawCamera {
    pub(super) name: Spanned<String>,
    #[serde(default = "default_source")]
    pub(super) source: String,
    #[serde(default)]
    pub(super) fps: Option<Spanned<f64>>,
    pub(super) width: Option<Spanned<u32>>,
    pub(super) height: Option<Spanned<u32>>,
    pub(super) fx: Option<Spanned<f64>>,
    pub(super) fy: Option<Spanned<f64>>,
    pub(super) cx: Option<f64>,
    pub(super) cy: Option<f64>,
    #[serde(default)]
    pub(super) dist: Option<Spanned<Vec<f64>>>,
    #[serde(default)]
    pub(super) calibration: Option<Spanned<String>>,
    #[serde(default)]
    pub(super) rvec: Option<[f64; 3]>,
    #[serde(default)]
    pub(super) tvec_mm: Option<[f64; 3]>,
}

/// `[background]` or `[specimen]` as written.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawTagSet<T> {
    pub(super) family: Spanned<String>,
    pub(super) size_mm: Spanned<f64>,
    #[serde(default = "Vec::new")]
    pub(super) tag: Vec<Spanned<T>>,
    #[serde(default)]
    pub(super) beam: Option<Spanned<crate::report::config::RawBeam>>,
}

/// One `[[background.tag]]` as written.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawBackgroundTag {
    pub(super) id: Spanned<u32>,
    pub(super) corners_mm: Spanned<Vec<Vec<f64>>>,
}

/// One `[[specimen.tag]]` as written.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct SpecimenTagRaw {
    pub(super) id: Spanned<u32>,
    #[serde(default)]
    pub(super) role: Option<TagRole>,
}

/// Turns byte spans into line numbers and builds located errors.
pub(super) struct Locator<'a> {
    pub(super) file: &'a Path,
    pub(super) text: &'a str,
}

impl Locator<'_> {
    /// The 1-based line where `span` starts.
    pub(super) fn line(&self, span: Range<usize>) -> usize {
        let end = span.start.min(self.text.len());
        self.text[..end].bytes().filter(|&b| b == b'\n').count() + 1
    }

    /// The span of the line `key = ...` inside a table's span (the value's own line), else the table's.
    pub(super) fn key_span(&self, table: Range<usize>, key: &str) -> Range<usize> {
        let end = table.end.min(self.text.len());
        let start = table.start.min(end);
        let mut at = start;
        for line in self.text[start..end].split_inclusive('\n') {
            let t = line.trim_start();
            if t.strip_prefix(key).is_some_and(|r| r.trim_start().starts_with('=')) {
                return at..at + line.len();
            }
            at += line.len();
        }
        table
    }

    /// An error at `span` (its line), naming `key`.
    pub(super) fn err(&self, span: Option<Range<usize>>, key: &str, message: impl Into<String>) -> ConfigError {
        ConfigError { file: self.file.to_path_buf(), line: span.map(|s| self.line(s)), key: Some(key.to_string()), message: message.into() }
    }
}

/// Parses the text into its raw form; a TOML syntax or type error is located by line and key.
pub(super) fn parse(loc: &Locator<'_>) -> Result<RawConfig, ConfigError> {
    toml::from_str(loc.text).map_err(|e| toml_error(loc, &e))
}

fn toml_error(loc: &Locator<'_>, e: &toml::de::Error) -> ConfigError {
    // toml's message already says what is wrong; add the location and the key.
    let msg = e.message().trim().to_string();
    let key = field_in_message(&msg).or_else(|| e.span().and_then(|s| key_on_line(loc.text, s.start)));
    ConfigError { file: loc.file.to_path_buf(), line: e.span().map(|s| loc.line(s)), key, message: msg }
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
