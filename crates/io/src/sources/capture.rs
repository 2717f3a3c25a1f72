//! Live cameras: one OS thread per camera pushing [`SourceEvent`]s into a bounded tokio
//! channel, the shared capture machinery (drop counting, reconnect backoff, statistics) and
//! the capture seam every camera uses ([`CaptureSession`], [`spawn_capture`], [`run_capture_loop`]).
//!
//! Capture APIs (V4L2 `DQBUF`, Aravis `timeout_pop_buffer`) block, so each camera owns a
//! thread. The thread only ever `try_send`s: when the channel is full the frame is dropped
//! and counted ([`DropReason::ChannelFull`]) — capture never waits for a slow consumer. Drop
//! counts and connection events that could not be delivered are kept and delivered before
//! the next frame. A shared `stop` flag ends every camera thread within about half a second;
//! a closed channel (receiver dropped) ends it too.
//!
//! Devices plug in through [`CaptureSession`] (one bounded wait → one [`Captured`]); the
//! common [`run_capture_loop`] does the rest: delivery, counting, loss detection (a failure,
//! or no complete frame for [`LoopTiming::stall`]) and reopening with [`Backoff`].

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Duration;

use tokio::sync::mpsc::Sender;

pub use tagdeflect_core::backoff::Backoff;
use tagdeflect_core::frame::Frame;

mod emitter;
pub(crate) use emitter::Emitter;

/// What a live camera reports to the pipeline.
#[derive(Debug, Clone)]
pub enum SourceEvent {
    /// A captured, complete, converted frame, stamped in ns since the Unix epoch.
    Frame(Frame),
    /// The camera stopped delivering (unplugged, read error, stalled); reopening with backoff.
    Lost {
        /// Index of the camera in the config.
        camera: usize,
        /// What went wrong, for the log and the feed's camera health.
        reason: String,
    },
    /// The camera is streaming again after [`SourceEvent::Lost`].
    Reopened {
        /// Index of the camera in the config.
        camera: usize,
    },
    /// Frames that were captured (or half-captured) but not delivered, since the last report.
    Dropped {
        /// Index of the camera in the config.
        camera: usize,
        /// Frames dropped for this reason since the last report.
        count: u64,
        /// Why they were dropped.
        why: DropReason,
    },
}

/// Why a frame was not delivered.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum DropReason {
    /// The pipeline's channel was full (the consumer is behind).
    ChannelFull,
    /// The driver/transport delivered an incomplete or failed buffer (missing packets,
    /// timeout, size mismatch, aborted); never fed to the detector.
    Incomplete,
    /// The buffer was complete but could not be converted (truncated, undecodable, wrong size).
    BadBuffer,
}

/// Errors opening a live source (the thread's later failures are [`SourceEvent::Lost`]).
#[derive(Debug, thiserror::Error)]
pub enum SourceError {
    /// Simulated and recorded cameras are not devices.
    #[error("camera {camera} ({name}): sim and recording cameras are started by sources::start, not by sources::spawn_camera")]
    Sim {
        /// Camera index.
        camera: usize,
        /// Camera name.
        name: String,
    },
    /// The device could not be opened or configured.
    #[error("camera {camera} ({name}) at {spec:?}: {message}")]
    Open {
        /// Camera index.
        camera: usize,
        /// Camera name.
        name: String,
        /// The source string.
        spec: String,
        /// What failed.
        message: String,
    },
    /// The capture thread could not be started.
    #[error("camera {camera} ({name}): cannot start the capture thread: {message}")]
    Thread {
        /// Camera index.
        camera: usize,
        /// Camera name.
        name: String,
        /// What failed.
        message: String,
    },
}

/// Counters of one live camera, readable from any thread while it runs.
#[derive(Debug, Default)]
pub struct CaptureStats {
    /// Frames delivered to the channel.
    pub delivered: AtomicU64,
    /// Frames dropped because the channel was full.
    pub dropped_full: AtomicU64,
    /// Buffers that arrived incomplete or failed (never delivered).
    pub incomplete: AtomicU64,
    /// Complete buffers that failed conversion.
    pub bad_buffers: AtomicU64,
    /// Times the camera was lost.
    pub lost: AtomicU64,
    /// Times the camera was reopened after being lost.
    pub reopened: AtomicU64,
}

impl CaptureStats {
    /// A snapshot `(delivered, dropped_full, incomplete, bad_buffers, lost, reopened)`.
    pub fn snapshot(&self) -> StatsSnapshot {
        StatsSnapshot {
            delivered: self.delivered.load(Ordering::Relaxed),
            dropped_full: self.dropped_full.load(Ordering::Relaxed),
            incomplete: self.incomplete.load(Ordering::Relaxed),
            bad_buffers: self.bad_buffers.load(Ordering::Relaxed),
            lost: self.lost.load(Ordering::Relaxed),
            reopened: self.reopened.load(Ordering::Relaxed),
        }
    }
}

