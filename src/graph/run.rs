//! The one graph behind `run`, `record`, `demo` and `replay` (with or without `--realtime`).
//!
//! ```text
//! camera threads (v4l2 / aravis / sim / recording player) ──SourceEvent──▶ assembler task
//!   assembler ──frame sets──▶ drop-oldest queue ──▶ solver thread ──feed lines──▶ sinks
//!   assembler ──frames──▶ recorder thread (optional)
//! UTM poller task ──UtmEvent──▶ solver thread (+ recorder)
//! ```
//!
//! A recording is a source like a camera; how it is played is its [`Pacing`]:
//! [`Pacing::Recorded`] (`replay --realtime`) plays each camera's frames at their recorded
//! times through the live run's threads and drop-oldest queues, so a replay meets what a run
//! met; [`Pacing::AsFast`] (plain `replay`) has one reader hand the frames over in time order
//! and every hand-off — source to assembler, queue to solver, solver to sinks — wait for room
//! instead of dropping, so the frame sets are exactly the recording's and the feed is the same
//! on every replay, however busy the machine. The status a live run adds to its lines
//! (`dropped_sets`, `latency_ms`, the UTM's state) describes the run, not the recording, and is
//! left out of an as-fast replay's lines; the recording's UTM samples are all known before the
//! first set, so each set's load is interpolated from the whole stream.
//!
//! Capture never blocks on the solver: camera threads only `try_send`, and the queue in
//! front of the solver holds at most [`QUEUE_SETS`] frame sets — when the solver falls
//! behind, the oldest set is dropped and counted, and every feed line carries the count
//! (`dropped_sets`). SIGTERM/SIGINT/SIGHUP (or `--duration-s`) stops capture, lets the solver
//! finish the sets already queued, flushes every sink and returns `Ok` (exit 0).
//!
//! systemd: READY=1 is sent once every source is open; the watchdog is pinged by the
//! solver after each solved frame set, so a pipeline whose frame sets stop flowing is
//! restarted by systemd (`WatchdogSec` in the unit).

use anyhow::{Context, Result};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::sync::{mpsc, watch};

use tagdeflect_core::feed_file::FeedWriter;
use tagdeflect_core::BadInput;
use tagdeflect_estimate::measure::Measurement;
use tagdeflect_io::sources::{OpenPolicy, SourceEvent};
use tagdeflect_io::sync::{FrameSetAssembler, WaitRule};
use tagdeflect_io::utm::modbus::UtmEvent;
use tagdeflect_io::utm::relay::relay;
use tagdeflect_sinks::{Fanout, Overflow};

use crate::config::Config;
use crate::graph::entry::LiveOptions;
use crate::graph::journal::FrameDrops;
use crate::graph::outputs::{OutputContext, Outputs};
use crate::graph::page::Page;
use crate::graph::playback::{spawn_paced_reader, spawn_reader, Pacing, Playback};
use crate::graph::queue::SetQueue;
use crate::graph::signals::StopSignals;
use crate::graph::smoothing::Smoothing;
use crate::graph::solver::{solver_loop, LineStatus, Solved, SolverIo};
use crate::graph::sources::Sources;
use crate::graph::utm::{self, UtmWatchers};
use crate::graph::utm_file::UtmFiles;

pub use crate::graph::queue::QUEUE_SETS;

/// UTM events live runs hold for the solver at most (drop-oldest; ~80 s at 50 Hz).
const UTM_RELAY_SAMPLES: usize = 4096;
/// A solver heartbeat older than this stops the watchdog pings (systemd then restarts the
/// daemon after `WatchdogSec`).
const WATCHDOG_STALE_MS: u64 = 10_000;

/// What kind of run this is, read once from the options and the playback.
#[derive(Debug, Clone, Copy)]
struct RunKind {
    replaying: bool,
    /// Every hand-off waits instead of dropping (an as-fast or a paced replay: see the module
    /// doc).
    lossless: bool,
    /// As fast as it goes: the recording's whole UTM stream is known before the first set, and
    /// the lines carry no run status.
    as_fast: bool,
    record_only: bool,
    /// A replay's page stays up after it until a signal.
    linger: bool,
}

