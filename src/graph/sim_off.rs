//! The simulated rig's place in a build without the `sim` feature: a simulated camera or UTM
//! is refused (`sim.rs` stands here with the feature).

use std::sync::atomic::AtomicBool;
use std::sync::Arc;

use anyhow::Result;
use tokio::sync::mpsc::Sender;

use tagdeflect_core::camera_config::CameraConfig;
use tagdeflect_io::sources::{LiveCamera, OpenPolicy, SourceError, SourceEvent};
use tagdeflect_io::utm::config::UtmConfig;

use crate::config::Config;

/// No simulated rig in this build.
#[derive(Debug, Clone, Default)]
pub struct Rig;

impl Rig {
    /// Nothing to build.
    pub(crate) fn build(_config: &Config, _wanted: bool) -> Result<Rig, SourceError> {
        Ok(Rig)
    }

    /// A simulated camera is refused.
    pub(crate) fn spawn_camera(
        &self,
        i: usize,
        cam: &CameraConfig,
        _policy: OpenPolicy,
        _tx: Sender<SourceEvent>,
        _stop: Arc<AtomicBool>,
    ) -> Result<LiveCamera, SourceError> {
        Err(SourceError::Open {
            camera: i,
            name: cam.name.clone(),
            spec: "sim".into(),
            message: "this build has no simulated rig: build with the `sim` feature".into(),
        })
    }
}

/// No simulated UTM in this build.
pub(crate) struct SimUtmServer;

/// `ucfg` itself; `address = "sim"` is refused.
pub(crate) async fn polled_utm(ucfg: &UtmConfig, _rig: Option<&Rig>) -> Result<(UtmConfig, SimUtmServer)> {
    if ucfg.address.is_sim() {
        return Err(
            tagdeflect_core::BadInput::new("utm.address = \"sim\": this build has no simulated UTM: build with the `sim` feature").into()
        );
    }
    Ok((ucfg.clone(), SimUtmServer))
}
