//! Frame sources: each produces timestamped [`crate::frame::Frame`]s.
//!
//! # Live cameras
//!
//! Each live camera (`v4l2:`, `aravis:`) runs in its own OS thread, because capture APIs
//! block, and pushes [`SourceEvent`]s into a bounded `tokio::sync::mpsc` channel with
//! `try_send` only: capture never waits for a slow consumer — a full channel drops the frame
//! and counts it ([`DropReason::ChannelFull`], reported as [`SourceEvent::Dropped`] once the
//! channel has room). Incomplete buffers are counted and never delivered. A camera that
//! disappears is reported ([`SourceEvent::Lost`]) and reopened with backoff while the others
//! go on ([`SourceEvent::Reopened`]). A shared `Arc<AtomicBool>` stop flag ends every thread.
//! [`spawn_camera`] dispatches on the config's `source` prefix and returns once the device is
//! open (the moment to send systemd's READY=1); `sim` cameras are started by the pipeline.
//! Every frame is stamped in ns since the Unix epoch ([`clock`]).

pub mod aravis;
pub use crate::clock;
pub mod convert;
pub mod live;
pub mod sim;
pub mod v4l2;

pub use live::{spawn_camera, CaptureStats, DropReason, LiveCamera, SourceError, SourceEvent, StatsSnapshot};