impl RunKind {
    fn of(opts: &LiveOptions, playback: Option<&Playback>) -> Self {
        let pacing = playback.map(|p| p.pacing);
        let as_fast = pacing == Some(Pacing::AsFast);
        let lossless = as_fast || pacing == Some(Pacing::Paced);
        Self { replaying: playback.is_some(), lossless, as_fast, record_only: opts.record_only, linger: !opts.no_linger }
    }

    /// The run's mode as the page shows it.
    fn mode(playback: Option<&Playback>) -> &'static str {
        match playback.map(|p| p.pacing) {
            None => "live",
            Some(Pacing::Recorded | Pacing::Paced) => "realtime",
            Some(Pacing::AsFast) => "replay",
        }
    }
}

/// The story of a run: outputs, measurement, sources, UTM, solver, then the assembler until
/// the sources end or a stop is asked for, then the shutdown.
pub(crate) async fn run_async(config: Config, opts: LiveOptions, playback: Option<Playback>, feeds: Vec<FeedWriter>) -> Result<()> {
    let started_at = Instant::now();
    // The stop signals are watched before anything starts: one that comes while the page,
    // the tests or the sources start up (systemd may stop a unit at any time) ends the run
    // at the first turn of the loop below, as it does later (last sync, report, recorder
    // drained) — never the default action, which would kill the process where it stands.
    let mut stop_signals = StopSignals::watch()?;
    let kind = RunKind::of(&opts, playback.as_ref());
    // Outputs first: an unwritable output is reported before any camera starts.
    let page = Page::start(&config, opts.http, RunKind::mode(playback.as_ref())).await?;
    let record_dir = record_dir(&config, &opts, kind);
    let ctx = OutputContext { config: &config, opts: &opts, replaying: kind.replaying, record_dir: record_dir.as_deref(), page: &page };
    let outputs = Outputs::build(&ctx, feeds)?;
    let measure = measurement(&config, &opts, kind, playback.as_ref(), &page)?;
    let stop = Arc::new(AtomicBool::new(false));
    let (src_tx, mut src_rx) = mpsc::channel::<SourceEvent>(4 * config.cameras.len().max(1));
    let (inputs, utm_link) = Inputs::start(&config, kind, playback.as_ref(), src_tx, stop.clone())?;
    let (shutdown_tx, shutdown_rx) = watch::channel(false);
    let run_utm = utm::start(&config, playback.as_ref(), inputs.sources.as_ref(), utm_link, shutdown_rx).await?;
    let _ = sd_notify::notify(false, &[sd_notify::NotifyState::Ready]);
    tracing::info!(cameras = config.cameras.len(), "sources started; measuring");
    let mut run = Running::start(&config, kind, outputs, measure, run_utm, &page, opts.smooth_lag_sets)?;
    let frames_seen = run.assemble(&config, &opts, kind, &mut src_rx, &page, &mut stop_signals).await;
    // Shutdown: stop capture, finish queued sets, flush sinks.
    let _ = sd_notify::notify(false, &[sd_notify::NotifyState::Stopping]);
    stop.store(true, Ordering::SeqCst);
    let _ = shutdown_tx.send(true);
    let ended = run.shutdown(kind, src_rx, inputs, frames_seen).await;
    ended.report(kind, playback.as_ref(), started_at, &page, &mut stop_signals).await
}

/// Where this run records: `--record DIR`, else a new timestamped folder under
/// `[output] record` (never in a replay).
fn record_dir(config: &Config, opts: &LiveOptions, kind: RunKind) -> Option<PathBuf> {
    opts.record.clone().or_else(|| {
        (!kind.replaying)
            .then(|| config.output.record.as_ref().map(|d| d.join(chrono::Utc::now().format("%Y%m%dT%H%M%SZ").to_string())))
            .flatten()
    })
}

