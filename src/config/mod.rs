//! The configuration file (SPEC "Configuration"): TOML schema, validation with
//! file/line/key errors, and OpenCV calibration import.
//!
//! Parsing happens in two steps: the TOML text is read into *raw* structs that keep
//! the source span of every value that validation may complain about, then
//! [`Config::from_toml_str`] checks the whole file and produces the clean [`Config`]
//! the rest of the program uses. [`Config::to_toml_string`] writes a config back
//! (recordings carry the config in force); it always writes resolved intrinsics, so a
//! recording does not depend on calibration files next to the original config.

use serde::{Deserialize, Serialize};
use std::collections::HashSet;
use std::fmt;
use std::ops::Range;
use std::path::{Path, PathBuf};
use toml::Spanned;

use crate::camera::CameraIntrinsics;

pub mod beam;
pub mod calibration;
pub mod sim;
use crate::frame::FrameFormat;
use crate::tags::TagFamily;
pub use beam::BeamConfig;
pub use calibration::{load_calibration, parse_calibration, CalibrationError};

// Sane ranges of rates and durations: values outside them are typos (1e-20 Hz would make
// a thread wait for 10^12 years; 1e23 ms overflows every timer), refused when loading.
/// Lowest camera frame rate accepted, Hz.
pub const MIN_FPS: f64 = 0.01;
/// Highest camera frame rate accepted, Hz.
pub const MAX_FPS: f64 = 1000.0;
/// Lowest UTM polling rate accepted, Hz.
pub const MIN_POLL_HZ: f64 = 0.01;
/// Highest UTM polling rate accepted, Hz.
pub const MAX_POLL_HZ: f64 = 1000.0;
/// Longest Modbus request timeout accepted, ms.
pub const MAX_TIMEOUT_MS: f64 = 60_000.0;
/// Largest frame-set tolerance accepted, ms.
pub const MAX_TOLERANCE_MS: f64 = 10_000.0;
/// Camera names that would collide with a recording's own files.
pub const RESERVED_NAMES: &[&str] = &["frames.jsonl", "utm.jsonl", "truth.jsonl", "sim_truth.jsonl", "tagdeflect.toml", "feed.jsonl"];

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

/// The whole, validated configuration.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
    /// World orientation.
    #[serde(default)]
    pub world: WorldConfig,
    /// Frame-set assembly.
    #[serde(default)]
    pub sync: SyncConfig,
    /// The cameras, in order (1 to 3 in a typical rig).
    #[serde(rename = "camera")]
    pub cameras: Vec<CameraConfig>,
    /// Tags fixed to the frame or bench: they define the world.
    pub background: BackgroundConfig,
    /// Tags on the beam: what is measured.
    pub specimen: SpecimenConfig,
    /// The testing machine over Modbus TCP (optional).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub utm: Option<UtmConfig>,
    /// Where `run` and `demo` send what they make.
    #[serde(default)]
    pub output: OutputConfig,
    /// The test report `run` writes at its end (optional; see `report`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub report: Option<crate::report::ReportConfig>,
    /// Measurement options (extension of SPEC; all optional).
    #[serde(default)]
    pub measure: MeasureConfig,
    /// Parameters of the built-in simulated rig (extension of SPEC; used by
    /// `source = "sim"` cameras, `utm.address = "sim"` and `simulate`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sim: Option<sim::SimParams>,
    /// Virtual gauges (`[[gauge]]`, see `solve::gauges`).
    #[serde(rename = "gauge", default, skip_serializing_if = "Vec::is_empty")]
    pub gauges: Vec<crate::solve::gauges::GaugeConfig>,
    /// The live clock check (`[clock_check]`, extension; see `solve::clock_offset`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub clock_check: Option<crate::solve::clock_offset::ClockCheckConfig>,
}

/// `[world]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WorldConfig {
    /// World direction that points up (normalised on load); deflection is positive downward.
    pub up: [f64; 3],
}

impl Default for WorldConfig {
    fn default() -> Self {
        Self { up: [0.0, 0.0, 1.0] }
    }
}

/// `[sync]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SyncConfig {
    /// Frames of different cameras closer than this form one frame set.
    pub tolerance_ms: f64,
}

impl Default for SyncConfig {
    fn default() -> Self {
        Self { tolerance_ms: 10.0 }
    }
}

/// One `[[camera]]`, with its intrinsics resolved (inline or from a calibration file).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraConfig {
    /// Camera name; also the recording's sub-folder name.
    pub name: String,
    /// Where the frames come from (`v4l2:/dev/videoN`, `aravis:<device id>`, `sim`,
    /// `recording:<folder>`).
    #[serde(default)]
    pub source: CameraSource,
    /// Requested frame rate of live sources.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fps: Option<f64>,
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Focal length x, pixels.
    pub fx: f64,
    /// Focal length y, pixels.
    pub fy: f64,
    /// Principal point x (OpenCV convention: pixel centres at integers).
    pub cx: f64,
    /// Principal point y.
    pub cy: f64,
    /// OpenCV k1, k2, p1, p2, k3.
    #[serde(default)]
    pub dist: [f64; 5],
    /// Optional fixed pose: rotation vector (Rodrigues), x_cam = R x_world + t.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rvec: Option<[f64; 3]>,
    /// Optional fixed pose: translation in mm.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tvec_mm: Option<[f64; 3]>,
}

