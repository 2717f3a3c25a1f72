//! The recorder of live runs (`run --record`, `record`, `[output] record`): frames and UTM
//! samples into a SPEC recording, in a thread of its own behind a bounded queue.
//!
//! It never holds the measurement back: a full queue drops the frame (counted). A write
//! error (disk full, folder gone) does not stop it for good: it switches to *failing*,
//! drops the frames that arrive meanwhile (counted; UTM samples are held back, at most
//! `UTM_BACKLOG`) and retries with backoff (`RETRY_MIN` doubling to `RETRY_MAX`);
//! the first frame written again switches it back to *ok*. Its state and drop count are
//! read by the solver for every feed line (`recording`, `recorder_dropped`). Images are
//! written under a temporary name and renamed; index lines are written whole or cut back
//! (see [`tagdeflect_core::linefile`]).

use std::collections::VecDeque;
use std::path::Path;
use std::sync::atomic::{AtomicU64, AtomicU8, Ordering};
use std::sync::{mpsc, Arc};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use tagdeflect_core::backoff::Backoff;
use tagdeflect_core::feed_file::SinkState;
use tagdeflect_core::frame::Frame;
use tagdeflect_core::frame::FrameFormat;
use tagdeflect_io::recording::{RecordedConfig, RecordingError, RecordingWriter};
use tagdeflect_io::utm::UtmSample;

/// First retry this long after a write error; doubled after each failed retry.
pub(crate) const RETRY_MIN: Duration = Duration::from_millis(500);
/// Longest wait between retries.
const RETRY_MAX: Duration = Duration::from_secs(10);
/// UTM samples held back while failing (about 30 min at 50 Hz); beyond that the oldest drop.
const UTM_BACKLOG: usize = 100_000;

/// The recorder's state and counters, shared with the solver (feed lines).
#[derive(Debug, Default)]
pub struct RecorderStatus {
    state: AtomicU8,
    dropped_frames: AtomicU64,
    dropped_utm: AtomicU64,
    written_frames: AtomicU64,
}

impl RecorderStatus {
    /// Ok, failing (retrying) or off (stopped).
    pub fn state(&self) -> SinkState {
        match self.state.load(Ordering::Relaxed) {
            0 => SinkState::Ok,
            1 => SinkState::Failing,
            _ => SinkState::Off,
        }
    }
    fn set(&self, s: SinkState) {
        self.state.store(
            match s {
                SinkState::Ok => 0,
                SinkState::Failing => 1,
                SinkState::Off => 2,
            },
            Ordering::Relaxed,
        );
    }
    /// Frames not recorded so far (queue full or write failing).
    pub fn dropped_frames(&self) -> u64 {
        self.dropped_frames.load(Ordering::Relaxed)
    }
    /// UTM samples not recorded so far.
    pub fn dropped_utm(&self) -> u64 {
        self.dropped_utm.load(Ordering::Relaxed)
    }
    /// Frames recorded so far.
    pub fn written_frames(&self) -> u64 {
        self.written_frames.load(Ordering::Relaxed)
    }
}

enum Msg {
    Frame(Frame),
    Utm(UtmSample),
}

/// The sending side: cheap to clone, never blocks.
#[derive(Clone)]
pub struct RecorderTx {
    tx: mpsc::SyncSender<Msg>,
    status: Arc<RecorderStatus>,
}

impl RecorderTx {
    /// Queues a frame; a full queue drops it (counted).
    pub fn frame(&self, f: Frame) {
        if self.tx.try_send(Msg::Frame(f)).is_err() {
            self.status.dropped_frames.fetch_add(1, Ordering::Relaxed);
        }
    }
    /// Queues a UTM sample; a full queue drops it (counted).
    pub fn utm(&self, s: UtmSample) {
        if self.tx.try_send(Msg::Utm(s)).is_err() {
            self.status.dropped_utm.fetch_add(1, Ordering::Relaxed);
        }
    }
}

/// A running recorder.
pub struct Recorder {
    tx: Option<RecorderTx>,
    status: Arc<RecorderStatus>,
    thread: Option<JoinHandle<()>>,
}

impl Recorder {
    /// Creates the recording folder (errors here are reported before anything starts) and
    /// starts the recorder thread with a queue of `queue` messages.
    pub fn start(dir: &Path, config: &impl RecordedConfig, format: FrameFormat, queue: usize) -> Result<Recorder, RecordingError> {
        let writer = RecordingWriter::create(dir, config)?.with_format(format);
        let names: Vec<String> = config.cameras().iter().map(|c| c.name.clone()).collect();
        Ok(Self::start_with(writer, names, queue, RETRY_MIN))
    }

