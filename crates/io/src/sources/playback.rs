//! A recording as a live source (`source = "recording:<folder>"`, and every camera of
//! `replay --realtime` / `bench --realtime`): each camera's recorded frames, played at their
//! recorded pace through the capture loop every camera uses ([`crate::sources::capture`]: same
//! emitter, frame pool, drop counting). A frame that cannot be read is a bad buffer (counted,
//! skipped); the camera's thread ends when its frames are played out.
//!
//! The cameras of one recording share one [`Playhead`]: frame `t` is due `t − t_first` after
//! the playhead started, so the cameras keep their recorded relative timing — except that a
//! pause in the recording longer than [`MAX_PLAYED_GAP`] is played as that long (and logged):
//! a frame stamped hours or 10^18 ns later is played next, never waited for.
//!
//! A replay's UTM samples go with its frames ([`UtmInStep`], `replay --realtime`): each camera
//! player hands over, before its frame, every sample recorded up to the first at or after the
//! frame's time, so the solver can wait for what a set's load needs by the recording's clock.

use std::sync::atomic::{AtomicI64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use crate::recording::{CameraList, RecordedConfig, Recording};
use crate::sources::capture::{CaptureSession, Captured};
use crate::utm::modbus::UtmEvent;
use tagdeflect_core::frame::GrayImage;
use tagdeflect_core::utm_sample::UtmSample;

/// The longest pause between two recorded frames that a paced replay waits out.
pub const MAX_PLAYED_GAP: Duration = Duration::from_secs(5);

/// When the newest [`Playhead::start`] of this process started: `bench --realtime` measures
/// exposure → feed line and register from it (a frame's exposure is its due time after it).
static LAST_START: std::sync::Mutex<Option<Instant>> = std::sync::Mutex::new(None);

/// How many times faster than recorded the playbacks of this process play (1 unless set;
/// `demo` plays its simulated test faster, the feed keeping the recorded times), as f64 bits.
static SPEED: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0x3FF0_0000_0000_0000);

/// Plays every recording of this process `speed` times faster than recorded (a finite number
/// above 0; others are ignored). The frames and UTM samples keep their recorded times.
pub fn set_playback_speed(speed: f64) {
    if speed.is_finite() && speed > 0.0 {
        SPEED.store(speed.to_bits(), std::sync::atomic::Ordering::SeqCst);
    }
}

fn playback_speed() -> f64 {
    f64::from_bits(SPEED.load(std::sync::atomic::Ordering::SeqCst))
}

/// A recorded interval as played at the process's speed.
fn played(recorded: Duration, speed: f64) -> Duration {
    if speed == 1.0 {
        recorded
    } else {
        recorded.div_f64(speed)
    }
}

/// The start of the newest playback of this process (see [`LAST_START`]).
pub fn last_playhead_start() -> Option<Instant> {
    *LAST_START.lock().unwrap_or_else(|e| e.into_inner())
}

/// The shared start of a recording's playback, and its schedule.
#[derive(Debug)]
pub struct Playhead {
    started: Instant,
    /// The recording's distinct frame times, ascending, with when each is due after the start
    /// (recorded time since the first frame, each pause capped at [`MAX_PLAYED_GAP`]).
    schedule: Vec<(i64, Duration)>,
    /// How many times faster than recorded ([`set_playback_speed`]).
    speed: f64,
}

impl Playhead {
    /// Starts now; the recording's earliest frame is due at once.
    pub fn start<C>(rec: &Recording<C>) -> Arc<Playhead> {
        let p = Self::with_times(rec.frames.iter().map(|f| f.t_ns), true);
        *LAST_START.lock().unwrap_or_else(|e| e.into_inner()) = Some(p.started);
        Arc::new(p)
    }

    /// As [`Playhead::start`], without logging the capped pauses (a second player of the same
    /// recording: its UTM stream).
    pub fn start_silent<C>(rec: &Recording<C>) -> Playhead {
        Self::with_times(rec.frames.iter().map(|f| f.t_ns), false)
    }

    fn with_times(times: impl Iterator<Item = i64>, warn: bool) -> Playhead {
        let mut times: Vec<i64> = times.collect();
        times.sort_unstable();
        times.dedup();
        let speed = playback_speed();
        let mut schedule = Vec::with_capacity(times.len());
        let mut due = Duration::ZERO;
        for (k, &t) in times.iter().enumerate() {
            if k > 0 {
                let gap = Duration::from_nanos(u64::try_from(t as i128 - times[k - 1] as i128).unwrap_or(u64::MAX));
                if warn && gap > MAX_PLAYED_GAP {
                    tracing::warn!(
                        "the recording pauses {:.1} s before the frame at t_ns={t}; played as {} s",
                        gap.as_secs_f64(),
                        MAX_PLAYED_GAP.as_secs()
                    );
                }
                due += played(gap, speed).min(MAX_PLAYED_GAP);
            }
            schedule.push((t, due));
        }
        Playhead { started: Instant::now(), schedule, speed }
    }

