//! A test's own frames (`[output] record_tests`): the frames of the cameras from the test's
//! start to its stop, and its UTM samples, recorded into its folder as a SPEC recording
//! (`<test folder>/frames/`: `tagdeflect.toml`, `frames.jsonl`, `utm.jsonl`, one folder per
//! camera) that `replay` reads. The recorder (the run's recorder, [`crate::recorder`]: its own
//! thread behind a bounded queue, never holding the measurement back, drops counted) is
//! started by the first frame at or after the test's start and finished when the test's
//! folder is completed, before its hashes are taken: `test.json` lists every frame file and
//! `report verify` checks them. A test resumed after a restart records into `frames-2/`, ...
//!
//! The disk's reserve: before a frame goes to the recorder (at most every
//! [`FREE_CHECK_EVERY`]) the free space under the test's folder is read; below the reserve
//! (`[output] record_tests_reserve_mb`) the test's frames stop — said once in the log and in
//! `test.json` (`frames_stopped`) — so the feeds and the test's lines keep their room.
//! The stop is kept in the running test's state at once, so a test resumed after a restart
//! records no frames again (its `test.json` says when and why they stopped).
//!
//! Whether a test records its frames is decided at its start (`test.json` `record_frames`):
//! its method's `record_frames` where the method sets it, else `[output] record_tests`.

use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use tagdeflect_core::frame::Frame;
use tagdeflect_core::lab_test::FramesStopped;
use tagdeflect_core::utm_sample::UtmSample;
use tagdeflect_io::recording::{RecordingError, RecordingWriter};

use super::LabTests;
use crate::recorder::{Recorder, RecorderTx};

/// Opens a recording writer in a folder (the config in force and the frame format are the
/// binary's: `RecordingWriter::create(dir, &config).with_format(format)`).
pub type OpenRecording = Box<dyn Fn(&Path) -> Result<RecordingWriter, RecordingError> + Send + Sync>;

/// How a test's frames are recorded ([`LabTests::set_frames`]).
pub struct FramesSetup {
    /// The recording writer for a folder.
    pub open: OpenRecording,
    /// The cameras' names, in config order.
    pub names: Vec<String>,
    /// The recorder's queue, frames.
    pub queue: usize,
    /// The free space kept under the tests folder: below it the test's frames stop, bytes.
    pub reserve_bytes: u64,
    /// Whether a test records its frames when its method does not say (`[output] record_tests`).
    pub default: bool,
}

/// The free space is read at most this often (3 × 1080p at 30 fps: ~90 MB between reads).
pub const FREE_CHECK_EVERY: Duration = Duration::from_secs(1);

/// The recorder of the running test's frames.
pub(super) struct ActiveFrames {
    id: String,
    /// None when the recording could not be started (said once).
    rec: Option<(Recorder, RecorderTx, PathBuf)>,
    /// When the free space was read last.
    checked: Option<Instant>,
    /// Set when the reserve was reached: no frame is sent any more.
    stopped: Option<FramesStopped>,
    /// The newest frame sent to the recorder (the cameras' frames arrive in any order).
    newest_sent_t_ns: Option<i64>,
}

/// The frames' state of a daemon's tests.
#[derive(Default)]
pub(super) struct TestFrames {
    pub(super) setup: std::sync::OnceLock<FramesSetup>,
    pub(super) active: Mutex<Option<ActiveFrames>>,
    /// The last test whose frames were closed (a late frame does not start them again).
    pub(super) closed: Mutex<Option<String>>,
}

/// The sub-folder a test's frames go to: `frames`, or `frames-2`, ... when a resumed test
/// has one already.
fn frames_dir(folder: &Path) -> PathBuf {
    let mut dir = folder.join("frames");
    let mut k = 2;
    while dir.exists() {
        dir = folder.join(format!("frames-{k}"));
        k += 1;
    }
    dir
}

impl LabTests {
    /// Records each test's frames into its folder from now on (see the module doc).
    pub fn set_frames(&self, setup: FramesSetup) {
        let _ = self.frames.setup.set(setup);
    }

    /// A camera frame: into the running test's recording when the test records frames and the
    /// frame is not older than its start.
    pub fn on_frame(&self, f: &Frame) {
        let Some(setup) = self.frames.setup.get() else { return };
        let running = self
            .lock()
            .running
            .as_ref()
            .filter(|r| Self::records_frames(&r.record, setup))
            .map(|r| (r.record.id.clone(), r.folder.clone(), r.record.started_t_ns));
        let Some((id, folder, started_t_ns)) = running else { return };
        if f.t_ns < started_t_ns {
            return;
        }
        let mut active = self.frames.active.lock().expect("test frames");
        if active.as_ref().is_some_and(|a| a.id != id) {
            if let Some(old) = active.take() {
                Self::finish_frames(old);
            }
        }
        if active.is_none() {
            if self.frames.closed.lock().expect("test frames").as_deref() == Some(id.as_str()) {
                return;
            }
            *active = Some(Self::start_frames(setup, id.clone(), &folder));
        }
        let Some(a) = active.as_mut() else { return };
        if a.within_reserve(f.t_ns, setup.reserve_bytes, &folder) {
            if let Some((_, tx, _)) = &a.rec {
                tx.frame(f.clone());
                a.newest_sent_t_ns = Some(a.newest_sent_t_ns.map_or(f.t_ns, |t| t.max(f.t_ns)));
            }
        } else if let Some(stopped) = a.stopped.clone() {
            drop(active);
            self.keep_frames_stopped(&id, stopped);
        }
    }