fn default_source() -> String {
    "sim".to_string()
}

/// Where a camera's frames come from (`[[camera]] source`). Written back as the same string.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub enum CameraSource {
    /// A V4L2 device, e.g. `v4l2:/dev/v4l/by-id/usb-...-video-index0` (by-id paths survive
    /// replugging; `/dev/videoN` numbers may change).
    V4l2 {
        /// Device path.
        path: String,
    },
    /// A GigE Vision / USB3 Vision camera through Aravis, `aravis:<device id>`.
    Aravis {
        /// Aravis device id (as `arv-tool-0.8` lists it).
        device: String,
    },
    /// The built-in simulated rig (`[sim]`).
    #[default]
    Sim,
    /// The frames of this camera (same name) in a recording folder, played at their recorded
    /// pace as if captured live: `recording:<folder>` (relative to the config's folder).
    /// `replay --realtime` plays every camera this way.
    Recording {
        /// The recording folder.
        dir: PathBuf,
    },
}

impl CameraSource {
    /// Parses a `source` string; the error says what is expected.
    pub fn parse(text: &str) -> Result<CameraSource, String> {
        let t = text.trim();
        let expected = "expected \"v4l2:/dev/videoN\", \"aravis:<device id>\", \"sim\" or \"recording:<folder>\"";
        let nonempty = |rest: &str, what: &str| {
            let r = rest.trim();
            if r.is_empty() {
                Err(format!("\"{t}\" names no {what}: {expected}"))
            } else {
                Ok(r.to_string())
            }
        };
        if let Some(p) = t.strip_prefix("v4l2:") {
            Ok(CameraSource::V4l2 { path: nonempty(p, "device path")? })
        } else if let Some(d) = t.strip_prefix("aravis:") {
            Ok(CameraSource::Aravis { device: nonempty(d, "device id")? })
        } else if t == "sim" {
            Ok(CameraSource::Sim)
        } else if let Some(d) = t.strip_prefix("recording:") {
            Ok(CameraSource::Recording { dir: PathBuf::from(nonempty(d, "folder")?) })
        } else {
            Err(format!("\"{t}\" is not a camera source: {expected}"))
        }
    }

    /// True for the simulated rig.
    pub fn is_sim(&self) -> bool {
        matches!(self, CameraSource::Sim)
    }
}

impl fmt::Display for CameraSource {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            CameraSource::V4l2 { path } => write!(f, "v4l2:{path}"),
            CameraSource::Aravis { device } => write!(f, "aravis:{device}"),
            CameraSource::Sim => write!(f, "sim"),
            CameraSource::Recording { dir } => write!(f, "recording:{}", dir.display()),
        }
    }
}

impl Serialize for CameraSource {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(&self.to_string())
    }
}

impl<'de> Deserialize<'de> for CameraSource {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let text = String::deserialize(d)?;
        CameraSource::parse(&text).map_err(serde::de::Error::custom)
    }
}

impl CameraConfig {
    /// The camera's intrinsic model.
    pub fn intrinsics(&self) -> CameraIntrinsics {
        CameraIntrinsics { width: self.width, height: self.height, fx: self.fx, fy: self.fy, cx: self.cx, cy: self.cy, dist: self.dist }
    }
}

/// `[background]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BackgroundConfig {
    /// Tag family name, e.g. `tag25h9`.
    pub family: TagFamily,
    /// Edge of the black square, mm.
    pub size_mm: f64,
    /// The tags with their world corners.
    #[serde(rename = "tag")]
    pub tags: Vec<BackgroundTag>,
}

/// One background tag at a known world position.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BackgroundTag {
    /// Tag id within the background family.
    pub id: u32,
    /// World corners of the black square: bottom-left, bottom-right, top-right, top-left
    /// as the tag is printed.
    pub corners_mm: [[f64; 3]; 4],
}

/// `[specimen]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SpecimenConfig {
    /// Tag family name, e.g. `tag36h11`.
    pub family: TagFamily,
    /// Edge of the black square, mm.
    pub size_mm: f64,
    /// The tags to measure.
    #[serde(rename = "tag")]
    pub tags: Vec<SpecimenTag>,
    /// `[specimen.beam]`: the specimen's geometry (for the report).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub beam: Option<beam::BeamConfig>,
}

/// One specimen tag.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SpecimenTag {
    /// Tag id within the specimen family.
    pub id: u32,
    /// Optional role for the net deflection.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub role: Option<TagRole>,
}

