//! A recording as a live source (`source = "recording:<folder>"`, and every camera of
//! `replay --realtime` / `bench --realtime`): each camera's recorded frames, played at their
//! recorded pace through the capture loop every camera uses ([`crate::sources::capture`]: same
//! emitter, frame pool, drop counting). A frame that cannot be read is a bad buffer (counted,
//! skipped); the camera's thread ends when its frames are played out.
//!
//! The cameras of one recording share one [`Playhead`]: frame `t` is due `t − t_first` after
//! the playhead started, so the cameras keep their recorded relative timing.

use std::sync::Arc;
use std::time::{Duration, Instant};

use crate::recording::{CameraList, RecordedConfig, Recording};
use crate::sources::capture::{CaptureSession, Captured};
use tagdeflect_core::frame::GrayImage;

/// The shared start of a recording's playback.
#[derive(Debug)]
pub struct Playhead {
    started: Instant,
    first_t_ns: i64,
}

impl Playhead {
    /// Starts now; the recording's earliest frame is due at once.
    pub fn start<C>(rec: &Recording<C>) -> Arc<Playhead> {
        Arc::new(Playhead { started: Instant::now(), first_t_ns: rec.frames.first().map_or(0, |f| f.t_ns) })
    }

    /// How long until a frame recorded at `t_ns` is due (zero when due or late).
    fn wait_for(&self, t_ns: i64) -> Duration {
        let due = Duration::from_nanos(t_ns.saturating_sub(self.first_t_ns).max(0).unsigned_abs());
        due.saturating_sub(self.started.elapsed())
    }
}

/// One camera of a recording, played as captured.
#[derive(Debug)]
pub struct RecordingSession {
    rec: Arc<Recording<CameraList>>,
    playhead: Arc<Playhead>,
    /// Indices into `rec.frames` of this camera's frames, in time order.
    entries: Vec<usize>,
    next: usize,
    scratch: Vec<u8>,
}

impl RecordingSession {
    /// The frames of the recording's camera named `name`.
    pub fn new<C: RecordedConfig>(rec: &Recording<C>, playhead: Arc<Playhead>, name: &str) -> Self {
        let rec = Arc::new(rec.with_cameras_only());
        let entries = rec.frames.iter().enumerate().filter(|(_, f)| f.camera == name).map(|(i, _)| i).collect();
        Self { rec, playhead, entries, next: 0, scratch: Vec::new() }
    }

    /// Frames this camera will play in all.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    /// Whether the camera has no frame in the recording.
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }
}

impl CaptureSession for RecordingSession {
    fn next(&mut self, into: &mut GrayImage) -> Captured {
        let Some(&i) = self.entries.get(self.next) else {
            return Captured::End;
        };
        let entry = &self.rec.frames[i];
        let wait = self.playhead.wait_for(entry.t_ns);
        if !wait.is_zero() {
            // Bounded wait, so the capture loop sees its stop flag.
            std::thread::sleep(wait.min(Duration::from_millis(100)));
            if !self.playhead.wait_for(entry.t_ns).is_zero() {
                return Captured::Timeout;
            }
        }
        self.next += 1;
        match self.rec.load_image_into(entry, into, &mut self.scratch) {
            Ok(()) => Captured::Image(entry.t_ns),
            Err(e) => Captured::Bad(e.to_string()),
        }
    }
}
