//! Frame sources: each produces timestamped [`tagdeflect_core::frame::Frame`]s.
//!
//! # One capture seam
//!
//! Every camera — V4L2, Aravis, the simulated rig, a recording played at its pace — runs in
//! its own OS thread through the same capture loop ([`capture::run_capture_loop`]) behind the
//! same [`capture::CaptureSession`] trait, and pushes [`SourceEvent`]s into one bounded
//! `tokio::sync::mpsc` channel with `try_send` only: capture never waits for a slow consumer —
//! a full channel drops the frame and counts it ([`DropReason::ChannelFull`], reported as
//! [`SourceEvent::Dropped`] once the channel has room). Frames land in recycled buffers
//! ([`tagdeflect_core::frame::ImagePool`]). Incomplete buffers are counted and never delivered. A
//! camera that disappears is reported ([`SourceEvent::Lost`]) and reopened with backoff while
//! the others go on ([`SourceEvent::Reopened`]). A shared `Arc<AtomicBool>` stop flag ends
//! every thread; a recording's camera ends by itself when its frames are played out.
//!
//! The binary's graph starts every camera of a config (`run`, `record`, `demo`, `check --config`,
//! `replay --realtime`, `bench --realtime`). Every frame is stamped on the process clock
//! ([`tagdeflect_core::clock`]).
//!
//! A plain `replay` (and `bench`) reads a recording as fast as it can instead, through
//! `Recording::frames` — the same frames, without the pacing, handed over in time order
//! (the graph's `Pacing::AsFast`). [`list`] says which cameras the machine can see.

#[cfg(feature = "aravis")]
pub mod aravis;
pub use tagdeflect_core::clock;
pub mod capture;
pub mod convert;
pub mod list;
pub mod playback;
pub mod v4l2;

use std::sync::atomic::AtomicBool;
use std::sync::Arc;

use tokio::sync::mpsc::Sender;

pub use capture::{CaptureStats, DropReason, LiveCamera, OpenPolicy, SourceError, SourceEvent, StatsSnapshot};

pub use capture::{spawn_capture, Backoff, LoopTiming};
use tagdeflect_core::camera_config::{CameraConfig, CameraSource};

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
        #[cfg(feature = "aravis")]
        CameraSource::Aravis { device } => aravis::spawn_with(index, cfg, device, aravis::AravisOptions::default(), policy, tx, stop),
        #[cfg(not(feature = "aravis"))]
        CameraSource::Aravis { .. } => Err(SourceError::Open {
            camera: index,
            name: cfg.name.clone(),
            spec: cfg.source.to_string(),
            message: "this build has no Aravis support: build with the `aravis` feature".into(),
        }),
        CameraSource::Sim | CameraSource::Recording { .. } => Err(SourceError::Sim { camera: index, name: cfg.name.clone() }),
    }
}