/// Role of a specimen tag in the net deflection (ASTM C1609 sense).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum TagRole {
    /// Over a support.
    Support,
    /// At midspan.
    Midspan,
}

/// `[utm]`: the testing machine over Modbus TCP.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct UtmConfig {
    /// `host:port`, or `sim` for the built-in simulated UTM.
    pub address: String,
    /// Modbus unit (slave) id.
    #[serde(default = "default_unit")]
    pub unit: u8,
    /// Polling rate, Hz.
    #[serde(default = "default_poll_hz")]
    pub poll_hz: f64,
    /// Per-request timeout, ms (extension; the Modbus client has none of its own).
    #[serde(default = "default_timeout_ms")]
    pub timeout_ms: f64,
    /// The load channel, kN.
    pub load: RegisterConfig,
    /// The stroke channel, mm.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stroke: Option<RegisterConfig>,
}

fn default_unit() -> u8 {
    1
}
fn default_poll_hz() -> f64 {
    50.0
}
fn default_timeout_ms() -> f64 {
    200.0
}

/// One Modbus value: `value = raw * scale + offset`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RegisterConfig {
    /// 0-based register address.
    pub register: u16,
    /// Input or holding register (both only ever read).
    #[serde(default)]
    pub kind: RegisterKind,
    /// Value type.
    #[serde(rename = "type", default)]
    pub value_type: ValueType,
    /// Word order of 32-bit types.
    #[serde(default)]
    pub word_order: WordOrder,
    /// Scale applied to the raw value.
    #[serde(default = "one")]
    pub scale: f64,
    /// Offset added after scaling.
    #[serde(default)]
    pub offset: f64,
}

fn one() -> f64 {
    1.0
}

/// Modbus register table.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum RegisterKind {
    /// Input registers (function 4).
    #[default]
    Input,
    /// Holding registers (function 3), read only.
    Holding,
}

/// Modbus value type.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ValueType {
    /// IEEE 754 single, two registers.
    #[default]
    F32,
    /// Signed 16-bit, one register.
    I16,
    /// Unsigned 16-bit, one register.
    U16,
    /// Signed 32-bit, two registers.
    I32,
    /// Unsigned 32-bit, two registers.
    U32,
}

impl ValueType {
    /// Number of 16-bit registers the type spans.
    pub fn registers(self) -> u16 {
        match self {
            ValueType::I16 | ValueType::U16 => 1,
            _ => 2,
        }
    }
}

/// Byte/word order of 32-bit values, named by the order of bytes A (most significant) .. D.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub enum WordOrder {
    /// Big endian, high word first (`ABCD` or `big`).
    #[default]
    #[serde(rename = "ABCD", alias = "big")]
    Abcd,
    /// Low word first (`CDAB` or `little`).
    #[serde(rename = "CDAB", alias = "little")]
    Cdab,
    /// High word first, bytes swapped in each word.
    #[serde(rename = "BADC")]
    Badc,
    /// Fully little endian.
    #[serde(rename = "DCBA")]
    Dcba,
}

/// `[output]`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OutputConfig {
    /// Append the feed to this file; `-` = stdout.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub feed: Option<String>,
    /// Save a recording of the run in a new timestamped sub-folder of this folder.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub record: Option<PathBuf>,
    /// (extension) How recorded frames are written: `"png"` (default; half the disk) or
    /// `"pgm"` (raw; no CPU spent encoding — for high frame rates on a small box).
    #[serde(default, skip_serializing_if = "is_default_format")]
    pub record_format: FrameFormat,
    /// Serve the live page and endpoints on this address (`IP:PORT`; see `sinks::http`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub http: Option<String>,
    /// `[output.mqtt]`: publish the feed to an MQTT broker (never written back: a
    /// recording carries no broker address or credentials).
    #[serde(default, skip_serializing)]
    pub mqtt: Option<crate::sinks::mqtt::MqttConfig>,
}

fn is_default_format(f: &FrameFormat) -> bool {
    *f == FrameFormat::default()
}

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

