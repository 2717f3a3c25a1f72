//! Reading a feed for the report: every SPEC field plus the optional extensions the report
//! uses (`gauges`, per-tag `sigma_mm`, camera health, UTM state, drops); any other field is
//! kept for the QC section (drift, stale poses, clock offset, ...).

use serde::Deserialize;
use std::collections::BTreeMap;
use std::io::Read;
use std::path::{Path, PathBuf};

use super::ReportError;

/// One gauge's reading in a feed line (`{"value", "sigma", "unit"}`).
#[derive(Debug, Clone, PartialEq, Deserialize)]
pub struct GaugeReading {
    /// The gauge's value.
    pub value: f64,
    /// Its 1-σ uncertainty (absent when the feed does not give it).
    #[serde(default)]
    pub sigma: Option<f64>,
    /// Its unit, e.g. `mm`.
    #[serde(default)]
    pub unit: Option<String>,
}

/// One solved specimen tag of a feed line.
#[derive(Debug, Clone, PartialEq, Deserialize)]
pub struct TagReading {
    /// Tag id.
    pub id: u32,
    /// Displacement since the tag's first solved frame set, mm.
    pub disp_mm: [f64; 3],
    /// Cameras that saw it.
    #[serde(default)]
    pub views: usize,
    /// 1-σ of the position along x, y, z, mm.
    #[serde(default)]
    pub sigma_mm: Option<[f64; 3]>,
}

/// A camera's health in a feed line (the fields the QC section uses; the rest kept).
#[derive(Debug, Clone, PartialEq, Deserialize)]
pub struct CameraReading {
    /// Camera name.
    pub name: String,
    /// The camera contributed a frame.
    #[serde(default = "yes")]
    pub frame: bool,
    /// The camera has a pose.
    #[serde(default = "yes")]
    pub posed: bool,
    /// Found moved and re-posed in this frame set.
    #[serde(default)]
    pub bumped: bool,
    /// Any other field (drift, stale pose, ...).
    #[serde(flatten)]
    pub extra: serde_json::Map<String, serde_json::Value>,
}

fn yes() -> bool {
    true
}

/// One feed line as the report reads it.
#[derive(Debug, Clone, PartialEq, Deserialize)]
pub struct FeedRecord {
    /// Frame-set number.
    pub seq: u64,
    /// Frame-set time, ns since the Unix epoch.
    pub t_ns: i64,
    /// Load, kN.
    #[serde(rename = "load_kN", default)]
    pub load_kn: Option<f64>,
    /// Stroke, mm.
    #[serde(default)]
    pub stroke_mm: Option<f64>,
    /// Solved specimen tags.
    #[serde(default)]
    pub tags: Vec<TagReading>,
    /// Net deflection, mm.
    #[serde(default)]
    pub net_deflection_mm: Option<f64>,
    /// Gauges by name.
    #[serde(default)]
    pub gauges: BTreeMap<String, GaugeReading>,
    /// Camera health.
    #[serde(default)]
    pub cameras: Vec<CameraReading>,
    /// UTM link state: "ok" / "down".
    #[serde(default)]
    pub utm: Option<String>,
    /// Frame sets dropped so far by the live pipeline.
    #[serde(default)]
    pub dropped_sets: Option<u64>,
    /// Every other field.
    #[serde(flatten)]
    pub extra: serde_json::Map<String, serde_json::Value>,
}

/// A whole feed file.
#[derive(Debug, Clone)]
pub struct Feed {
    /// Where it was read from.
    pub path: PathBuf,
    /// The lines in time order.
    pub lines: Vec<FeedRecord>,
    /// Warnings from reading (a truncated last line).
    pub warnings: Vec<String>,
}

impl Feed {
    /// Reads a feed (JSON Lines). A truncated last line (no newline, cut JSON — what a
    /// writer killed mid-line leaves) is skipped with a warning, as the recording reader
    /// does; any other bad line is an error naming the file and line.
    pub fn read(path: &Path) -> Result<Feed, ReportError> {
        let mut text = String::new();
        std::fs::File::open(path)
            .and_then(|mut f| f.read_to_string(&mut text))
            .map_err(|e| ReportError::Io { path: path.to_path_buf(), message: format!("cannot read the feed: {e}") })?;
        Self::parse(&text, path)
    }

    /// Parses feed text; `path` names the file in errors.
    pub fn parse(text: &str, path: &Path) -> Result<Feed, ReportError> {
        let ends_with_newline = text.ends_with('\n');
        let raw: Vec<&str> = text.lines().collect();
        let mut lines = Vec::with_capacity(raw.len());
        let mut warnings = Vec::new();
        for (i, line) in raw.iter().enumerate() {
            if line.trim().is_empty() {
                continue;
            }
            match serde_json::from_str::<FeedRecord>(line) {
                Ok(r) => lines.push(r),
                Err(e) => {
                    if i + 1 == raw.len() && !ends_with_newline && e.is_eof() {
                        let msg = format!("{}:{}: truncated last line skipped", path.display(), i + 1);
                        tracing::warn!("{msg}");
                        warnings.push(msg);
                    } else {
                        return Err(ReportError::BadLine { path: path.to_path_buf(), line: i + 1, message: e.to_string() });
                    }
                }
            }
        }
        if lines.is_empty() {
            return Err(ReportError::BadLine { path: path.to_path_buf(), line: raw.len().max(1), message: "the feed has no lines".into() });
        }
        lines.sort_by_key(|l| l.t_ns);
        Ok(Feed { path: path.to_path_buf(), lines, warnings })
    }

    /// Gauge names in order of first appearance.
    pub fn gauge_names(&self) -> Vec<String> {
        let mut names: Vec<String> = Vec::new();
        for l in &self.lines {
            for k in l.gauges.keys() {
                if !names.contains(k) {
                    names.push(k.clone());
                }
            }
        }
        names
    }

    /// The unit of a gauge (from its first reading that names one).
    pub fn gauge_unit(&self, name: &str) -> Option<String> {
        self.lines.iter().find_map(|l| l.gauges.get(name).and_then(|g| g.unit.clone()))
    }

    /// Tag ids seen, sorted.
    pub fn tag_ids(&self) -> Vec<u32> {
        let mut ids: Vec<u32> = self.lines.iter().flat_map(|l| l.tags.iter().map(|t| t.id)).collect();
        ids.sort_unstable();
        ids.dedup();
        ids
    }
}
