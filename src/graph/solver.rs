//! The solver thread: takes frame sets from the queue, keeps the UTM's samples for the
//! measurement, measures each set, completes its line with the run's status and hands it to
//! the sinks' thread. It beats a heartbeat at least once a second (idle or solving) for the
//! systemd watchdog.

use std::sync::atomic::{AtomicI64, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use tagdeflect_core::feed::FeedLine;
use tagdeflect_core::frame::FrameSet;
use tagdeflect_estimate::measure::{MeasureStats, Measurement};
use tagdeflect_io::utm::modbus::UtmEvent;
use tagdeflect_io::utm::relay::RelayReceiver;
use tagdeflect_sinks::lab_test::LabTests;
use tagdeflect_sinks::recorder::RecorderStatus;
use tagdeflect_sinks::{Fanout, Finished};

use crate::config::Config;
use crate::graph::broker::Broker;
use crate::graph::journal::{FrameDrops, JournalSummary, SUMMARY_INTERVAL};
use crate::graph::queue::{CloseOnDrop, SetQueue};
use crate::graph::smoothing::Smoothing;

/// UTM samples kept for interpolation in live runs: this far behind the newest.
const LIVE_UTM_WINDOW_NS: i64 = 60_000_000_000;

/// A UTM feeds the run: each set waits at most `wait` for the sample after it while the UTM
/// is up (`up_at_start`: before its first event — a recorded stream).
#[derive(Debug, Clone)]
pub(crate) struct UtmFeed {
    pub(crate) wait: Duration,
    pub(crate) up_at_start: bool,
    /// A paced replay's samples, handed over in step with the frames
    /// ([`crate::graph::playback::PacedUtm`]): the recorded time of the newest one handed
    /// over. Each set waits, however long it takes, for every sample handed over before its
    /// frames up to the first at or after its time — by the recording's clock, not the wall's.
    pub(crate) in_step: Option<Arc<AtomicI64>>,
}

/// A machine this much slower, for tests and benchmarks (never set in service): the solver
/// sleeps this many ms before measuring each frame set, and the UTM forwarder before handing
/// on each event ([`throttle`]). A replay then falls behind its recorded pace however fast the
/// machine is.
pub(crate) const THROTTLE_ENV: &str = "TAGDEFLECT_THROTTLE_MS";

/// The throttle of [`THROTTLE_ENV`], if set to a whole number of ms above 0.
pub(crate) fn throttle() -> Option<Duration> {
    std::env::var(THROTTLE_ENV).ok().and_then(|v| v.trim().parse::<u64>().ok()).filter(|ms| *ms > 0).map(Duration::from_millis)
}

/// How long a set of a paced replay waits for a sample handed over before it at most (the
/// forwarder takes it in microseconds on a quiet machine; this only bounds a broken run).
const IN_STEP_WAIT: Duration = Duration::from_secs(30);

/// What the solver did, when it ended.
pub(crate) struct Solved {
    pub(crate) sets: u64,
    pub(crate) stats: MeasureStats,
}

/// What the solver takes its work from and hands its lines to.
pub(crate) struct SolverIo {
    pub(crate) queue: Arc<SetQueue>,
    pub(crate) utm: RelayReceiver,
    pub(crate) utm_feed: Option<UtmFeed>,
    pub(crate) fanout: Arc<Fanout>,
    /// A live run's status (absent in an as-fast replay: see [`crate::graph::run`]).
    pub(crate) status: Option<LineStatus>,
    pub(crate) heartbeat: Arc<AtomicU64>,
    pub(crate) smoothing: Option<Smoothing>,
}

/// What the solver adds to every feed line of a live run besides the measurement: the
/// state the run's other parts share (the recorder's, the cameras' drops, the MQTT buffer's
/// drops), read here so that the line is complete before any sink sees it.
pub(crate) struct LineStatus {
    /// The running test: its id, events and zero (`[output] tests`).
    pub(crate) tests: Option<Arc<LabTests>>,
    pub(crate) recorder: Option<Arc<RecorderStatus>>,
    pub(crate) frame_drops: Arc<FrameDrops>,
    pub(crate) broker: Option<Broker>,
}

impl LineStatus {
    fn apply(&self, line: &mut FeedLine) {
        if let Some(t) = &self.tests {
            t.apply(line);
        }
        self.frame_drops.apply(line);
        if let Some(r) = &self.recorder {
            line.recording = Some(r.state().as_str().to_string());
            line.recorder_dropped = Some(r.dropped_frames());
        }
        if let Some(b) = &self.broker {
            b.apply(line);
        }
    }
}

/// The UTM as the solver knows it: whether it is up, and how long a set waits for it.
struct UtmState {
    up: bool,
    configured: bool,
    wait: Duration,
    in_step: Option<Arc<AtomicI64>>,
}

impl UtmState {
    fn handle(&mut self, ev: UtmEvent, m: &mut Measurement) {
        match ev {
            UtmEvent::Sample(s) => {
                self.up = true;
                m.utm_mut().push(s)
            }
            UtmEvent::Down { reason } => {
                self.up = false;
                tracing::warn!("UTM down: {reason}; the feed goes on without load");
            }
            UtmEvent::Up => {
                self.up = true;
                tracing::debug!("UTM up"); // the poller logs it at INFO
            }
        }
    }

    /// Takes the events that came, then waits briefly for a UTM sample after the set's time,
    /// so load is interpolated, not extrapolated (and `run` gives the same load as a replay
    /// of its recording).
    fn catch_up(&mut self, rx: &RelayReceiver, m: &mut Measurement, set_t_ns: i64) {
        while let Some(ev) = rx.try_recv() {
            self.handle(ev, m);
        }
        if !(self.configured && self.up) {
            return;
        }
        if let Some(sent) = self.in_step.clone() {
            return self.catch_up_in_step(rx, m, set_t_ns, &sent);
        }
        let until = Instant::now() + self.wait;
        while m.utm_mut().newest_t_ns().is_none_or(|t| t < set_t_ns) {
            let left = until.saturating_duration_since(Instant::now());
            if left.is_zero() {
                break;
            }
            match rx.recv_timeout(left) {
                Some(ev) => self.handle(ev, m),
                None => break,
            }
        }
    }
}

impl UtmState {
    /// A paced replay's set: every sample handed over before its frames, up to the first at
    /// or after `set_t_ns`, is received before it is measured (see [`UtmFeed::in_step`]).
    fn catch_up_in_step(&mut self, rx: &RelayReceiver, m: &mut Measurement, set_t_ns: i64, sent: &AtomicI64) {
        let until = Instant::now() + IN_STEP_WAIT;
        loop {
            let needed = set_t_ns.min(sent.load(Ordering::SeqCst));
            if needed == i64::MIN || m.utm_mut().newest_t_ns().is_some_and(|t| t >= needed) {
                return;
            }
            let left = until.saturating_duration_since(Instant::now());
            if left.is_zero() {
                tracing::warn!(set_t_ns, "the replay's UTM samples up to this set did not arrive within {} s", IN_STEP_WAIT.as_secs());
                return;
            }
            if let Some(ev) = rx.recv_timeout(left.min(Duration::from_secs(1))) {
                self.handle(ev, m);
            }
        }
    }
}

/// Warns of a hole in time whatever the counters say (a stalled process, a suspended
/// machine: SIGSTOP for 20 s gave contiguous seq and no dropped set).
struct GapWatch {
    last_t_ns: Option<i64>,
    warn_s: f64,
}

impl GapWatch {
    /// A gap worth a warning: ten frame periods of the slowest camera, at least 2 s.
    fn new(config: &Config) -> Self {
        let min_fps = config.cameras.iter().filter_map(|c| c.fps).fold(f64::INFINITY, f64::min);
        let warn_s = if min_fps.is_finite() && min_fps > 0.0 { (10.0 / min_fps).max(2.0) } else { 2.0 };
        Self { last_t_ns: None, warn_s }
    }

    fn see(&mut self, set: &FrameSet) {
        if let Some(prev) = self.last_t_ns {
            let gap_s = (set.t_ns as i128 - prev as i128) as f64 * 1e-9;
            if gap_s > self.warn_s {
                tracing::warn!(gap_s = format!("{gap_s:.1}"), seq = set.seq, "no frame set for {gap_s:.1} s: the feed has a gap here");
            }
        }
        self.last_t_ns = Some(set.t_ns);
    }
}

/// The solver's loop, until the queue is closed and empty.
pub(crate) fn solver_loop(config: Config, mut measure: Measurement, io: SolverIo) -> Solved {
    let SolverIo { queue, utm, utm_feed, fanout, status, heartbeat, mut smoothing } = io;
    let _close = CloseOnDrop(queue.clone());
    let started = Instant::now();
    let beat = || heartbeat.store(started.elapsed().as_millis() as u64 + 1, Ordering::Relaxed);
    // A live run keeps a minute of UTM samples; a run's status (`status`) marks a live line.
    if status.is_some() {
        measure.utm_mut().set_window(LIVE_UTM_WINDOW_NS);
    }
    let mut sets = 0u64;
    let mut gaps = GapWatch::new(&config);
    let mut journal = JournalSummary::new(config.cameras.iter().map(|c| c.name.clone()).collect(), SUMMARY_INTERVAL);
    let mut utm_state = UtmState {
        up: utm_feed.as_ref().is_some_and(|u| u.up_at_start),
        configured: utm_feed.is_some(),
        wait: utm_feed.as_ref().map(|u| u.wait).unwrap_or_default(),
        in_step: utm_feed.and_then(|u| u.in_step),
    };
    let send =
        |line: FeedLine, set: Option<FrameSet>, m: &Measurement| fanout.send(Finished { line, set, observed: Arc::new(m.observed()) });
    let throttle = throttle();
    loop {
        beat();
        let Some(popped) = queue.pop_timeout(Duration::from_secs(1)) else {
            for line in smoothing.as_mut().map(Smoothing::finish).unwrap_or_default() {
                send(line, None, &measure);
            }
            return Solved { sets, stats: measure.stats().clone() };
        };
        let Some((set, arrived)) = popped else { continue };
        if let Some(t) = throttle {
            std::thread::sleep(t);
        }
        utm_state.catch_up(&utm, &mut measure, set.t_ns);
        gaps.see(&set);
        let (mut line, _) = measure.process(&set);
        sets += 1;
        if utm_state.configured {
            line.utm = Some(if utm_state.up { "ok" } else { "down" }.to_string());
        }
        if let Some(status) = &status {
            line.dropped_sets = Some(queue.dropped());
            line.latency_ms = Some((arrived.elapsed().as_secs_f64() * 1e4).round() / 10.0);
            status.apply(&mut line);
        }
        journal.observe(&line, measure.rejected_views_by_camera());
        // A smoothed line leaves the smoother some sets later: its frames are gone by then.
        match smoothing.as_mut() {
            Some(sm) => {
                if let Some(line) = sm.push(line, &measure) {
                    send(line, None, &measure);
                }
            }
            // The line is complete: the sinks take it on their own thread.
            None => send(line, Some(set), &measure),
        }
    }
}