/// A plain copy of [`CaptureStats`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct StatsSnapshot {
    /// Frames delivered to the channel.
    pub delivered: u64,
    /// Frames dropped because the channel was full.
    pub dropped_full: u64,
    /// Buffers that arrived incomplete or failed.
    pub incomplete: u64,
    /// Complete buffers that failed conversion.
    pub bad_buffers: u64,
    /// Times the camera was lost.
    pub lost: u64,
    /// Times the camera was reopened.
    pub reopened: u64,
}

/// A running live camera: its thread and its counters.
#[derive(Debug)]
pub struct LiveCamera {
    /// The capture thread; it ends when the stop flag is set or the channel closes.
    pub thread: JoinHandle<()>,
    /// Its counters.
    pub stats: Arc<CaptureStats>,
}

impl LiveCamera {
    /// Waits for the capture thread to end (set the stop flag first).
    pub fn join(self) {
        if self.thread.join().is_err() {
            tracing::error!("a camera capture thread panicked");
        }
    }
}

/// What to do when a device cannot be opened at start.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum OpenPolicy {
    /// Fail with the error (`check --config`: the operator is told at once).
    Require,
    /// Report the camera lost and keep trying to open it with backoff in its capture thread
    /// (`run`: a camera switched on or plugged in after the daemon started joins then).
    Retry,
}

/// Starts the capture thread of camera `index`: the device is opened inside the thread
/// with `open` (capture handles stay on the thread that made them), readiness is reported
/// back, then [`run_capture_loop`] runs (reopening with `open` after a loss). Returns once
/// the device is open, or with the error that prevented it.
#[allow(clippy::too_many_arguments)]
pub fn spawn_capture<S, F, E>(
    index: usize,
    name: &str,
    source: String,
    mut open: F,
    timing: LoopTiming,
    policy: OpenPolicy,
    tx: Sender<SourceEvent>,
    stop: Arc<AtomicBool>,
) -> Result<LiveCamera, SourceError>
where
    S: CaptureSession,
    F: FnMut() -> Result<S, E> + Send + 'static,
    E: std::fmt::Display + Send + 'static,
{
    let stats = Arc::new(CaptureStats::default());
    let (ready_tx, ready_rx) = std::sync::mpsc::sync_channel::<Result<(), E>>(1);
    let thread_stats = stats.clone();
    let label = source.clone();
    let prefix = source.split(':').next().unwrap_or("camera").to_string();
    let thread = std::thread::Builder::new()
        .name(format!("{prefix}-{name}"))
        .spawn(move || {
            let mut em = Emitter::new(index, tx, thread_stats);
            let session = match open() {
                Ok(s) => {
                    let _ = ready_tx.send(Ok(()));
                    Some(s)
                }
                Err(e) if policy == OpenPolicy::Retry => {
                    // Not there yet: reported, and opened by the loop as soon as it appears.
                    let _ = ready_tx.send(Ok(()));
                    em.lost(format!("{label}: cannot open: {e}; retrying"));
                    None
                }
                Err(e) => {
                    let _ = ready_tx.send(Err(e));
                    return;
                }
            };
            run_capture_loop(&mut em, &label, session, open, timing, &stop);
        })
        .map_err(|e| SourceError::Thread { camera: index, name: name.to_string(), message: e.to_string() })?;
    let name = name.to_string();
    match ready_rx.recv() {
        Ok(Ok(())) => Ok(LiveCamera { thread, stats }),
        Ok(Err(e)) => {
            let _ = thread.join();
            Err(SourceError::Open { camera: index, name, spec: source, message: e.to_string() })
        }
        Err(_) => {
            let _ = thread.join();
            Err(SourceError::Thread { camera: index, name, message: "capture thread ended while opening".into() })
        }
    }
}

/// Sleeps up to `d` in short steps; returns `false` if `stop` was set meanwhile.
pub(crate) fn sleep_unless_stopped(d: Duration, stop: &AtomicBool) -> bool {
    let step = Duration::from_millis(50);
    let mut left = d;
    while !left.is_zero() {
        if stop.load(Ordering::Relaxed) {
            return false;
        }
        let s = left.min(step);
        std::thread::sleep(s);
        left -= s;
    }
    !stop.load(Ordering::Relaxed)
}