    /// Whether the test records frames now: as decided at its start (the rig's default for an
    /// older record), and not stopped at the disk's reserve (by this daemon or one before).
    fn records_frames(record: &super::TestRecord, setup: &FramesSetup) -> bool {
        record.record_frames.unwrap_or(setup.default) && record.frames_stopped.is_none()
    }

    /// The frames stopped at the disk's reserve: into the running test's record and its state
    /// on disk at once (a resumed test records no frames again).
    fn keep_frames_stopped(&self, id: &str, stopped: FramesStopped) {
        let mut g = self.lock();
        if let Some(r) = g.running.as_mut().filter(|r| r.record.id == id && r.record.frames_stopped.is_none()) {
            r.record.frames_stopped = Some(stopped);
            self.persist(r);
        }
    }

    /// A UTM sample of the running test into its recording (when frames are recorded).
    pub(super) fn frames_utm(&self, s: &UtmSample) {
        if self.frames.setup.get().is_none() {
            return;
        }
        if let Some((_, tx, _)) =
            self.frames.active.lock().expect("test frames").as_ref().filter(|a| a.stopped.is_none()).and_then(|a| a.rec.as_ref())
        {
            tx.utm(s.clone());
        }
    }

    fn start_frames(setup: &FramesSetup, id: String, folder: &Path) -> ActiveFrames {
        let dir = frames_dir(folder);
        match (setup.open)(&dir) {
            Ok(writer) => {
                let rec = Recorder::start_with(writer, setup.names.clone(), setup.queue, crate::recorder::RETRY_MIN);
                let tx = rec.sender();
                tracing::info!(test = %id, folder = %dir.display(), "the test's frames are recorded");
                ActiveFrames { id, rec: Some((rec, tx, dir)), checked: None, stopped: None, newest_sent_t_ns: None }
            }
            Err(e) => {
                tracing::error!(test = %id, "the test's frames cannot be recorded: {e}");
                ActiveFrames { id, rec: None, checked: None, stopped: None, newest_sent_t_ns: None }
            }
        }
    }

    /// Ends the recording of test `id`'s frames: what is queued is written and synced before
    /// this returns (the folder's hashes are taken after it). Answers when the frames stopped
    /// early (the disk's reserve).
    pub(super) fn close_frames(&self, id: &str) -> Option<FramesStopped> {
        *self.frames.closed.lock().expect("test frames") = Some(id.to_string());
        let taken = {
            let mut active = self.frames.active.lock().expect("test frames");
            if active.as_ref().is_some_and(|a| a.id == id) {
                active.take()
            } else {
                None
            }
        };
        let stopped = taken.as_ref().and_then(|a| a.stopped.clone());
        if let Some(a) = taken {
            Self::finish_frames(a);
        }
        stopped
    }

    /// Ends the running test's recording (the daemon stops; a resumed test records anew).
    pub fn finish_test_frames(&self) {
        let taken = self.frames.active.lock().expect("test frames").take();
        if let Some(a) = taken {
            Self::finish_frames(a);
        }
    }

    fn finish_frames(a: ActiveFrames) {
        if let Some(s) = &a.stopped {
            tracing::info!(test = %a.id, folder = %s.folder, "the test's frames ended early at the disk's reserve (test.json: frames_stopped)");
        }
        let Some((rec, tx, dir)) = a.rec else { return };
        drop(tx);
        let status = rec.status();
        rec.finish();
        let (written, dropped) = (status.written_frames(), status.dropped_frames());
        if dropped > 0 {
            tracing::warn!(test = %a.id, written, dropped, folder = %dir.display(), "the test's frames: some were not recorded");
        } else {
            tracing::info!(test = %a.id, written, folder = %dir.display(), "the test's frames recorded");
        }
    }
}

impl ActiveFrames {
    /// True while the free space under `folder` is above `reserve` (read at most every
    /// [`FREE_CHECK_EVERY`]); the first time it is not, the frames stop for good and it is said.
    fn within_reserve(&mut self, t_ns: i64, reserve: u64, folder: &Path) -> bool {
        if self.stopped.is_some() {
            return false;
        }
        if self.checked.is_some_and(|t| t.elapsed() < FREE_CHECK_EVERY) {
            return true;
        }
        self.checked = Some(Instant::now());
        let free = match tagdeflect_core::disk::free_bytes(folder) {
            Ok(b) => b,
            Err(e) => {
                tracing::debug!(test = %self.id, "free space under {} not read: {e}", folder.display());
                return true;
            }
        };
        if free >= reserve {
            return true;
        }
        let sub =
            self.rec.as_ref().and_then(|(_, _, d)| d.file_name()).map_or_else(|| "frames".into(), |n| n.to_string_lossy().into_owned());
        let (free_mb, reserve_mb) = (free as f64 / 1e6, reserve as f64 / 1e6);
        tracing::warn!(test = %self.id, folder = %sub, free_mb, reserve_mb, "the test's frames stop: the disk under the tests folder is down to its reserve (its lines go on; free space for frames of the next tests)");
        // Another camera's frame, newer than this one, may already be with the recorder: the
        // stop's time is after every frame recorded.
        let t_ns = self.newest_sent_t_ns.map_or(t_ns, |newest| t_ns.max(newest + 1));
        self.stopped = Some(FramesStopped { t_ns, folder: sub, free_mb, reserve_mb });
        false
    }
}
