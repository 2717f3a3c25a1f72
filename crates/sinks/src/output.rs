//! `[output]`: where `run` and `demo` send what they make.

use serde::{Deserialize, Serialize};
use std::path::PathBuf;

use tagdeflect_core::frame::FrameFormat;

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
    pub mqtt: Option<crate::mqtt::MqttConfig>,
}

fn is_default_format(f: &FrameFormat) -> bool {
    *f == FrameFormat::default()
}

