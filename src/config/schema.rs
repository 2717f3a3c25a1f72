//! The whole configuration: one field per section, each section's type owned by the
//! component that uses it. It is what [`super::Config::load`] hands out after validation,
//! and what [`super::Config::to_toml_string`] writes into a recording, so a field's
//! `skip_serializing_if` keeps old recordings' configs as they were.

use serde::{Deserialize, Serialize};

use tagdeflect_core::camera_config::CameraConfig;
use tagdeflect_core::rig::{BackgroundConfig, SpecimenConfig, TagRole, WorldConfig};
use tagdeflect_estimate::clock_offset::ClockCheckConfig;
use tagdeflect_estimate::gauges::GaugeConfig;
use tagdeflect_estimate::measure_config::MeasureConfig;
use tagdeflect_io::sync::SyncConfig;
use tagdeflect_io::utm::config::UtmConfig;
use tagdeflect_report::ReportConfig;
use tagdeflect_sinks::output::OutputConfig;

/// `[sim]` as this build takes it: the simulated rig's parameters with the `sim` feature;
/// without it the table is kept as written (a recording made from the simulated rig still
/// replays; `source = "sim"` and `utm.address = "sim"` are refused at load).
#[cfg(feature = "sim")]
pub type SimSection = tagdeflect_sim::SimParams;
/// `[sim]` as this build takes it (built without the `sim` feature): kept as written.
#[cfg(not(feature = "sim"))]
pub type SimSection = toml::Table;

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
    pub report: Option<ReportConfig>,
    /// Measurement options (extension of SPEC; all optional).
    #[serde(default)]
    pub measure: MeasureConfig,
    /// Parameters of the built-in simulated rig (extension of SPEC; used by
    /// `source = "sim"` cameras, `utm.address = "sim"` and `simulate`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sim: Option<SimSection>,
    /// Virtual gauges (`[[gauge]]`, see `tagdeflect_estimate::gauges`).
    #[serde(rename = "gauge", default, skip_serializing_if = "Vec::is_empty")]
    pub gauges: Vec<GaugeConfig>,
    /// The live clock check (`[clock_check]`, extension; see `tagdeflect_estimate::clock_offset`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub clock_check: Option<ClockCheckConfig>,
}

impl Config {
    /// Index of the camera with this name.
    pub fn camera_index(&self, name: &str) -> Option<usize> {
        self.cameras.iter().position(|c| c.name == name)
    }

    /// Role of a specimen tag.
    pub fn role_of(&self, id: u32) -> Option<TagRole> {
        self.specimen.role_of(id)
    }

    /// What the measurement is built from.
    pub fn measurement(&self) -> tagdeflect_estimate::measure::MeasurementConfig {
        tagdeflect_estimate::measure::MeasurementConfig {
            world: self.world.clone(),
            cameras: self.cameras.clone(),
            background: self.background.clone(),
            specimen: self.specimen.clone(),
            measure: self.measure.clone(),
            gauges: self.gauges.clone(),
            clock_check: self.clock_check.clone(),
            utm_poll_hz: self.utm.as_ref().map(|u| u.poll_hz),
        }
    }

    /// What the live page, the metrics and the MQTT status show of the rig.
    pub fn rig_info(&self) -> tagdeflect_sinks::RigInfo {
        tagdeflect_sinks::RigInfo {
            cameras: self.cameras.clone(),
            world: self.world.clone(),
            specimen: self.specimen.clone(),
            utm: self.utm.as_ref().map(|u| u.address.clone()),
        }
    }

    /// What the report needs of the rig.
    pub fn test_rig(&self) -> tagdeflect_report::TestRig {
        tagdeflect_report::TestRig { world: self.world.clone(), specimen: self.specimen.clone(), gauges: self.gauges.clone() }
    }
}

impl tagdeflect_io::recording::RecordedConfig for Config {
    type Error = super::ConfigError;
    fn load(path: &std::path::Path) -> Result<Self, Self::Error> {
        Config::load(path)
    }
    fn cameras(&self) -> &[CameraConfig] {
        &self.cameras
    }
    fn to_toml_string(&self) -> String {
        Config::to_toml_string(self)
    }
}
