//! `[[camera]]`: a camera of the rig — its name, where its frames come from, and its
//! intrinsics (inline, or imported from a calibration file by [`crate::calibration_file`]).

use serde::{Deserialize, Serialize};
use std::fmt;
use std::path::PathBuf;

use crate::camera::CameraIntrinsics;

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
    /// Live cameras: ask for the deepest monochrome format the camera offers (V4L2
    /// `Y16`/`Y12`/`Y10`, GenICam `Mono16`/`Mono12`/`Mono10`) before the 8-bit one, so the
    /// edge fit reads the full depth and recordings keep it (16-bit PNG). Off by default
    /// (8-bit formats first: half the bandwidth).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub full_depth: bool,
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

/// A `source` string that names no camera source.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum CameraSourceError {
    /// A known kind with nothing after its `kind:` prefix.
    #[error("\"{text}\" names no {what}: {EXPECTED_SOURCES}")]
    NamesNothing {
        /// The (trimmed) `source` text.
        text: String,
        /// What the kind needs after its prefix (`device path`, `device id`, `folder`).
        what: &'static str,
    },
    /// Not one of the known kinds.
    #[error("\"{text}\" is not a camera source: {EXPECTED_SOURCES}")]
    NotASource {
        /// The (trimmed) `source` text.
        text: String,
    },
}

/// What a `source` may be, as the errors say it.
const EXPECTED_SOURCES: &str = "expected \"v4l2:/dev/videoN\", \"aravis:<device id>\", \"sim\" or \"recording:<folder>\"";

