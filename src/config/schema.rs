//! The schema: the clean, validated configuration the rest of the program uses, as serde
//! structs with their defaults. Every struct here is what [`super::Config::load`] hands out
//! after validation (see `validate.rs`); it is also what [`super::Config::to_toml_string`]
//! writes into a recording, so a field's `skip_serializing_if` keeps old recordings' configs
//! as they were.
//!
//! The `[specimen.beam]` table is [`super::beam::BeamConfig`], the `[sim]` table
//! [`super::sim::SimParams`]; tables of other components (`[report]`, `[output.mqtt]`,
//! `[[gauge]]`, `[clock_check]`) have their structs beside their component.

use serde::{Deserialize, Serialize};
use std::fmt;
use std::path::PathBuf;

use crate::camera::CameraIntrinsics;
use crate::frame::FrameFormat;
use crate::tags::TagFamily;

use super::beam;

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
    pub sim: Option<super::sim::SimParams>,
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

impl Config {
    /// Index of the camera with this name.
    pub fn camera_index(&self, name: &str) -> Option<usize> {
        self.cameras.iter().position(|c| c.name == name)
    }

    /// Role of a specimen tag.
    pub fn role_of(&self, id: u32) -> Option<TagRole> {
        self.specimen.tags.iter().find(|t| t.id == id).and_then(|t| t.role)
    }
}
