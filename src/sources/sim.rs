//! Simulated live cameras (`source = "sim"`) and the built-in demo rig.
//!
//! The scene is the one `simulate` renders ([`crate::sim::SimRig`]), run live: the rig's
//! clock starts at the moment the pipeline starts and the load cycles (up, down, up …) so a
//! demo can run for hours. Each simulated camera is a thread that renders its frame of
//! frame set `k` at the nominal time `start + k / fps` (with the rig's jitter and simulated
//! dropped frames) and sends it like a real camera: `try_send` only, a full channel drops
//! the frame. If rendering falls behind the frame clock, frames are skipped (counted), never
//! queued up, so the demo reflects a real camera's behaviour.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::mpsc;

use crate::config::{Config, UtmConfig};
use crate::frame::Frame;
use crate::sim::{SimError, SimParams, SimRig};
use crate::sources::{clock, SourceEvent};
use crate::utm::sim_server::UtmModel;

/// The simulated rig of a live run.
#[derive(Debug)]
pub struct LiveRig {
    rig: SimRig,
}

impl LiveRig {
    /// Builds the rig from the config's `[sim]` section (defaults when absent), with its
    /// clock starting at `start_ns` and a cyclic load history. The config's cameras must be
    /// the rig's cameras (same count and names), as `demo_config` and `simulate` write them.
    pub fn new(config: &Config, start_ns: i64) -> Result<LiveRig, SimError> {
        let mut params = config.sim.clone().unwrap_or_default();
        params.start_ns = start_ns;
        params.cyclic = true;
        let rig = SimRig::new(&params)?;
        let names: Vec<String> = rig.cameras().into_iter().map(|c| c.name).collect();
        for (i, cam) in config.cameras.iter().enumerate() {
            if cam.source == "sim" && names.get(i) != Some(&cam.name) {
                return Err(SimError::Param {
                    option: "camera",
                    message: format!(
                        "sim camera {i} is named \"{}\" but the simulated rig's camera {i} is {:?}: a config with sim cameras must list the rig's cameras ({names:?}) in order",
                        cam.name,
                        names.get(i)
                    ),
                });
            }
        }
        Ok(LiveRig { rig })
    }

    /// The underlying rig (truth, rendering).
    pub fn rig(&self) -> &SimRig {
        &self.rig
    }

    /// The simulated UTM's outage window (ns since the Unix epoch), if `[sim]` sets one.
    pub fn utm_outage(&self) -> Option<(i64, i64)> {
        self.rig.utm_outage()
    }

    /// The UTM's load and stroke as functions of time, for the simulated Modbus server.
    pub fn utm_model(self: &Arc<Self>) -> UtmModel {
        let me = self.clone();
        Arc::new(move |t_ns| {
            let s = me.rig.utm_sample(t_ns);
            (s.load_kn, s.stroke_mm.unwrap_or(0.0))
        })
    }
}

/// Starts simulated camera `camera` of the rig as a live source.
pub fn spawn_live_camera(
    rig: Arc<LiveRig>,
    camera: usize,
    tx: mpsc::Sender<SourceEvent>,
    stop: Arc<AtomicBool>,
) -> std::thread::JoinHandle<()> {
    std::thread::Builder::new()
        .name(format!("sim-camera-{camera}"))
        .spawn(move || {
            let r = &rig.rig;
            let mut skipped = 0u64;
            let mut full = 0u64;
            let mut k: u64 = 0;
            while !stop.load(Ordering::Relaxed) {
                let due = r.set_time_ns(k);
                let now = clock::now_epoch_ns();
                if due > now {
                    std::thread::sleep(Duration::from_nanos((due - now) as u64).min(Duration::from_millis(200)));
                    continue;
                }
                // Behind the frame clock by more than a frame: skip to the current frame.
                let current = r.set_index_at(now).max(k as i64) as u64;
                if current > k + 1 {
                    skipped += current - k - 1;
                    k = current;
                    continue;
                }
                if let Some(t_ns) = r.frame_time_ns(camera, k) {
                    let image = r.render(camera, t_ns);
                    let frame = Frame { camera, seq: k, t_ns, image: Arc::new(image) };
                    match tx.try_send(SourceEvent::Frame(frame)) {
                        Ok(()) => {}
                        Err(mpsc::error::TrySendError::Full(_)) => full += 1,
                        Err(mpsc::error::TrySendError::Closed(_)) => break,
                    }
                }
                k += 1;
            }
            if skipped + full > 0 {
                tracing::info!(camera, skipped, channel_full = full, "simulated camera: frames not delivered");
            }
        })
        .expect("sim camera thread")
}

/// The built-in demo rig: three simulated 640x480 cameras at 5 fps and a simulated UTM
/// served over Modbus TCP on loopback (f32 load at input register 0, f32 stroke at 2).
/// Sized to keep up on a 2-core machine (rendering and measuring share the cores).
pub fn demo_config() -> Config {
    let params =
        SimParams { cameras: 3, width: 640, height: 480, fps: 5.0, frame_sets: 60, rest_frames: 5, subsamples: 4, ..SimParams::default() };
    let rig = SimRig::new(&params).expect("demo parameters are valid");
    let mut config = rig.config();
    config.utm = Some(UtmConfig {
        address: "sim".into(),
        unit: 1,
        poll_hz: 50.0,
        timeout_ms: 200.0,
        load: crate::config::RegisterConfig {
            register: 0,
            kind: crate::config::RegisterKind::Input,
            value_type: crate::config::ValueType::F32,
            word_order: crate::config::WordOrder::Abcd,
            scale: 1.0,
            offset: 0.0,
        },
        stroke: Some(crate::config::RegisterConfig {
            register: 2,
            kind: crate::config::RegisterKind::Input,
            value_type: crate::config::ValueType::F32,
            word_order: crate::config::WordOrder::Abcd,
            scale: 1.0,
            offset: 0.0,
        }),
    });
    config
}