/// The measurement, built before any source starts: a detector option it cannot take is a
/// config error (exit 2), never a daemon that captures without measuring. None in `record`.
/// As fast as it goes, the recording's whole UTM stream is known before its first set.
fn measurement(
    config: &Config,
    opts: &LiveOptions,
    kind: RunKind,
    playback: Option<&Playback>,
    page: &Page,
) -> Result<Option<Measurement>> {
    if opts.record_only {
        return Ok(None);
    }
    let mut m = Measurement::new(&config.measurement(), !opts.full_frame)
        .map_err(|e| BadInput::new(format!("cannot build the measurement: {e}")))?;
    if let Some(pb) = playback.filter(|_| kind.as_fast) {
        let hooks = page.handle();
        for s in &pb.rec.utm {
            m.utm_mut().push(*s);
            hooks.on_utm(&UtmEvent::Sample(*s));
        }
    }
    Ok(Some(m))
}

/// The frames' sources: the cameras (a recording's frames too: `replay --realtime` sets every
/// camera's source to it), or — as fast as it goes, or paced without dropping — one reader
/// handing the recording's frames over in time order. At the recorded pace (paced or not)
/// the recording's UTM samples are handed over with the frames; their receiving side is
/// returned for the run's UTM. `run` keeps retrying a camera that is not
/// there yet; a replay's recording must open.
struct Inputs {
    sources: Option<Sources>,
    reader: Option<std::thread::JoinHandle<u64>>,
}

impl Inputs {
    fn start(
        config: &Config,
        kind: RunKind,
        playback: Option<&Playback>,
        tx: mpsc::Sender<SourceEvent>,
        stop: Arc<AtomicBool>,
    ) -> Result<(Inputs, Option<utm::InStepLink>)> {
        let policy = if kind.replaying { OpenPolicy::Require } else { OpenPolicy::Retry };
        let (players_utm, link) = playback.and_then(utm::in_step_link).unzip();
        let inputs = match playback.filter(|_| kind.lossless) {
            Some(pb) if pb.pacing == Pacing::Paced => {
                Inputs { sources: None, reader: Some(spawn_paced_reader(&pb.rec, tx, players_utm, stop)?) }
            }
            Some(pb) => Inputs { sources: None, reader: Some(spawn_reader(&pb.rec, pb.progress, tx, stop)?) },
            None => Inputs { sources: Some(crate::graph::sources::start(config, policy, tx, stop, players_utm)?), reader: None },
        };
        Ok((inputs, link))
    }

    /// Waits (at most 5 s) for the capture threads and the reader; the frames the reader skipped.
    async fn join(self) -> Option<u64> {
        let Inputs { sources, reader } = self;
        let threads_done = tokio::task::spawn_blocking(move || {
            if let Some(s) = sources {
                s.join();
            }
            reader.map(|r| r.join().unwrap_or_default())
        });
        tokio::time::timeout(Duration::from_secs(5), threads_done).await.ok().and_then(|r| r.ok()).flatten()
    }
}

/// A run once everything is started: the queue, the solver, the sinks' thread and the
/// outputs' handles.
struct Running {
    queue: Arc<SetQueue>,
    heartbeat: Arc<AtomicU64>,
    frame_drops: Arc<FrameDrops>,
    solver: Option<std::thread::JoinHandle<Solved>>,
    forwarder: tokio::task::JoinHandle<()>,
    /// The sinks' thread (taken at shutdown).
    fanout: Option<Arc<Fanout>>,
    outputs: Outputs,
    assembler: FrameSetAssembler,
    /// The recorder's frames and UTM samples (ended before the recorder is finished).
    rec_tx: Option<tagdeflect_sinks::recorder::RecorderTx>,
    /// Keeps the UTM's server up (the simulated UTM) while the run goes.
    _utm: utm::UtmGuard,
}

