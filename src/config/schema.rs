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