    /// Starts the thread over an open writer (`retry_min`: first backoff; tests shorten it).
    pub fn start_with(writer: RecordingWriter, names: Vec<String>, queue: usize, retry_min: Duration) -> Recorder {
        let status = Arc::new(RecorderStatus::default());
        let (tx, rx) = mpsc::sync_channel::<Msg>(queue.max(1));
        let st = status.clone();
        let thread = std::thread::Builder::new()
            .name("recorder".into())
            .spawn(move || recorder_loop(writer, names, rx, st, retry_min))
            .expect("recorder thread");
        Recorder { tx: Some(RecorderTx { tx, status: status.clone() }), status, thread: Some(thread) }
    }

    /// A sender for the pipeline's tasks.
    pub fn sender(&self) -> RecorderTx {
        self.tx.clone().expect("recorder running")
    }

    /// The shared state and counters.
    pub fn status(&self) -> Arc<RecorderStatus> {
        self.status.clone()
    }

    /// Ends the recorder once every sender is dropped: writes what is queued, syncs, joins.
    pub fn finish(mut self) {
        self.tx = None;
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

fn recorder_loop(
    mut writer: RecordingWriter,
    names: Vec<String>,
    rx: mpsc::Receiver<Msg>,
    status: Arc<RecorderStatus>,
    retry_min: Duration,
) {
    let mut failing_since: Option<Instant> = None;
    let mut next_retry = Instant::now();
    let mut backoff = Backoff::new(retry_min, RETRY_MAX);
    let mut utm_backlog: VecDeque<UtmSample> = VecDeque::new();
    let mut dropped_at_failure = 0u64;
    for msg in rx {
        let retry_now = failing_since.is_none() || Instant::now() >= next_retry;
        let res = match msg {
            Msg::Frame(f) => {
                if !retry_now {
                    status.dropped_frames.fetch_add(1, Ordering::Relaxed);
                    continue;
                }
                let r =
                    flush_utm(&mut writer, &mut utm_backlog).and_then(|_| writer.write_frame(&names[f.camera], f.seq, f.t_ns, &f.image));
                match &r {
                    Ok(()) => status.written_frames.fetch_add(1, Ordering::Relaxed),
                    // The frame whose write failed is lost.
                    Err(_) => status.dropped_frames.fetch_add(1, Ordering::Relaxed),
                };
                r
            }
            Msg::Utm(s) => {
                utm_backlog.push_back(s);
                if utm_backlog.len() > UTM_BACKLOG {
                    utm_backlog.pop_front();
                    status.dropped_utm.fetch_add(1, Ordering::Relaxed);
                }
                if !retry_now {
                    continue;
                }
                flush_utm(&mut writer, &mut utm_backlog)
            }
        };
        match res {
            Ok(()) => {
                if let Some(since) = failing_since.take() {
                    let lost = status.dropped_frames() - dropped_at_failure;
                    tracing::warn!(after_s = since.elapsed().as_secs(), frames_lost = lost, "recording writes again");
                    status.set(SinkState::Ok);
                    backoff.reset();
                }
                if let Err(e) = writer.sync_if_due() {
                    tracing::warn!("recording: fdatasync failed: {e}");
                }
            }
            Err(e) => {
                let wait = backoff.next_delay();
                if failing_since.is_none() {
                    failing_since = Some(Instant::now());
                    dropped_at_failure = status.dropped_frames();
                    status.set(SinkState::Failing);
                    tracing::error!("recording failing: {e}; frames are dropped (counted in the feed as recorder_dropped) and writing is retried, first in {:.1} s", wait.as_secs_f64());
                } else {
                    tracing::debug!("recording still failing: {e}");
                }
                next_retry = Instant::now() + wait;
            }
        }
    }
    let _ = flush_utm(&mut writer, &mut utm_backlog);
    if !utm_backlog.is_empty() {
        status.dropped_utm.fetch_add(utm_backlog.len() as u64, Ordering::Relaxed);
    }
    if let Err(e) = writer.finish() {
        tracing::error!("recording: {e}");
    }
    status.set(SinkState::Off);
}

fn flush_utm(writer: &mut RecordingWriter, backlog: &mut VecDeque<UtmSample>) -> Result<(), RecordingError> {
    while let Some(s) = backlog.front() {
        writer.write_utm(s)?;
        backlog.pop_front();
    }
    Ok(())
}