    /// When something recorded at `t_ns` (a frame, a UTM sample) is due after the start: the
    /// schedule of the last frame at or before it, plus the rest (capped as a pause is).
    pub fn due(&self, t_ns: i64) -> Duration {
        let k = self.schedule.partition_point(|(t, _)| *t <= t_ns);
        if k == 0 {
            return Duration::ZERO;
        }
        let (t, at) = self.schedule[k - 1];
        let rest = Duration::from_nanos(u64::try_from(t_ns as i128 - t as i128).unwrap_or(u64::MAX));
        at + played(rest, self.speed).min(MAX_PLAYED_GAP)
    }

    /// How long until a frame recorded at `t_ns` is due (zero when due or late).
    fn wait_for(&self, t_ns: i64) -> Duration {
        self.due(t_ns).saturating_sub(self.started.elapsed())
    }
}

/// A recording's UTM samples handed over by its camera players in step with the frames
/// (`replay --realtime`, `bench --realtime`), shared by the players of one recording: each
/// sample at its own due time on the players' [`Playhead`] while a player waits for its frame,
/// and — before a frame is delivered — every sample up to the first recorded at or after the
/// frame's time, that one ahead of its time (the frame's line interpolates between the two).
/// `sent` is the recorded time of the newest sample handed over (`i64::MIN` before the first):
/// a set's solver waits to have received the samples up to its time or up to `sent`, so a
/// busy machine can delay a set's load or drop the set, never leave it without the load
/// recorded around it. Samples after the recording's last frame are not played. A hand-over
/// waits for room (the samples are the recording's, not a live link that can lose them).
#[derive(Debug)]
pub struct UtmInStep {
    samples: Vec<UtmSample>,
    next: usize,
    /// None once nobody takes them (the run ends).
    tx: Option<tokio::sync::mpsc::Sender<UtmEvent>>,
    sent: Arc<AtomicI64>,
}

impl UtmInStep {
    /// The samples of `rec`, to `tx`; `sent` as in the type's doc.
    pub fn new<C>(rec: &Recording<C>, tx: tokio::sync::mpsc::Sender<UtmEvent>, sent: Arc<AtomicI64>) -> Arc<Mutex<UtmInStep>> {
        Arc::new(Mutex::new(UtmInStep { samples: rec.utm.clone(), next: 0, tx: Some(tx), sent }))
    }

    /// Hands over the samples due by now on `head`; how long until the next one is due.
    fn hand_over_due(&mut self, head: &Playhead) -> Option<Duration> {
        while let Some(s) = self.samples.get(self.next).copied() {
            let wait = head.wait_for(s.t_ns);
            if !wait.is_zero() {
                return Some(wait);
            }
            self.send(s);
        }
        None
    }

    /// Hands over every sample up to the first recorded at or after `t_ns` (see the type's doc).
    fn hand_over_to(&mut self, t_ns: i64) {
        if self.sent.load(Ordering::SeqCst) >= t_ns {
            return;
        }
        while let Some(s) = self.samples.get(self.next).copied() {
            self.send(s);
            if s.t_ns >= t_ns {
                break;
            }
        }
    }

    fn send(&mut self, s: UtmSample) {
        self.next += 1;
        if self.tx.as_ref().is_some_and(|tx| tx.blocking_send(UtmEvent::Sample(s)).is_err()) {
            self.tx = None;
        }
        self.sent.store(s.t_ns, Ordering::SeqCst);
    }
}

/// How far a paced replay that never drops may fall behind its schedule before the schedule
/// slips ([`ElasticClock`]).
pub const SLIP_AFTER: Duration = Duration::from_millis(100);

/// The clock of a paced replay that never drops (`demo --c1609`): one schedule for the
/// recording's frames and UTM samples ([`Playhead`]'s), which *slips* when the replay falls
/// behind it — a pipeline that cannot keep the recorded pace (a busy machine) makes the replay
/// play slower, keeping the recorded spacing from where it is, instead of dropping frame sets
/// or handing over a burst to catch up. Recorded times are never changed: only when each
/// frame and sample is handed over.
#[derive(Debug)]
pub struct ElasticClock {
    head: Playhead,
    /// How much later than scheduled the replay now runs.
    slip: Duration,
    /// How many times it slipped.
    slips: u64,
}