impl Running {
    /// Starts the UTM forwarder, the sinks' thread and the solver thread.
    fn start(
        config: &Config,
        kind: RunKind,
        mut outputs: Outputs,
        measure: Option<Measurement>,
        run_utm: utm::Utm,
        page: &Page,
        smooth_lag_sets: Option<usize>,
    ) -> Result<Running> {
        let frame_drops = Arc::new(FrameDrops::new(config.cameras.len()));
        let utm::Utm { events, feed: utm_feed, guard } = run_utm;
        // UTM events to the solver (std channel: the solver is a plain thread) and the recorder.
        // Bounded (drop-oldest): memory stays flat while the solver waits, and in `record`
        // (no solver) nothing accumulates.
        let (solver_utm_tx, solver_utm_rx) = relay(UTM_RELAY_SAMPLES);
        let watchers = UtmWatchers {
            page: page.handle(),
            tests: outputs.tests.clone(),
            files: UtmFiles::for_run(
                config.output.feed.as_deref(),
                outputs.run_report.as_ref().map(|r| r.dir()),
                !kind.replaying && !kind.record_only,
            ),
            recorder: outputs.recorder.as_ref().map(|r| r.sender()),
        };
        let forwarder = utm::forward(events, watchers, solver_utm_tx);
        let queue = Arc::new(SetQueue::new());
        let heartbeat = Arc::new(AtomicU64::new(0));
        let overflow = if kind.lossless { Overflow::Wait } else { Overflow::DropOldest };
        let sinks = std::mem::take(&mut outputs.sinks);
        let fanout = Arc::new(Fanout::start_with(sinks, overflow).context("cannot start the sinks' thread")?);
        let solver = match measure {
            None => None,
            Some(mut measure) => {
                // Smoothing looks ahead: only where nothing waits for the line (an as-fast replay).
                let smoothing = smooth_lag_sets.filter(|_| kind.as_fast).map(|lag| Smoothing::attach(&mut measure, lag));
                let status = LineStatus {
                    tests: outputs.tests.clone(),
                    recorder: outputs.recorder.as_ref().map(|r| r.status()),
                    frame_drops: frame_drops.clone(),
                    broker: outputs.broker.clone(),
                };
                let io = SolverIo {
                    queue: queue.clone(),
                    utm: solver_utm_rx,
                    utm_feed,
                    fanout: fanout.clone(),
                    status: (!kind.as_fast).then_some(status),
                    heartbeat: heartbeat.clone(),
                    smoothing,
                };
                let config = config.clone();
                Some(std::thread::Builder::new().name("solver".into()).spawn(move || solver_loop(config, measure, io))?)
            }
        };
        // A recording read in time order closes each set as the next one starts; a live run's
        // frames of different cameras may arrive out of order, so its assembler keeps several
        // sets open, learns each camera's arrival delay and waits for a steadily late camera.
        let assembler = if kind.replaying {
            let open_sets = if kind.lossless { 1 } else { 3 };
            FrameSetAssembler::with_open_sets(config.cameras.len(), config.sync.tolerance_ms, open_sets)
        } else {
            let names = config.cameras.iter().map(|c| c.name.clone()).collect();
            FrameSetAssembler::live(names, config.sync.tolerance_ms, wait_rule(config))
        };
        let rec_tx = outputs.recorder.as_ref().map(|r| r.sender());
        Ok(Running { queue, heartbeat, frame_drops, solver, forwarder, fanout: Some(fanout), outputs, assembler, rec_tx, _utm: guard })
    }

    /// The assembler: until the sources end, a stop signal or the duration. Returns the
    /// frames seen.
    async fn assemble(
        &mut self,
        config: &Config,
        opts: &LiveOptions,
        kind: RunKind,
        src_rx: &mut mpsc::Receiver<SourceEvent>,
        page: &Page,
        stop_signals: &mut StopSignals,
    ) -> u64 {
        let mut watchdog = Watchdog::new(self.heartbeat.clone(), opts.record_only);
        // A set waits for its missing cameras a frame period (at least 50 ms), or longer for a
        // camera whose frames steadily arrive later (learned by the assembler, bounded).
        let set_wait = wait_rule(config).base();
        let mut tick = tokio::time::interval(Duration::from_millis(((config.sync.tolerance_ms as u64) / 2).max(5)));
        // An absurd duration (from the library API) means no deadline rather than a panic.
        let deadline =
            opts.duration_s.and_then(|s| Duration::try_from_secs_f64(s).ok()).and_then(|d| tokio::time::Instant::now().checked_add(d));
        let mut frames_seen = 0u64;
        loop {
            let until_deadline = async {
                match deadline {
                    Some(d) => tokio::time::sleep_until(d).await,
                    None => std::future::pending().await,
                }
            };
            tokio::select! {
                ev = src_rx.recv() => match page.observe(ev) {
                    None => break, // every source ended (a recording was played out)
                    Some(ev) => frames_seen += self.on_source(config, kind, ev),
                },
                _ = tick.tick() => {
                    if !kind.replaying {
                        for set in self.assembler.poll(set_wait) {
                            self.queue.push(set);
                        }
                        if let Some(d) = self.assembler.arrival_delays() {
                            self.frame_drops.set_delays(d, tagdeflect_core::clock::now_epoch_ns());
                        }
                    }
                    watchdog.tick();
                }
                why = stop_signals.recv() => { tracing::info!("{why}"); break; }
                _ = until_deadline => { tracing::info!("duration reached: stopping"); break; }
            }
        }
        frames_seen
    }