// ---------------------------------------------------------------------------------------
// Raw schema: what the TOML says, with spans for validation messages.

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawConfig {
    #[serde(default)]
    world: Option<Spanned<RawWorld>>,
    #[serde(default)]
    sync: Option<RawSync>,
    #[serde(default)]
    camera: Vec<Spanned<RawCamera>>,
    background: Option<Spanned<RawTagSet<RawBackgroundTag>>>,
    specimen: Option<Spanned<RawTagSet<SpecimenTagRaw>>>,
    #[serde(default)]
    utm: Option<Spanned<UtmConfig>>,
    #[serde(default)]
    output: Option<OutputConfig>,
    #[serde(default)]
    report: Option<Spanned<crate::report::ReportConfig>>,
    #[serde(default)]
    measure: Option<Spanned<MeasureConfig>>,
    #[serde(default)]
    sim: Option<sim::SimParams>,
    #[serde(default)]
    gauge: Vec<Spanned<crate::solve::gauges::RawGauge>>,
    #[serde(default)]
    clock_check: Option<Spanned<crate::solve::clock_offset::ClockCheckConfig>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawWorld {
    up: Spanned<[f64; 3]>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawSync {
    tolerance_ms: Spanned<f64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawCamera {
    name: Spanned<String>,
    #[serde(default = "default_source")]
    source: String,
    #[serde(default)]
    fps: Option<Spanned<f64>>,
    width: Option<Spanned<u32>>,
    height: Option<Spanned<u32>>,
    fx: Option<Spanned<f64>>,
    fy: Option<Spanned<f64>>,
    cx: Option<f64>,
    cy: Option<f64>,
    #[serde(default)]
    dist: Option<Spanned<Vec<f64>>>,
    #[serde(default)]
    calibration: Option<Spanned<String>>,
    #[serde(default)]
    rvec: Option<[f64; 3]>,
    #[serde(default)]
    tvec_mm: Option<[f64; 3]>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawTagSet<T> {
    family: Spanned<String>,
    size_mm: Spanned<f64>,
    #[serde(default = "Vec::new")]
    tag: Vec<Spanned<T>>,
    #[serde(default)]
    beam: Option<Spanned<crate::report::config::RawBeam>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawBackgroundTag {
    id: Spanned<u32>,
    corners_mm: Spanned<Vec<Vec<f64>>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct SpecimenTagRaw {
    id: Spanned<u32>,
    #[serde(default)]
    role: Option<TagRole>,
}

/// Turns byte spans into line numbers and builds located errors.
struct Locator<'a> {
    file: &'a Path,
    text: &'a str,
}

impl Locator<'_> {
    fn line(&self, span: Range<usize>) -> usize {
        let end = span.start.min(self.text.len());
        self.text[..end].bytes().filter(|&b| b == b'\n').count() + 1
    }

    /// The span of the line `key = ...` inside a table's span (the value's own line), else the table's.
    fn key_span(&self, table: Range<usize>, key: &str) -> Range<usize> {
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

    fn err(&self, span: Option<Range<usize>>, key: &str, message: impl Into<String>) -> ConfigError {
        ConfigError { file: self.file.to_path_buf(), line: span.map(|s| self.line(s)), key: Some(key.to_string()), message: message.into() }
    }
}

impl Config {
    /// Reads and validates a config file; relative paths are relative to its folder.
    pub fn load(path: &Path) -> Result<Config, ConfigError> {
        let text = read_text_limited(path).map_err(|e| ConfigError {
            file: path.to_path_buf(),
            line: None,
            key: None,
            message: format!("cannot read the config file: {e}"),
        })?;
        Self::from_toml_str(&text, path)
    }

    /// Parses and validates config text. `path` names the file in errors and anchors
    /// relative paths (calibration files).
    pub fn from_toml_str(text: &str, path: &Path) -> Result<Config, ConfigError> {
        let loc = Locator { file: path, text };
        let raw: RawConfig = toml::from_str(text).map_err(|e| toml_error(&loc, &e))?;
        let base = path.parent().unwrap_or(Path::new("."));

        let world = match raw.world {
            None => WorldConfig::default(),
            Some(w) => {
                let up = w.get_ref().up.clone();
                let v = *up.get_ref();
                let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
                if !(n.is_finite() && n > 1e-9) {
                    return Err(loc.err(Some(up.span()), "world.up", "must be a non-zero direction, e.g. [0.0, 0.0, 1.0]"));
                }
                WorldConfig { up: [v[0] / n, v[1] / n, v[2] / n] }
            }
        };

        let sync = match raw.sync {
            None => SyncConfig::default(),
            Some(s) => {
                let t = *s.tolerance_ms.get_ref();
                if !(t.is_finite() && t > 0.0 && t <= MAX_TOLERANCE_MS) {
                    return Err(loc.err(
                        Some(s.tolerance_ms.span()),
                        "sync.tolerance_ms",
                        format!("must be a positive number of milliseconds up to {MAX_TOLERANCE_MS}, got {t}"),
                    ));
                }
                SyncConfig { tolerance_ms: t }
            }
        };

        if raw.camera.is_empty() {
            return Err(loc.err(None, "camera", "at least one [[camera]] is required"));
        }
        let mut cameras = Vec::new();
        let mut names = HashSet::new();
        for (i, cam) in raw.camera.iter().enumerate() {
            let c = resolve_camera(&loc, base, i, cam)?;
            if !names.insert(c.name.clone()) {
                return Err(loc.err(
                    Some(cam.get_ref().name.span()),
                    &format!("camera[{i}].name"),
                    format!("duplicate camera name \"{}\": names must be unique (they are folder names)", c.name),
                ));
            }
            cameras.push(c);
        }

        let bg = raw.background.ok_or_else(|| loc.err(None, "background", "a [background] section is required"))?;
        let background = resolve_background(&loc, bg)?;
        let sp = raw.specimen.ok_or_else(|| loc.err(None, "specimen", "a [specimen] section is required"))?;
        let sp_span = sp.span();
        let specimen = resolve_specimen(&loc, sp)?;
        if specimen.family == background.family {
            if let Some(t) = specimen.tags.iter().find(|t| background.tags.iter().any(|b| b.id == t.id)) {
                return Err(loc.err(
                    Some(sp_span),
                    "specimen.tag.id",
                    format!(
                        "id {} is both a background and a specimen tag of {}: with one family for both, ids must differ",
                        t.id, specimen.family
                    ),
                ));
            }
        }

        let utm = match raw.utm {
            None => None,
            Some(u) => Some(validate_utm(&loc, u)?),
        };
        let measure = match raw.measure {
            None => MeasureConfig::default(),
            Some(m) => {
                let span = m.span();
                let m = m.into_inner();
                if !(m.quad_decimate.is_finite() && m.quad_decimate >= 1.0) {
                    return Err(loc.err(Some(span), "measure.quad_decimate", "must be >= 1.0 (1 = full resolution)"));
                }
                if m.detector_threads == 0 {
                    return Err(loc.err(Some(span), "measure.detector_threads", "must be >= 1"));
                }
                // The detector's own limits, checked here so nothing fails after `check`.
                let opts = crate::detect::DetectorOptions {
                    quad_decimate: m.quad_decimate,
                    nthreads: m.detector_threads,
                    ..crate::detect::DetectorOptions::default()
                };
                if let Err(crate::detect::DetectError::BadOption { name, value, expected }) = opts.validate() {
                    let key = match name {
                        "nthreads" => "measure.detector_threads",
                        "quad_decimate" => "measure.quad_decimate",
                        _ => "measure",
                    };
                    return Err(loc.err(Some(span), key, format!("{value} is out of range: {expected}")));
                }
                if !(m.full_search_interval_s.is_finite() && m.full_search_interval_s > 0.0 && m.full_search_interval_s <= 3600.0) {
                    let span = loc.key_span(span, "full_search_interval_s");
                    return Err(loc.err(
                        Some(span),
                        "measure.full_search_interval_s",
                        format!("must be in (0, 3600] seconds, got {}", m.full_search_interval_s),
                    ));
                }
                if let Err((key, msg)) = crate::solve::DriftConfig::from_measure(&m).validate() {
                    return Err(loc.err(Some(span), &format!("measure.drift_{key}"), msg));
                }
                m
            }
        };
        // [report] (the report's own checks live in report::config).
        let report = match raw.report {
            None => None,
            Some(r) => {
                let span = r.span();
                let mut r = r.into_inner();
                crate::report::config::validate_report(&r, specimen.beam.as_ref())
                    .map_err(|(key, msg)| loc.err(Some(span), &format!("report.{key}"), msg))?;
                if r.out.is_relative() {
                    r.out = base.join(&r.out);
                }
                Some(r)
            }
        };
        let mut output = raw.output.unwrap_or_default();
        if let Some(h) = &output.http {
            crate::sinks::http::parse_addr(h)
                .map_err(|m| loc.err(crate::sinks::http::key_span(text, "output", "http"), "output.http", m))?;
        }
        if let Some(r) = &output.record {
            if r.is_relative() {
                output.record = Some(base.join(r));
            }
        }
        if let Some(f) = &output.feed {
            if f != "-" && Path::new(f).is_relative() {
                output.feed = Some(base.join(f).to_string_lossy().into_owned());
            }
        }
        if let Some(sim) = &raw.sim {
            if let Err(sim::SimParamError { option, message }) = sim.validate() {
                let table = text.find("[sim]").map_or(0..0, |i| i..text.len());
                return Err(loc.err(Some(loc.key_span(table, option)), &format!("sim.{option}"), message));
            }
        }
        // Simulated cameras are the rig's cameras, by name and in order.
        if cameras.iter().any(|c| c.source.is_sim()) {
            let params = raw.sim.clone().unwrap_or_default();
            let names = sim::camera_names(params.cameras as usize);
            for (i, (cam, raw_cam)) in cameras.iter().zip(&raw.camera).enumerate() {
                if cam.source.is_sim() && names.get(i) != Some(&cam.name) {
                    return Err(loc.err(
                        Some(raw_cam.get_ref().name.span()),
                        &format!("camera[{i}].name"),
                        format!(
                            "sim camera {i} is named \"{}\" but the simulated rig's camera {i} is {}: a config with sim cameras lists the rig's cameras ({names:?}) in order",
                            cam.name,
                            names.get(i).map_or("missing (see `[sim] cameras`)".to_string(), |n| format!("\"{n}\""))
                        ),
                    ));
                }
            }
        }
        if let Some(m) = output.mqtt.as_mut() {
            m.validate(base).map_err(|(k, msg)| {
                let at = crate::sinks::mqtt::key_offset(text, k);
                loc.err(at.map(|a| a..a), &format!("output.mqtt.{k}"), msg)
            })?;
        }
        let gauges = crate::solve::gauges::validate_gauges(&raw.gauge, &specimen).map_err(|e| loc.err(e.span, &e.key, e.message))?;
        let clock_check = match raw.clock_check {
            None => None,
            Some(c) => {
                let span = c.span();
                let c = c.into_inner();
                c.validate().map_err(|(k, m)| loc.err(Some(span), &format!("clock_check.{k}"), m))?;
                Some(c)
            }
        };
        Ok(Config { world, sync, cameras, background, specimen, utm, output, report, measure, sim: raw.sim, gauges, clock_check })
    }

    /// Writes the config as TOML (resolved intrinsics inline).
    pub fn to_toml_string(&self) -> String {
        toml::to_string(self).expect("config serialises")
    }

    /// Index of the camera with this name.
    pub fn camera_index(&self, name: &str) -> Option<usize> {
        self.cameras.iter().position(|c| c.name == name)
    }

    /// Role of a specimen tag.
    pub fn role_of(&self, id: u32) -> Option<TagRole> {
        self.specimen.tags.iter().find(|t| t.id == id).and_then(|t| t.role)
    }
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

fn resolve_camera(loc: &Locator<'_>, base: &Path, i: usize, cam: &Spanned<RawCamera>) -> Result<CameraConfig, ConfigError> {
    let span = cam.span();
    let c = cam.get_ref();
    let key = |k: &str| format!("camera[{i}].{k}");
    let name = c.name.get_ref().trim().to_string();
    if name.is_empty() || name.contains(['/', '\\']) || name == "." || name == ".." || name.chars().any(|ch| ch.is_control()) {
        return Err(loc.err(Some(c.name.span()), &key("name"), "must be a non-empty name usable as a folder name (no slashes)"));
    }
    if let Some(f) = RESERVED_NAMES.iter().find(|f| f.eq_ignore_ascii_case(&name)) {
        return Err(loc.err(
            Some(c.name.span()),
            &key("name"),
            format!(
                "\"{name}\" is the name of a recording's own file ({f}): the camera's folder would collide with it; choose another name"
            ),
        ));
    }
    let mut source = CameraSource::parse(&c.source).map_err(|m| loc.err(Some(span.clone()), &key("source"), m))?;
    if let CameraSource::Recording { dir } = &mut source {
        if dir.is_relative() {
            *dir = base.join(&*dir);
        }
    }
    if let Some(f) = &c.fps {
        if !(f.get_ref().is_finite() && (MIN_FPS..=MAX_FPS).contains(f.get_ref())) {
            return Err(loc.err(
                Some(f.span()),
                &key("fps"),
                format!("must be a frame rate from {MIN_FPS} to {MAX_FPS} Hz, got {}", f.get_ref()),
            ));
        }
    }
    let mut intr: Option<CameraIntrinsics> = None;
    if let Some(cal) = &c.calibration {
        if c.fx.is_some() || c.fy.is_some() || c.cx.is_some() || c.cy.is_some() || c.dist.is_some() {
            return Err(loc.err(Some(cal.span()), &key("calibration"), "give either `calibration` or fx/fy/cx/cy/dist, not both"));
        }
        let p = base.join(cal.get_ref());
        intr = Some(load_calibration(&p).map_err(|e| loc.err(Some(cal.span()), &key("calibration"), e.to_string()))?);
    }
    let (width, height) = match (&c.width, &c.height, &intr) {
        (Some(w), Some(h), _) => (*w.get_ref(), *h.get_ref()),
        (None, None, Some(i)) if i.width > 0 && i.height > 0 => (i.width, i.height),
        (None, _, _) => return Err(loc.err(Some(span), &key("width"), "missing: the image width in pixels is required")),
        (_, None, _) => return Err(loc.err(Some(span), &key("height"), "missing: the image height in pixels is required")),
    };
    if width == 0 || height == 0 {
        return Err(loc.err(Some(span), &key("width"), "width and height must be positive"));
    }
    let intr = match intr {
        Some(mut i) => {
            i.width = width;
            i.height = height;
            i
        }
        None => {
            let need = |v: Option<f64>, k: &str| {
                v.ok_or_else(|| {
                    loc.err(Some(span.clone()), &key(k), "missing: give fx, fy, cx, cy (and optionally dist), or `calibration = \"file\"`")
                })
            };
            let fx = need(c.fx.as_ref().map(|v| *v.get_ref()), "fx")?;
            let fy = need(c.fy.as_ref().map(|v| *v.get_ref()), "fy")?;
            let cx = need(c.cx, "cx")?;
            let cy = need(c.cy, "cy")?;
            let mut dist = [0.0; 5];
            if let Some(d) = &c.dist {
                let v = d.get_ref();
                if v.len() > 5 || v.len() < 4 {
                    return Err(loc.err(
                        Some(d.span()),
                        &key("dist"),
                        format!("expected 4 or 5 coefficients [k1, k2, p1, p2, k3], got {}", v.len()),
                    ));
                }
                dist[..v.len()].copy_from_slice(v);
            }
            CameraIntrinsics { width, height, fx, fy, cx, cy, dist }
        }
    };
    for (k, v, sp) in [("fx", intr.fx, c.fx.as_ref().map(|s| s.span())), ("fy", intr.fy, c.fy.as_ref().map(|s| s.span()))] {
        if !(v.is_finite() && v > 0.0) {
            return Err(loc.err(sp.or(Some(span.clone())), &key(k), format!("focal length must be positive, got {v}")));
        }
    }
    if intr.dist.iter().any(|d| !d.is_finite()) || !intr.cx.is_finite() || !intr.cy.is_finite() {
        return Err(loc.err(Some(span), &key("dist"), "intrinsics must be finite numbers"));
    }
    if c.rvec.is_some() != c.tvec_mm.is_some() {
        return Err(loc.err(Some(span), &key("rvec"), "give both `rvec` and `tvec_mm` for a fixed pose, or neither"));
    }
    Ok(CameraConfig {
        name,
        source,
        fps: c.fps.as_ref().map(|f| *f.get_ref()),
        width,
        height,
        fx: intr.fx,
        fy: intr.fy,
        cx: intr.cx,
        cy: intr.cy,
        dist: intr.dist,
        rvec: c.rvec,
        tvec_mm: c.tvec_mm,
    })
}

fn parse_family(loc: &Locator<'_>, section: &str, f: &Spanned<String>) -> Result<TagFamily, ConfigError> {
    f.get_ref().parse::<TagFamily>().map_err(|e| loc.err(Some(f.span()), &format!("{section}.family"), e))
}

fn check_size(loc: &Locator<'_>, section: &str, s: &Spanned<f64>) -> Result<f64, ConfigError> {
    let v = *s.get_ref();
    if !(v.is_finite() && v > 0.0) {
        return Err(loc.err(Some(s.span()), &format!("{section}.size_mm"), format!("must be a positive edge length in mm, got {v}")));
    }
    Ok(v)
}

fn resolve_background(loc: &Locator<'_>, bg: Spanned<RawTagSet<RawBackgroundTag>>) -> Result<BackgroundConfig, ConfigError> {
    let span = bg.span();
    let bg = bg.into_inner();
    if let Some(b) = &bg.beam {
        return Err(loc.err(Some(b.span()), "background.beam", "the beam's geometry belongs in [specimen.beam]"));
    }
    let family = parse_family(loc, "background", &bg.family)?;
    let size_mm = check_size(loc, "background", &bg.size_mm)?;
    if bg.tag.is_empty() {
        return Err(loc.err(Some(span), "background.tag", "at least one [[background.tag]] with world corners is required"));
    }
    let mut ids = HashSet::new();
    let mut tags = Vec::new();
    for (i, t) in bg.tag.iter().enumerate() {
        let t = t.get_ref();
        let key = format!("background.tag[{i}]");
        let id = *t.id.get_ref();
        if !ids.insert(id) {
            return Err(loc.err(Some(t.id.span()), &format!("{key}.id"), format!("duplicate background tag id {id}")));
        }
        if id >= family.code_count() {
            return Err(loc.err(
                Some(t.id.span()),
                &format!("{key}.id"),
                format!("{family} has ids 0..{}, got {id}", family.code_count() - 1),
            ));
        }
        let c = t.corners_mm.get_ref();
        let cspan = Some(t.corners_mm.span());
        if c.len() != 4 || c.iter().any(|p| p.len() != 3) {
            return Err(loc.err(
                cspan,
                &format!("{key}.corners_mm"),
                format!("expected 4 corners of [x, y, z] mm (bottom-left, bottom-right, top-right, top-left), got {} corners", c.len()),
            ));
        }
        let p: Vec<[f64; 3]> = c.iter().map(|p| [p[0], p[1], p[2]]).collect();
        check_square(&p, size_mm).map_err(|m| loc.err(cspan.clone(), &format!("{key}.corners_mm"), m))?;
        tags.push(BackgroundTag { id, corners_mm: [p[0], p[1], p[2], p[3]] });
    }
    Ok(BackgroundConfig { family, size_mm, tags })
}

/// Checks that four world corners form a planar square whose edge matches `size_mm`
/// (within 2 %, so measured positions with small survey errors pass).
fn check_square(p: &[[f64; 3]], size_mm: f64) -> Result<(), String> {
    let v = |a: usize, b: usize| nalgebra::Vector3::new(p[b][0] - p[a][0], p[b][1] - p[a][1], p[b][2] - p[a][2]);
    if p.iter().flatten().any(|x| !x.is_finite()) {
        return Err("corners must be finite numbers".into());
    }
    let edges = [v(0, 1), v(1, 2), v(2, 3), v(3, 0)];
    let lens: Vec<f64> = edges.iter().map(|e| e.norm()).collect();
    if lens.iter().any(|&l| l < 1e-6) {
        return Err("degenerate square: two corners coincide".into());
    }
    let mean = lens.iter().sum::<f64>() / 4.0;
    if lens.iter().any(|&l| (l - mean).abs() > 0.02 * mean) {
        return Err(format!("not a square: edge lengths {:.2?} mm differ", lens));
    }
    let d1 = v(0, 2).norm();
    let d2 = v(1, 3).norm();
    if (d1 - d2).abs() > 0.02 * d1 || (d1 - mean * 2f64.sqrt()).abs() > 0.03 * d1 {
        return Err(format!("not a square: diagonals {d1:.2} and {d2:.2} mm (edges {mean:.2} mm)"));
    }
    let n = edges[0].cross(&edges[1]).normalize();
    if n.dot(&v(0, 3)).abs() > 0.02 * mean {
        return Err("the four corners are not in one plane".into());
    }
    if (mean - size_mm).abs() > 0.02 * size_mm {
        return Err(format!("edge {mean:.2} mm does not match background.size_mm = {size_mm}"));
    }
    Ok(())
}

fn resolve_specimen(loc: &Locator<'_>, sp: Spanned<RawTagSet<SpecimenTagRaw>>) -> Result<SpecimenConfig, ConfigError> {
    let span = sp.span();
    let sp = sp.into_inner();
    let family = parse_family(loc, "specimen", &sp.family)?;
    let size_mm = check_size(loc, "specimen", &sp.size_mm)?;
    if sp.tag.is_empty() {
        return Err(loc.err(Some(span), "specimen.tag", "at least one [[specimen.tag]] is required"));
    }
    let mut ids = HashSet::new();
    let mut tags = Vec::new();
    for (i, t) in sp.tag.iter().enumerate() {
        let t = t.get_ref();
        let id = *t.id.get_ref();
        if !ids.insert(id) {
            return Err(loc.err(Some(t.id.span()), &format!("specimen.tag[{i}].id"), format!("duplicate specimen tag id {id}")));
        }
        if id >= family.code_count() {
            return Err(loc.err(
                Some(t.id.span()),
                &format!("specimen.tag[{i}].id"),
                format!("{family} has ids 0..{}, got {id}", family.code_count() - 1),
            ));
        }
        tags.push(SpecimenTag { id, role: t.role });
    }
    let beam = match &sp.beam {
        None => None,
        Some(b) => Some(b.get_ref().resolve().map_err(|(span, key, msg)| loc.err(Some(span), &format!("specimen.beam.{key}"), msg))?),
    };
    Ok(SpecimenConfig { family, size_mm, tags, beam })
}

fn validate_utm(loc: &Locator<'_>, u: Spanned<UtmConfig>) -> Result<UtmConfig, ConfigError> {
    let span = Some(u.span());
    let u = u.into_inner();
    if u.address != "sim" && u.address.parse::<std::net::SocketAddr>().is_err() && !u.address.contains(':') {
        return Err(loc.err(span, "utm.address", format!("\"{}\" is not host:port (e.g. \"192.0.2.10:502\") or \"sim\"", u.address)));
    }
    let table = span.clone().unwrap_or(0..0);
    if !(u.poll_hz.is_finite() && (MIN_POLL_HZ..=MAX_POLL_HZ).contains(&u.poll_hz)) {
        return Err(loc.err(
            Some(loc.key_span(table.clone(), "poll_hz")),
            "utm.poll_hz",
            format!("must be from {MIN_POLL_HZ} to {MAX_POLL_HZ} Hz, got {}", u.poll_hz),
        ));
    }
    if !(u.timeout_ms.is_finite() && u.timeout_ms >= 1.0 && u.timeout_ms <= MAX_TIMEOUT_MS) {
        return Err(loc.err(
            Some(loc.key_span(table, "timeout_ms")),
            "utm.timeout_ms",
            format!("must be from 1 to {MAX_TIMEOUT_MS} milliseconds, got {}", u.timeout_ms),
        ));
    }
    for (name, r) in [("load", Some(&u.load)), ("stroke", u.stroke.as_ref())] {
        if let Some(r) = r {
            if !(r.scale.is_finite() && r.offset.is_finite()) || r.scale == 0.0 {
                return Err(loc.err(
                    span.clone(),
                    &format!("utm.{name}.scale"),
                    "scale must be a non-zero finite number and offset finite",
                ));
            }
            if r.register as u32 + r.value_type.registers() as u32 > 65536 {
                return Err(loc.err(span.clone(), &format!("utm.{name}.register"), "register address out of range"));
            }
        }
    }
    Ok(u)
}
