//! The simulated rig in the graph (the `sim` feature; without it `sim_off.rs` stands here and
//! refuses it): its cameras (`source = "sim"`) and its UTM (`utm.address = "sim"`, served on
//! loopback from the rig's load and polled like a real one). One rig per run, its clock
//! started with the sources.

use std::sync::atomic::AtomicBool;
use std::sync::Arc;

use anyhow::{Context, Result};
use tokio::sync::mpsc::Sender;

use tagdeflect_core::camera_config::CameraConfig;
use tagdeflect_io::sources::{spawn_capture, LiveCamera, LoopTiming, OpenPolicy, SourceError, SourceEvent};
use tagdeflect_io::utm::config::UtmConfig;
use tagdeflect_io::utm::sim_server::{start_sim_utm_with_outage, SimUtm};
use tagdeflect_sim::live_rig::{LiveRig, SimSession};

use crate::config::Config;

/// The run's simulated rig, when a camera or the UTM is simulated.
#[derive(Debug, Clone, Default)]
pub struct Rig(Option<Arc<LiveRig>>);

impl Rig {
    /// The rig `config` asks for (see [`crate::graph::sources::wants_rig`]); its clock starts now.
    pub(crate) fn build(config: &Config, wanted: bool) -> Result<Rig, SourceError> {
        if !wanted {
            return Ok(Rig(None));
        }
        let rig = LiveRig::new(config.sim.as_ref(), tagdeflect_core::clock::now_epoch_ns()).map_err(|e| SourceError::Open {
            camera: 0,
            name: "sim".into(),
            spec: "sim".into(),
            message: format!("cannot build the simulated rig: {e}"),
        })?;
        Ok(Rig(Some(Arc::new(rig))))
    }

    /// Starts camera `i` of the rig.
    pub(crate) fn spawn_camera(
        &self,
        i: usize,
        cam: &CameraConfig,
        policy: OpenPolicy,
        tx: Sender<SourceEvent>,
        stop: Arc<AtomicBool>,
    ) -> Result<LiveCamera, SourceError> {
        let rig = self.0.clone().expect("the rig is built when a camera is simulated");
        let mut session = Some(SimSession::new(rig.clone(), i));
        let open = move || Ok::<_, String>(session.take().unwrap_or_else(|| SimSession::new(rig.clone(), i)));
        spawn_capture(i, &cam.name, "sim".into(), open, LoopTiming::for_fps(cam.fps), policy, tx, stop)
    }
}

/// The simulated UTM's server: it runs while this is held.
pub(crate) struct SimUtmServer(#[allow(dead_code)] Option<SimUtm>);

/// The UTM config to poll: `ucfg` itself, or — for `address = "sim"` — the simulated UTM's
/// server, started here on `rig`.
pub(crate) async fn polled_utm(ucfg: &UtmConfig, rig: Option<&Rig>) -> Result<(UtmConfig, SimUtmServer)> {
    if !ucfg.address.is_sim() {
        return Ok((ucfg.clone(), SimUtmServer(None)));
    }
    let rig = rig.and_then(|r| r.0.clone()).expect("sim rig built");
    let (polled, server) =
        start_sim_utm_with_outage(ucfg, rig.utm_model(), rig.utm_outage()).await.context("cannot start the simulated UTM")?;
    Ok((polled, SimUtmServer(Some(server))))
}
