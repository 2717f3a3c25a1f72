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
}

impl RigInfo {
    /// Index of the camera with this name.
    pub fn camera_index(&self, name: &str) -> Option<usize> {
        self.cameras.iter().position(|c| c.name == name)
    }
}