    /// One source event; the frames it brought (0 or 1).
    fn on_source(&mut self, config: &Config, kind: RunKind, ev: SourceEvent) -> u64 {
        match ev {
            SourceEvent::Frame(f) => {
                if let Some(tx) = &self.rec_tx {
                    tx.frame(f.clone());
                }
                if let Some(t) = &self.outputs.tests {
                    t.on_frame(&f);
                }
                if !kind.record_only {
                    for set in self.assembler.push(f) {
                        self.queue.push_by(set, kind.lossless);
                    }
                    self.frame_drops.set_late(self.assembler.late_by_camera());
                }
                return 1;
            }
            SourceEvent::Lost { camera, reason } => {
                tracing::error!(camera = %config.cameras[camera].name, "camera lost: {reason}; reopening")
            }
            SourceEvent::Reopened { camera } => tracing::info!(camera = %config.cameras[camera].name, "camera back"),
            SourceEvent::Dropped { camera, count, why } => {
                self.frame_drops.add_source(camera, count);
                tracing::debug!(camera = %config.cameras[camera].name, count, "frames dropped: {why:?}");
            }
        }
        0
    }
}

/// The set wait's rule, from the fastest camera's rate (see `tagdeflect_io::sync`).
fn wait_rule(config: &Config) -> WaitRule {
    let max_fps = config.cameras.iter().filter_map(|c| c.fps).fold(0.0f64, f64::max);
    WaitRule::for_fps((max_fps > 0.0).then_some(max_fps))
}

/// The systemd watchdog, pinged at a third of its interval (at most once a second) while the
/// solver's heartbeat is fresh: liveness, not solved sets — the loop runs, sources are read or
/// retried, and the solver is not stuck (a camera unplugged for a minute is not a reason to be
/// killed; a hung solver is). It also has the one process clock checked once a second.
struct Watchdog {
    heartbeat: Arc<AtomicU64>,
    started: Instant,
    every: Option<Duration>,
    last_ping: Option<Instant>,
    last_clock_check: Instant,
    record_only: bool,
}

impl Watchdog {
    fn new(heartbeat: Arc<AtomicU64>, record_only: bool) -> Self {
        let started = Instant::now();
        heartbeat.store(1, Ordering::Relaxed);
        let every = std::env::var("WATCHDOG_USEC")
            .ok()
            .and_then(|v| v.parse::<u64>().ok())
            .map(|us| Duration::from_micros(us / 3).min(Duration::from_secs(1)));
        Self { heartbeat, started, every, last_ping: None, last_clock_check: Instant::now(), record_only }
    }

    fn tick(&mut self) {
        if self.last_clock_check.elapsed() >= Duration::from_secs(1) {
            self.last_clock_check = Instant::now();
            // A stepped wall clock re-maps the one process clock (logged there).
            let _ = tagdeflect_core::clock::process().check_step();
        }
        let beat_now = self.started.elapsed().as_millis() as u64 + 1;
        let solver_alive = self.record_only || beat_now.saturating_sub(self.heartbeat.load(Ordering::Relaxed)) < WATCHDOG_STALE_MS;
        if let Some(every) = self.every {
            if solver_alive && self.last_ping.is_none_or(|t| t.elapsed() >= every) {
                self.last_ping = Some(Instant::now());
                let _ = sd_notify::notify(false, &[sd_notify::NotifyState::Watchdog]);
            }
        }
    }
}

/// What a run did, once everything stopped.
struct RunEnd {
    bad_frames: Option<u64>,
    late_frames: u64,
    solved: Option<Solved>,
    solver_panicked: bool,
}

