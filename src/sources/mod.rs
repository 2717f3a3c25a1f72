//! Frame sources: each produces timestamped [`crate::frame::Frame`]s.
//!
//! # One capture seam
//!
//! Every camera — V4L2, Aravis, the simulated rig, a recording played at its pace — runs in
//! its own OS thread through the same capture loop ([`live::run_capture_loop`]) behind the
//! same [`live::CaptureSession`] trait, and pushes [`SourceEvent`]s into one bounded
//! `tokio::sync::mpsc` channel with `try_send` only: capture never waits for a slow consumer —
//! a full channel drops the frame and counts it ([`DropReason::ChannelFull`], reported as
//! [`SourceEvent::Dropped`] once the channel has room). Frames land in recycled buffers
//! ([`crate::frame::ImagePool`]). Incomplete buffers are counted and never delivered. A
//! camera that disappears is reported ([`SourceEvent::Lost`]) and reopened with backoff while
//! the others go on ([`SourceEvent::Reopened`]). A shared `Arc<AtomicBool>` stop flag ends
//! every thread; a recording's camera ends by itself when its frames are played out.
//!
//! [`start`] starts every camera of a config (`run`, `record`, `demo`, `check --config`,
//! `replay --realtime`, `bench --realtime`). Every frame is stamped on the process clock
//! ([`crate::clock`]).
//!
//! `replay` and `bench` read a recording as fast as they can instead, through
//! [`crate::recording::Recording::frames`] — the same frames, without the pacing.

pub mod aravis;
pub use crate::clock;
pub mod convert;
pub mod live;
pub mod recording;
pub mod sim;
pub mod v4l2;

use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::Duration;

use tokio::sync::mpsc::Sender;

pub use live::{CaptureStats, DropReason, LiveCamera, OpenPolicy, SourceError, SourceEvent, StatsSnapshot};

use crate::config::{CameraConfig, CameraSource, Config};
use crate::recording::Recording;
use live::{spawn_capture, Backoff, LoopTiming};

/// Every camera of a config, started.
#[derive(Debug)]
pub struct Sources {
    /// The cameras, in config order.
    pub cameras: Vec<LiveCamera>,
    /// The simulated rig, when a camera or the UTM is simulated (the simulated UTM server
    /// reads its load from it).
    pub rig: Option<Arc<sim::LiveRig>>,
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
    config.cameras.iter().any(|c| c.source.is_sim()) || (!replaying && config.utm.as_ref().is_some_and(|u| u.address == "sim"))
}

/// Starts every camera of `config` (see the module doc). Returns once each device is open —
/// or, with [`OpenPolicy::Retry`], once each device is open or being retried. The simulated
/// rig's clock starts now.
pub fn start(config: &Config, policy: OpenPolicy, tx: Sender<SourceEvent>, stop: Arc<AtomicBool>) -> Result<Sources, SourceError> {
    let rig = if wants_rig(config) {
        let rig = sim::LiveRig::new(config, clock::now_epoch_ns()).map_err(|e| SourceError::Open {
            camera: 0,
            name: "sim".into(),
            spec: "sim".into(),
            message: format!("cannot build the simulated rig: {e}"),
        })?;
        Some(Arc::new(rig))
    } else {
        None
    };
    let mut recordings: HashMap<PathBuf, (Arc<Recording>, Arc<recording::Playhead>)> = HashMap::new();
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
            CameraSource::Sim => {
                let rig = rig.clone().expect("the rig is built when a camera is simulated");
                let mut session = Some(sim::SimSession::new(rig.clone(), i));
                let open = move || Ok::<_, String>(session.take().unwrap_or_else(|| sim::SimSession::new(rig.clone(), i)));
                spawn_capture(i, &cam.name, "sim".into(), open, LoopTiming::for_fps(cam.fps), policy, tx.clone(), stop.clone())
            }
            CameraSource::Recording { dir } => {
                let entry = match recordings.get(dir) {
                    Some(e) => Ok(e.clone()),
                    None => Recording::open_with(dir, config.clone()).map(|rec| {
                        let rec = Arc::new(rec);
                        let e = (rec.clone(), recording::Playhead::start(&rec));
                        recordings.insert(dir.clone(), e.clone());
                        e
                    }),
                };
                match entry {
                    Err(e) => {
                        Err(SourceError::Open { camera: i, name: cam.name.clone(), spec: cam.source.to_string(), message: e.to_string() })
                    }
                    Ok((rec, playhead)) => {
                        let name = cam.name.clone();
                        let mut session = Some(recording::RecordingSession::new(rec, playhead, &name));
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

/// Starts a live device camera in its own thread and returns once the device is open and
/// configured, or with the error that prevented it ([`OpenPolicy::Require`]: `check`,
/// tests). The pipeline starts every kind of source with [`crate::sources::start`].
///
/// `v4l2:` ([`crate::sources::v4l2`]) and `aravis:` ([`crate::sources::aravis`]) sources;
/// `sim` and `recording:` sources need the rig or the recording that
/// [`crate::sources::start`] holds, and give [`SourceError::Sim`].
pub fn spawn_camera(index: usize, cfg: &CameraConfig, tx: Sender<SourceEvent>, stop: Arc<AtomicBool>) -> Result<LiveCamera, SourceError> {
    spawn_device(index, cfg, OpenPolicy::Require, tx, stop)
}

/// [`spawn_camera`] with a policy for a device that is not there yet.
pub fn spawn_device(
    index: usize,
    cfg: &CameraConfig,
    policy: OpenPolicy,
    tx: Sender<SourceEvent>,
    stop: Arc<AtomicBool>,
) -> Result<LiveCamera, SourceError> {
    match &cfg.source {
        CameraSource::V4l2 { path } => v4l2::spawn(index, cfg, path, policy, tx, stop),
        CameraSource::Aravis { device } => aravis::spawn_with(index, cfg, device, aravis::AravisOptions::default(), policy, tx, stop),
        CameraSource::Sim | CameraSource::Recording { .. } => Err(SourceError::Sim { camera: index, name: cfg.name.clone() }),
    }
}
