//! What the sinks know of the rig: its cameras, its world's up direction, its specimen tags
//! and the UTM's address — built by the binary from the config, never the whole config.

use tagdeflect_core::camera_config::CameraConfig;
use tagdeflect_core::rig::{SpecimenConfig, WorldConfig};
use tagdeflect_io::utm::config::UtmAddress;

/// The rig as the live page, the metrics and the MQTT status describe it.
#[derive(Debug, Clone, PartialEq)]
pub struct RigInfo {
    /// The cameras, in config order.
    pub cameras: Vec<CameraConfig>,
    /// `[world]`.
    pub world: WorldConfig,
    /// `[specimen]`.
    pub specimen: SpecimenConfig,
    /// `utm.address`, when a UTM is configured.
    pub utm: Option<UtmAddress>,
    /// The CMOD gauge, when the rig has one (the page's load–CMOD curve, EN 14651's rate).
    pub cmod_gauge: Option<String>,
    /// Per standard (`astm-c1609`, `astm-c1856`, `en-14651`): its deflection-rate windows for
    /// this beam as the report judges them (`{"split_mm", "below_mm_per_min": [lo, hi],
    /// "above_mm_per_min": [lo, hi]}`); empty without `[specimen.beam]`.
    pub rate_windows: std::collections::BTreeMap<String, serde_json::Value>,
}

impl RigInfo {
    /// Index of the camera with this name.
    pub fn camera_index(&self, name: &str) -> Option<usize> {
        self.cameras.iter().position(|c| c.name == name)
    }
}