impl Running {
    /// Finishes the queued sets, waits for the sources, the solver, the recorder and the
    /// sinks, drains the broker and writes the run's report.
    async fn shutdown(mut self, kind: RunKind, mut src_rx: mpsc::Receiver<SourceEvent>, inputs: Inputs, frames_seen: u64) -> RunEnd {
        src_rx.close();
        while let Ok(ev) = src_rx.try_recv() {
            if let (SourceEvent::Frame(f), false) = (ev, kind.record_only) {
                for set in self.assembler.push(f) {
                    self.queue.push_by(set, kind.lossless);
                }
            }
        }
        for set in self.assembler.flush() {
            self.queue.push_by(set, kind.lossless);
        }
        self.queue.close();
        let bad_frames = inputs.join().await;
        let (solved, solver_panicked) = match self.solver.take() {
            None => (None, false),
            Some(s) => match tokio::task::spawn_blocking(move || s.join()).await {
                Ok(Ok(done)) => (Some(done), false),
                Ok(Err(_)) => (None, true),
                Err(_) => (None, false),
            },
        };
        self.finish_outputs(frames_seen).await;
        RunEnd { bad_frames, late_frames: self.assembler.late_frames(), solved, solver_panicked }
    }

    /// The recorder, the sinks, the broker and the report, in that order.
    async fn finish_outputs(&mut self, frames_seen: u64) {
        // The forwarder holds a sender of the recorder: end it before waiting for the recorder.
        self.forwarder.abort();
        let _ = (&mut self.forwarder).await;
        self.rec_tx = None;
        let rec_status = self.outputs.recorder.as_ref().map(|r| r.status());
        if let Some(r) = self.outputs.recorder.take() {
            tokio::task::spawn_blocking(move || r.finish()).await.ok();
        }
        if let Some(t) = self.outputs.tests.clone() {
            tokio::task::spawn_blocking(move || t.finish_test_frames()).await.ok();
        }
        // Every queued line reaches every sink before the broker's buffer is drained.
        match self.fanout.take().map(Arc::try_unwrap) {
            Some(Ok(f)) => drop(tokio::task::spawn_blocking(move || f.finish()).await),
            Some(Err(_)) => tracing::error!("the sinks are still in use at shutdown"),
            None => {}
        }
        if let Some(b) = &self.outputs.broker {
            b.finish().await;
        }
        let dropped = self.queue.dropped();
        let rec_dropped = rec_status.as_ref().map_or(0, |s| s.dropped_frames());
        tracing::info!(frames = frames_seen, dropped_sets = dropped, recorder_dropped = rec_dropped, "stopped");
        if let Some(r) = self.outputs.run_report.take() {
            tokio::task::spawn_blocking(move || r.finish()).await.ok();
        }
    }
}

impl RunEnd {
    /// Logs an as-fast replay's figures, keeps a replay's page up until a stop signal, and
    /// says how the run ended: an empty replay is bad input, a failed solver a runtime failure.
    async fn report(
        self,
        kind: RunKind,
        playback: Option<&Playback>,
        started_at: Instant,
        page: &Page,
        signals: &mut StopSignals,
    ) -> Result<()> {
        if let (true, Some(done)) = (kind.as_fast, &self.solved) {
            tracing::info!(
                sets = done.sets,
                bad_frames = self.bad_frames.unwrap_or(0),
                late_frames = self.late_frames,
                full_frame_searches = done.stats.full_frame_searches,
                window_searches = done.stats.window_searches,
                tracked_tags = done.stats.tracked_tags,
                "replay done in {:.2} s",
                started_at.elapsed().as_secs_f64()
            );
            if done.sets == 0 {
                let dir = playback.map(|p| p.rec.dir.display().to_string()).unwrap_or_default();
                return Err(BadInput::new(format!("{dir}: no frame could be read, nothing was solved")).into());
            }
        }
        if kind.replaying && kind.linger && page.is_served() {
            page.on_finished();
            signals.linger().await;
        }
        if self.solver_panicked {
            return Err(anyhow::Error::new(tagdeflect_core::RuntimeFailure::new(
                "the solver thread failed (see the log); frame sets after the failure were not measured",
            )));
        }
        Ok(())
    }
}