/// What one wait on an open device produced.
#[derive(Debug)]
pub enum Captured {
    /// A complete image, converted into the buffer given to [`CaptureSession::next`], and
    /// its time (ns since the epoch).
    Image(i64),
    /// A buffer the driver/transport marked incomplete or failed (why, for the debug log).
    Incomplete(String),
    /// A complete buffer that could not be converted (why).
    Bad(String),
    /// Nothing arrived within the device's wait time.
    Timeout,
    /// The device failed (unplugged, I/O error): it is closed and reopened.
    Failed(String),
    /// The source has no more frames (a recording played out): the capture thread ends.
    End,
}

/// An open, streaming device as the capture loop sees it.
pub trait CaptureSession {
    /// Waits (boundedly, so the stop flag is seen) for the next buffer; a complete image is
    /// converted into `into` (a recycled frame buffer: see [`tagdeflect_core::frame::ImagePool`]).
    fn next(&mut self, into: &mut tagdeflect_core::frame::GrayImage) -> Captured;
    /// Frames the transport lost entirely since the last call (no buffer was free).
    fn take_missed(&mut self) -> u64 {
        0
    }
}

/// The capture loop's timing.
#[derive(Debug, Clone)]
pub struct LoopTiming {
    /// No complete frame for this long: the camera is reported lost and reopened.
    pub stall: Duration,
    /// Delays between reopen attempts.
    pub backoff: Backoff,
}

impl LoopTiming {
    /// `max(2 s, 10 frame periods)` stall time (100 ms period without `fps`), default backoff.
    pub fn for_fps(fps: Option<f64>) -> Self {
        let period = fps.filter(|f| *f > 0.0 && f.is_finite()).map_or(Duration::from_millis(100), |f| Duration::from_secs_f64(1.0 / f));
        Self { stall: (period * 10).max(Duration::from_secs(2)), backoff: Backoff::default() }
    }
}

/// The body of every live camera thread: delivers frames from `session`, counts incomplete
/// and bad buffers, reports the device lost on failure or stall, reopens it with `open`
/// after backoff delays, and ends when `stop` is set or the channel closes. `label` names the
/// device in messages. `seq` counts complete frames across reopenings.
pub(crate) fn run_capture_loop<S: CaptureSession, E: std::fmt::Display>(
    em: &mut Emitter,
    label: &str,
    session: Option<S>,
    mut open: impl FnMut() -> Result<S, E>,
    mut timing: LoopTiming,
    stop: &AtomicBool,
) {
    let camera = em.camera();
    let mut session = session;
    let mut seq: u64 = 0;
    let mut last_frame = std::time::Instant::now();
    let mut pool = tagdeflect_core::frame::ImagePool::default();
    while !stop.load(Ordering::Relaxed) && !em.is_closed() {
        let Some(s) = session.as_mut() else {
            if !sleep_unless_stopped(timing.backoff.next_delay(), stop) {
                break;
            }
            match open() {
                Ok(s) => {
                    session = Some(s);
                    timing.backoff.reset();
                    last_frame = std::time::Instant::now();
                    em.reopened();
                }
                Err(e) => tracing::debug!(camera, error = %e, "reopen failed"),
            }
            continue;
        };
        // The image lands in a recycled buffer: a steady stream allocates no frames.
        let mut t_ns = 0;
        let got = pool.fill(|img| match s.next(img) {
            Captured::Image(t) => {
                t_ns = t;
                Ok(())
            }
            other => Err(other),
        });
        let missed = s.take_missed();
        if missed > 0 {
            em.dropped(DropReason::Incomplete, missed);
        }
        match got {
            Ok(image) => {
                last_frame = std::time::Instant::now();
                em.frame(Frame { camera, seq, t_ns, image });
                seq += 1;
            }
            // Images are the `Ok` above.
            Err(Captured::Image(_)) => {}
            Err(Captured::Incomplete(why)) => {
                tracing::debug!(camera, %why, "incomplete buffer");
                em.dropped(DropReason::Incomplete, 1);
            }
            Err(Captured::Bad(why)) => {
                tracing::debug!(camera, %why, "bad buffer");
                em.dropped(DropReason::BadBuffer, 1);
            }
            Err(Captured::Timeout) => em.flush(),
            Err(Captured::Failed(why)) => {
                em.lost(format!("{label}: {why}"));
                session = None;
                continue;
            }
            Err(Captured::End) => break,
        }
        if last_frame.elapsed() > timing.stall {
            em.lost(format!("{label}: no complete frame for {:.1} s", last_frame.elapsed().as_secs_f64()));
            session = None;
        }
    }
    drop(session);
    em.flush();
}

#[cfg(test)]
mod tests;