impl ElasticClock {
    /// Starts now (as [`Playhead::start`]): the recording's earliest frame is due at once.
    pub fn start<C>(rec: &Recording<C>) -> ElasticClock {
        let head = Playhead::with_times(rec.frames.iter().map(|f| f.t_ns), true);
        *LAST_START.lock().unwrap_or_else(|e| e.into_inner()) = Some(head.started);
        ElasticClock { head, slip: Duration::ZERO, slips: 0 }
    }

    /// Waits until something recorded at `t_ns` is due (in naps of at most 100 ms); false
    /// when `stop` was set meanwhile. Due more than [`SLIP_AFTER`] ago: the schedule slips
    /// by the lateness (it is due now; what follows keeps its recorded spacing from here).
    pub fn wait_until_due(&mut self, t_ns: i64, stop: &std::sync::atomic::AtomicBool) -> bool {
        let due = self.head.due(t_ns) + self.slip;
        loop {
            if stop.load(std::sync::atomic::Ordering::SeqCst) {
                return false;
            }
            let now = self.head.started.elapsed();
            if now >= due {
                if now - due > SLIP_AFTER {
                    self.slip += now - due;
                    self.slips += 1;
                }
                return true;
            }
            std::thread::sleep((due - now).min(Duration::from_millis(100)));
        }
    }

    /// How much later than the recorded pace the replay runs now, and how many times it slipped.
    pub fn slipped(&self) -> (Duration, u64) {
        (self.slip, self.slips)
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
    /// The recording's UTM samples, handed over with the frames (none: not played).
    utm: Option<Arc<Mutex<UtmInStep>>>,
}

impl RecordingSession {
    /// The frames of the recording's camera named `name`.
    pub fn new<C: RecordedConfig>(rec: &Recording<C>, playhead: Arc<Playhead>, name: &str) -> Self {
        let rec = Arc::new(rec.with_cameras_only());
        let entries = rec.frames.iter().enumerate().filter(|(_, f)| f.camera == name).map(|(i, _)| i).collect();
        Self { rec, playhead, entries, next: 0, scratch: Vec::new(), utm: None }
    }

    /// This camera's player hands over the recording's UTM samples with its frames (every
    /// player of the recording shares `utm`).
    pub fn with_utm(mut self, utm: Arc<Mutex<UtmInStep>>) -> Self {
        self.utm = Some(utm);
        self
    }

