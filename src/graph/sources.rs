//! Every camera of a config, started: the one place that builds the sources (V4L2, Aravis,
//! a recording played at its pace, the simulated rig's cameras).

use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::Duration;

use tokio::sync::mpsc::Sender;

use tagdeflect_core::camera_config::CameraSource;
use tagdeflect_io::sources::playback as player;
use tagdeflect_io::sources::{spawn_capture, spawn_device, Backoff, LiveCamera, LoopTiming, OpenPolicy, SourceError, SourceEvent};

use crate::config::Config;
use crate::config::Recording;

use crate::graph::playback::PacedUtm;
use crate::graph::sim::Rig;

/// A recording played by its cameras' players: the recording, their shared playhead and the
/// UTM samples they hand over with their frames (a replay's).
type Played = (Arc<Recording>, Arc<player::Playhead>, Option<Arc<std::sync::Mutex<player::UtmInStep>>>);

/// Every camera of a config, started.
#[derive(Debug)]
pub struct Sources {
    /// The cameras, in config order.
    pub cameras: Vec<LiveCamera>,
    /// The simulated rig, when a camera or the UTM is simulated (the simulated UTM server
    /// reads its load from it).
    pub rig: Rig,
}

impl Sources {
    /// Waits for every capture thread to end (set the stop flag first).
    pub fn join(self) {
        for c in self.cameras {
            c.join();
        }
    }
}

/// Whether the config asks for the simulated rig: a `sim` camera, or `utm.address = "sim"`
/// unless the cameras play a recording (a replay takes its UTM samples from the recording).
pub fn wants_rig(config: &Config) -> bool {
    let replaying = config.cameras.iter().any(|c| matches!(c.source, CameraSource::Recording { .. }));
    config.cameras.iter().any(|c| c.source.is_sim()) || (!replaying && config.utm.as_ref().is_some_and(|u| u.address.is_sim()))
}

/// Starts every camera of `config` (see the module doc). Returns once each device is open —
/// or, with [`OpenPolicy::Retry`], once each device is open or being retried. The simulated
/// rig's clock starts now. `recorded_utm`: a replay's UTM stream, handed over by the players
/// of its recording with their frames ([`player::UtmInStep`]).
pub fn start(
    config: &Config,
    policy: OpenPolicy,
    tx: Sender<SourceEvent>,
    stop: Arc<AtomicBool>,
    mut recorded_utm: Option<PacedUtm>,
) -> Result<Sources, SourceError> {
    let rig = Rig::build(config, wants_rig(config))?;
    let mut recordings: HashMap<PathBuf, Played> = HashMap::new();
    let mut cameras = Vec::with_capacity(config.cameras.len());
    let fail = |cameras: Vec<LiveCamera>, stop: &AtomicBool, e: SourceError| {
        stop.store(true, std::sync::atomic::Ordering::SeqCst);
        for c in cameras {
            c.join();
        }
        Err(e)
    };
    for (i, cam) in config.cameras.iter().enumerate() {
        let started = match &cam.source {
            CameraSource::V4l2 { .. } | CameraSource::Aravis { .. } => spawn_device(i, cam, policy, tx.clone(), stop.clone()),
            CameraSource::Sim => rig.spawn_camera(i, cam, policy, tx.clone(), stop.clone()),
            CameraSource::Recording { dir } => {
                let entry = match recordings.get(dir) {
                    Some(e) => Ok(e.clone()),
                    None => Recording::open_with(dir, config.clone()).map(|rec| {
                        let utm = recorded_utm.take().map(|u| player::UtmInStep::new(&rec, u.tx, u.sent));
                        let rec = Arc::new(rec);
                        let e = (rec.clone(), player::Playhead::start(&*rec), utm);
                        recordings.insert(dir.clone(), e.clone());
                        e
                    }),
                };
                match entry {
                    Err(e) => {
                        Err(SourceError::Open { camera: i, name: cam.name.clone(), spec: cam.source.to_string(), message: e.to_string() })
                    }
                    Ok((rec, playhead, utm)) => {
                        let name = cam.name.clone();
                        let session = player::RecordingSession::new(&rec, playhead, &name);
                        let mut session = Some(match utm {
                            Some(u) => session.with_utm(u),
                            None => session,
                        });
                        // A recording is played once: a "reopen" has nothing more to give.
                        let open = move || session.take().ok_or_else(|| "played out".to_string());
                        // Gaps in a recording are not a lost camera.
                        let timing = LoopTiming { stall: Duration::from_secs(365 * 24 * 3600), backoff: Backoff::default() };
                        spawn_capture(i, &cam.name, cam.source.to_string(), open, timing, OpenPolicy::Require, tx.clone(), stop.clone())
                    }
                }
            }
        };
        match started {
            Ok(c) => cameras.push(c),
            Err(e) => return fail(cameras, &stop, e),
        }
    }
    Ok(Sources { cameras, rig })
}