impl CameraSource {
    /// Parses a `source` string; the error says what is expected.
    pub fn parse(text: &str) -> Result<CameraSource, CameraSourceError> {
        let t = text.trim();
        let nonempty = |rest: &str, what: &'static str| {
            let r = rest.trim();
            if r.is_empty() {
                Err(CameraSourceError::NamesNothing { text: t.to_string(), what })
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
            Err(CameraSourceError::NotASource { text: t.to_string() })
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

/// Lowest camera frame rate accepted, Hz.
pub const MIN_FPS: f64 = 0.01;
/// Highest camera frame rate accepted, Hz.
pub const MAX_FPS: f64 = 1000.0;
/// Camera names that would collide with a recording's own files.
pub const RESERVED_NAMES: &[&str] = &["frames.jsonl", "utm.jsonl", "truth.jsonl", "sim_truth.jsonl", "tagdeflect.toml", "feed.jsonl"];

fn default_source() -> String {
    "sim".to_string()
}

/// One `[[camera]]` as written: inline intrinsics or a calibration file, resolved by
/// [`CameraSection::resolve`] into a [`CameraConfig`].
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraSection {
    /// Camera name.
    pub name: String,
    /// Source string (`v4l2:…`, `aravis:…`, `sim`, `recording:…`).
    #[serde(default = "default_source")]
    pub source: String,
    /// Requested frame rate, Hz.
    #[serde(default)]
    pub fps: Option<f64>,
    /// Image width, px.
    pub width: Option<u32>,
    /// Image height, px.
    pub height: Option<u32>,
    /// Focal length x, px.
    pub fx: Option<f64>,
    /// Focal length y, px.
    pub fy: Option<f64>,
    /// Principal point x, px.
    pub cx: Option<f64>,
    /// Principal point y, px.
    pub cy: Option<f64>,
    /// k1, k2, p1, p2[, k3].
    #[serde(default)]
    pub dist: Option<Vec<f64>>,
    /// A calibration file (OpenCV, Kalibr, ROS), relative to the config's folder.
    #[serde(default)]
    pub calibration: Option<String>,
    /// Fixed pose: rotation vector.
    #[serde(default)]
    pub rvec: Option<[f64; 3]>,
    /// Fixed pose: translation, mm.
    #[serde(default)]
    pub tvec_mm: Option<[f64; 3]>,
    /// Deepest monochrome format first (see [`CameraConfig::full_depth`]).
    #[serde(default)]
    pub full_depth: bool,
}

impl CameraSection {
    /// Checks the camera and resolves its intrinsics (inline, or from its calibration file
    /// relative to `base`); a relative `recording:` folder is taken relative to `base` too.
    /// Problems name keys relative to the camera's table.
    pub fn resolve(&self, base: &std::path::Path) -> Result<CameraConfig, crate::Problem> {
        use crate::Problem;
        let name = self.name.trim().to_string();
        // A name is a folder name, a metric label, an MQTT topic level and text on the live
        // page: letters, digits, `_`, `-`, `.` only, so that no name is markup, a path or a
        // topic wildcard wherever it lands.
        let allowed = |ch: char| ch.is_alphanumeric() || matches!(ch, '_' | '-' | '.');
        if name.is_empty() || name.chars().count() > 64 || name.starts_with('.') || !name.chars().all(allowed) {
            return Err(Problem::new(
                "name",
                format!(
                    "\"{}\" is not a camera name: 1 to 64 letters, digits, `_`, `-` and `.` (not first), usable as a folder name",
                    self.name.escape_debug()
                ),
            ));
        }
        if let Some(f) = RESERVED_NAMES.iter().find(|f| f.eq_ignore_ascii_case(&name)) {
            return Err(Problem::new(
                "name",
                format!("\"{name}\" is the name of a recording's own file ({f}): the camera's folder would collide with it; choose another name"),
            ));
        }
        let mut source = CameraSource::parse(&self.source).map_err(|e| Problem::new("source", e.to_string()))?;
        if let CameraSource::Recording { dir } = &mut source {
            if dir.is_relative() {
                *dir = base.join(&*dir);
            }
        }
        if let Some(f) = self.fps {
            if !(f.is_finite() && (MIN_FPS..=MAX_FPS).contains(&f)) {
                return Err(Problem::new("fps", format!("must be a frame rate from {MIN_FPS} to {MAX_FPS} Hz, got {f}")));
            }
        }
        let mut intr: Option<CameraIntrinsics> = None;
        if let Some(cal) = &self.calibration {
            if self.fx.is_some() || self.fy.is_some() || self.cx.is_some() || self.cy.is_some() || self.dist.is_some() {
                return Err(Problem::new("calibration", "give either `calibration` or fx/fy/cx/cy/dist, not both"));
            }
            let p = base.join(cal);
            intr = Some(crate::calibration_file::load_calibration(&p).map_err(|e| Problem::new("calibration", e.to_string()))?);
        }
        let (width, height) = match (self.width, self.height, &intr) {
            (Some(w), Some(h), _) => (w, h),
            (None, None, Some(i)) if i.width > 0 && i.height > 0 => (i.width, i.height),
            (None, _, _) => return Err(Problem::new("width", "missing: the image width in pixels is required")),
            (_, None, _) => return Err(Problem::new("height", "missing: the image height in pixels is required")),
        };
        if width == 0 || height == 0 {
            return Err(Problem::new("width", "width and height must be positive"));
        }
        let intr = match intr {
            Some(i) if i.width > 0 && i.height > 0 && (i.width, i.height) != (width, height) => {
                return Err(Problem::new(
                    "calibration",
                    format!(
                        "{} was made for {}x{} px images; this camera is {width}x{height}: intrinsics of another image size measure wrongly. Calibrate at the camera's resolution",
                        self.calibration.as_deref().unwrap_or_default(),
                        i.width,
                        i.height
                    ),
                ));
            }
            Some(mut i) => {
                i.width = width;
                i.height = height;
                i
            }
            None => {
                let need = |v: Option<f64>, k: &str| {
                    v.ok_or_else(|| Problem::new(k, "missing: give fx, fy, cx, cy (and optionally dist), or `calibration = \"file\"`"))
                };
                let fx = need(self.fx, "fx")?;
                let fy = need(self.fy, "fy")?;
                let cx = need(self.cx, "cx")?;
                let cy = need(self.cy, "cy")?;
                let mut dist = [0.0; 5];
                if let Some(v) = &self.dist {
                    if v.len() > 5 || v.len() < 4 {
                        return Err(Problem::new("dist", format!("expected 4 or 5 coefficients [k1, k2, p1, p2, k3], got {}", v.len())));
                    }
                    dist[..v.len()].copy_from_slice(v);
                }
                CameraIntrinsics { width, height, fx, fy, cx, cy, dist }
            }
        };
        for (k, v) in [("fx", intr.fx), ("fy", intr.fy)] {
            if !(v.is_finite() && v > 0.0) {
                return Err(Problem::new(k, format!("focal length must be positive, got {v}")));
            }
        }
        if intr.dist.iter().any(|d| !d.is_finite()) || !intr.cx.is_finite() || !intr.cy.is_finite() {
            return Err(Problem::new("dist", "intrinsics must be finite numbers"));
        }
        if self.rvec.is_some() != self.tvec_mm.is_some() {
            return Err(Problem::new("rvec", "give both `rvec` and `tvec_mm` for a fixed pose, or neither"));
        }
        Ok(CameraConfig {
            name,
            source,
            fps: self.fps,
            width,
            height,
            fx: intr.fx,
            fy: intr.fy,
            cx: intr.cx,
            cy: intr.cy,
            dist: intr.dist,
            rvec: self.rvec,
            tvec_mm: self.tvec_mm,
            full_depth: self.full_depth,
        })
    }
}

/// Checks a rig's cameras as a whole: at least one, names unique. Keys are `camera[i]…`.
pub fn resolve_cameras(sections: &[CameraSection], base: &std::path::Path) -> Result<Vec<CameraConfig>, crate::Problem> {
    use crate::Problem;
    if sections.is_empty() {
        return Err(Problem::new("camera", "at least one [[camera]] is required"));
    }
    let mut cameras: Vec<CameraConfig> = Vec::new();
    for (i, s) in sections.iter().enumerate() {
        let c = s.resolve(base).map_err(|p| p.within(&format!("camera[{i}]")))?;
        if cameras.iter().any(|o| o.name == c.name) {
            return Err(Problem::new(
                format!("camera[{i}].name"),
                format!("duplicate camera name \"{}\": names must be unique (they are folder names)", c.name),
            ));
        }
        cameras.push(c);
    }
    Ok(cameras)
}