    /// The UTM samples due by now handed over; how long until the next one is due.
    fn utm_due(&self) -> Option<Duration> {
        self.utm.as_ref().and_then(|u| u.lock().unwrap_or_else(|e| e.into_inner()).hand_over_due(&self.playhead))
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
        let t_ns = self.rec.frames[i].t_ns;
        let utm_wait = self.utm_due();
        let wait = self.playhead.wait_for(t_ns);
        if !wait.is_zero() {
            // Bounded wait, so the capture loop sees its stop flag (and the UTM samples due
            // meanwhile go at their time).
            std::thread::sleep(wait.min(utm_wait.unwrap_or(wait)).min(Duration::from_millis(100)));
            if !self.playhead.wait_for(t_ns).is_zero() {
                return Captured::Timeout;
            }
        }
        if let Some(u) = &self.utm {
            u.lock().unwrap_or_else(|e| e.into_inner()).hand_over_to(t_ns);
        }
        self.next += 1;
        let entry = &self.rec.frames[i];
        match self.rec.load_image_into(entry, into, &mut self.scratch) {
            Ok(()) => Captured::Image(entry.t_ns),
            Err(e) => Captured::Bad(e.to_string()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_elastic_clock_slips_when_late_and_keeps_the_recorded_spacing_after() {
        let ms = 1_000_000i64;
        let head = Playhead::with_times([0, 20 * ms, 40 * ms, 60 * ms].into_iter(), false);
        let mut clock = ElasticClock { head, slip: Duration::ZERO, slips: 0 };
        let stop = std::sync::atomic::AtomicBool::new(false);
        assert!(clock.wait_until_due(0, &stop));
        // The replay is held up 300 ms (a hand-over waited): the frame due at 20 ms is
        // handed over at once, and the schedule slips by its lateness.
        std::thread::sleep(Duration::from_millis(300));
        assert!(clock.wait_until_due(20 * ms, &stop));
        let (slip, slips) = clock.slipped();
        assert_eq!(slips, 1);
        assert!(slip >= Duration::from_millis(280), "{slip:?}");
        // The next frame keeps its recorded 20 ms after the late one (handed over at 300 ms
        // or later): waited for, not rushed to catch up with the schedule.
        assert!(clock.wait_until_due(40 * ms, &stop));
        let at = clock.head.started.elapsed();
        assert!(at >= Duration::from_millis(320), "{at:?}");
        stop.store(true, std::sync::atomic::Ordering::SeqCst);
        assert!(!clock.wait_until_due(60 * ms + 3_600_000 * ms, &stop), "a stop ends the wait");
    }

    #[test]
    fn the_utm_samples_a_frame_needs_go_before_it_the_rest_at_their_time() {
        let ms = 1_000_000i64;
        let sample = |t_ns: i64| UtmSample { t_ns, load_kn: t_ns as f64 / ms as f64, stroke_mm: None };
        let (tx, mut rx) = tokio::sync::mpsc::channel(16);
        let sent = Arc::new(AtomicI64::new(i64::MIN));
        // Samples every 5 ms from 0 to 60 ms; a gap from 60 to 500 ms.
        let samples: Vec<UtmSample> = (0..=12).map(|k| sample(5 * k * ms)).chain([sample(500 * ms)]).collect();
        let mut utm = UtmInStep { samples, next: 0, tx: Some(tx), sent: sent.clone() };
        let got = |rx: &mut tokio::sync::mpsc::Receiver<UtmEvent>| {
            std::iter::from_fn(|| rx.try_recv().ok())
                .map(|e| match e {
                    UtmEvent::Sample(s) => s.t_ns / ms,
                    other => panic!("{other:?}"),
                })
                .collect::<Vec<_>>()
        };
        // A frame at 12 ms: the samples up to the first at or after it (15 ms, ahead of time).
        utm.hand_over_to(12 * ms);
        assert_eq!(got(&mut rx), vec![0, 5, 10, 15]);
        assert_eq!(sent.load(Ordering::SeqCst), 15 * ms);
        // A frame at 15 ms needs nothing more.
        utm.hand_over_to(15 * ms);
        assert!(got(&mut rx).is_empty());
        // A frame inside the gap: the sample after it, ahead of its time.
        utm.hand_over_to(100 * ms);
        assert_eq!(got(&mut rx), vec![20, 25, 30, 35, 40, 45, 50, 55, 60, 500]);
        // Every sample went: nothing is left to hand over by the clock.
        let head = Playhead::with_times([0i64].into_iter(), false);
        assert_eq!(utm.hand_over_due(&head), None);
        // Nobody takes them any more: no error, the time still advances.
        let (tx, rx) = tokio::sync::mpsc::channel(1);
        drop(rx);
        let sent = Arc::new(AtomicI64::new(i64::MIN));
        let mut utm = UtmInStep { samples: vec![sample(0), sample(5 * ms)], next: 0, tx: Some(tx), sent: sent.clone() };
        utm.hand_over_to(5 * ms);
        assert_eq!(sent.load(Ordering::SeqCst), 5 * ms);
    }

    #[test]
    fn utm_samples_are_handed_over_at_their_time_while_a_player_waits() {
        let ms = 1_000_000i64;
        let (tx, mut rx) = tokio::sync::mpsc::channel(16);
        let samples: Vec<UtmSample> =
            [0, 20 * ms, 400 * ms].iter().map(|&t_ns| UtmSample { t_ns, load_kn: 1.0, stroke_mm: None }).collect();
        let mut utm = UtmInStep { samples, next: 0, tx: Some(tx), sent: Arc::new(AtomicI64::new(i64::MIN)) };
        let head = Playhead::with_times([0i64, 1000 * ms].into_iter(), false);
        std::thread::sleep(Duration::from_millis(50));
        // 50 ms after the start: the samples at 0 and 20 ms are due, the one at 400 ms is not.
        let next = utm.hand_over_due(&head).expect("one sample left");
        assert!(next <= Duration::from_millis(350) && next >= Duration::from_millis(200), "{next:?}");
        assert_eq!(std::iter::from_fn(|| rx.try_recv().ok()).count(), 2);
    }

    #[test]
    fn the_schedule_keeps_recorded_spacing_and_caps_long_pauses() {
        let s = 1_000_000_000i64;
        let head = Playhead::with_times([0, s / 10, 2 * s / 10, 2 * s / 10 + 1_000_000_000_000_000_000, i64::MAX].into_iter(), false);
        assert_eq!(head.due(0), Duration::ZERO);
        assert_eq!(head.due(s / 10), Duration::from_millis(100));
        assert_eq!(head.due(s / 20), Duration::from_millis(50), "between frames: recorded spacing");
        // A frame 10^18 ns later is due one capped pause later, not in 31 years.
        assert_eq!(head.due(2 * s / 10 + 1_000_000_000_000_000_000), Duration::from_millis(200) + MAX_PLAYED_GAP);
        assert_eq!(head.due(i64::MAX), Duration::from_millis(200) + 2 * MAX_PLAYED_GAP);
        assert_eq!(head.due(i64::MIN), Duration::ZERO, "before the first frame: at once");
    }
}
