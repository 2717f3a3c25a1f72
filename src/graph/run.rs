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
use std::collections::VecDeque;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};
use tokio::sync::{mpsc, watch};

use crate::config::{CameraSource, Config};
use crate::frame::{Frame, FrameSet};
use crate::graph::page::{HttpOptions, Page};
use crate::pipeline::journal::{FrameDrops, JournalSummary, SUMMARY_INTERVAL};
use crate::pipeline::measure::Measurement;
use crate::recording::Recording;
use crate::sinks::feed::FeedWriter;
use crate::sinks::recorder::{Recorder, RecorderStatus};
use crate::sources::{OpenPolicy, SourceEvent};
use crate::sync::FrameSetAssembler;
use crate::utm::modbus::{run_poller, UtmEvent};
use crate::utm::relay::{relay, RelayReceiver};
use tagdeflect_sinks::{Fanout, FeedFileSink, Finished, LineSink, Overflow};

/// Frame sets waiting for the solver at most; older ones are dropped first.
pub const QUEUE_SETS: usize = 2;

/// How a recording is played through the graph (see the module doc).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Pacing {
    /// At its recorded pace, one player per camera, as a run would have met it.
    Recorded,
    /// As fast as the measurement goes, in time order, nothing dropped.
    AsFast,
}

/// A recording as the graph's source.
struct Playback {
    rec: Recording,
    pacing: Pacing,
    /// A progress bar on stderr ([`Pacing::AsFast`], when stderr is a terminal).
    progress: bool,
}

/// Options of a live run.
#[derive(Debug, Clone, Default)]
pub struct LiveOptions {
    /// Save a recording into this new folder.
    pub record: Option<PathBuf>,
    /// Stop after this many seconds.
    pub duration_s: Option<f64>,
    /// Record only: no detection or solving (`tagdeflect record`).
    pub record_only: bool,
    /// Write the feed to stdout as well as to `[output] feed`.
    pub feed_to_stdout: bool,
    /// Force full-frame detection.
    pub full_frame: bool,
    /// Serve the live page (`demo`, `replay --http`); else `[output] http` decides.
    pub http: Option<HttpOptions>,
    /// Smooth the lines with this many frame sets after them (`replay --smooth`: a fixed-lag
    /// RTS smoother over the temporal estimate, `estimate::smooth`); as-fast replays only.
    pub smooth_lag_sets: Option<usize>,
}

/// `run`, `record` and `demo`: live sources from the config.
pub fn run(config: Config, opts: LiveOptions) -> Result<()> {
    runtime()?.block_on(run_async(config, opts, None, Vec::new()))
}

/// `replay DIR [--http ADDR]` (without `--realtime`): the recording as fast as it goes
/// ([`Pacing::AsFast`]), the feed to stdout; with the page, it stays up after the recording is
/// consumed until SIGINT/SIGTERM.
pub fn replay(dir: &std::path::Path, config: Option<Config>, full_frame: bool, http: Option<HttpOptions>) -> Result<()> {
    replay_smoothed(dir, config, full_frame, http, None)
}

/// [`replay`], the lines smoothed with `smooth_lag_sets` frame sets after them when given
/// (`replay --smooth`; needs `[measure] estimator = "temporal"`).
pub fn replay_smoothed(
    dir: &std::path::Path,
    config: Option<Config>,
    full_frame: bool,
    http: Option<HttpOptions>,
    smooth_lag_sets: Option<usize>,
) -> Result<()> {
    let rec = crate::pipeline::replay::open(dir, config)?;
    if smooth_lag_sets.is_some() && rec.config.measure.estimator != tagdeflect_estimate::temporal::Estimator::Temporal {
        return Err(crate::BadInput::new(format!(
            "{}: --smooth needs [measure] estimator = \"temporal\" (the config in force says \"per_set\")",
            rec.dir.join("tagdeflect.toml").display()
        ))
        .into());
    }
    let progress = std::io::IsTerminal::is_terminal(&std::io::stderr());
    let playback = Playback { rec, pacing: Pacing::AsFast, progress };
    play(playback, LiveOptions { full_frame, http, smooth_lag_sets, ..LiveOptions::default() }, vec![FeedWriter::stdout()])
}

/// `replay --realtime`: the recording's frames at their recorded pace through the live
/// pipeline (same drop policy as `run`, drops counted); the feed goes to stdout.
pub fn replay_realtime(dir: &std::path::Path, config: Option<Config>, full_frame: bool) -> Result<()> {
    replay_realtime_http(dir, config, full_frame, None)
}

/// `replay --realtime [--http ADDR]`: as [`replay_realtime`], serving the live page; with
/// the page, it stays up after the recording is consumed until SIGINT/SIGTERM.
pub fn replay_realtime_http(dir: &std::path::Path, config: Option<Config>, full_frame: bool, http: Option<HttpOptions>) -> Result<()> {
    let rec = crate::pipeline::replay::open(dir, config)?;
    let playback = Playback { rec, pacing: Pacing::Recorded, progress: false };
    play(playback, LiveOptions { full_frame, http, ..LiveOptions::default() }, vec![FeedWriter::stdout()])
}

/// A recording's frames at their recorded pace through the live pipeline, the feed to
/// `feeds` (`replay --realtime`, `bench --realtime`).
pub fn replay_paced(rec: Recording, full_frame: bool, feeds: Vec<FeedWriter>) -> Result<()> {
    play(Playback { rec, pacing: Pacing::Recorded, progress: false }, LiveOptions { full_frame, ..LiveOptions::default() }, feeds)
}

fn play(playback: Playback, opts: LiveOptions, feeds: Vec<FeedWriter>) -> Result<()> {
    let rec = &playback.rec;
    let mut cfg = rec.config.clone();
    // A replay's feed goes to `feeds` only, never to the recorded run's feed file.
    cfg.output.feed = None;
    // Every camera plays its recorded frames: the recording is the source.
    for cam in &mut cfg.cameras {
        cam.source = CameraSource::Recording { dir: rec.dir.clone() };
    }
    // Nor is the recorded run's page served: only `--http` does.
    cfg.output.http = None;
    runtime()?.block_on(run_async(cfg, opts, Some(playback), feeds))
}

fn runtime() -> Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().context("cannot start the async runtime")
}

/// A bounded queue that drops its oldest entry when full.
struct SetQueue {
    inner: Mutex<(VecDeque<(FrameSet, Instant)>, bool)>,
    ready: Condvar,
    /// A set was taken (for [`SetQueue::push_wait`]).
    room: Condvar,
    dropped: AtomicU64,
}

impl SetQueue {
    fn new() -> Self {
        Self { inner: Mutex::new((VecDeque::new(), false)), ready: Condvar::new(), room: Condvar::new(), dropped: AtomicU64::new(0) }
    }
    fn push(&self, set: FrameSet) {
        let mut g = self.inner.lock().expect("queue lock");
        if g.0.len() >= QUEUE_SETS {
            g.0.pop_front();
            self.dropped.fetch_add(1, Ordering::Relaxed);
        }
        g.0.push_back((set, Instant::now()));
        self.ready.notify_one();
    }
    /// Queues `set`, waiting while the queue is full ([`Pacing::AsFast`]: nothing dropped).
    fn push_wait(&self, set: FrameSet) {
        let mut g = self.inner.lock().expect("queue lock");
        while g.0.len() >= QUEUE_SETS && !g.1 {
            g = self.room.wait(g).expect("queue lock");
        }
        if g.1 {
            // The solver has ended (it failed): nobody takes the set.
            self.dropped.fetch_add(1, Ordering::Relaxed);
            return;
        }
        g.0.push_back((set, Instant::now()));
        self.ready.notify_one();
    }
    /// Queues `set` by the run's policy: drop-oldest, or wait when `lossless`.
    fn push_by(&self, set: FrameSet, lossless: bool) {
        if lossless {
            self.push_wait(set)
        } else {
            self.push(set)
        }
    }
    fn close(&self) {
        self.inner.lock().expect("queue lock").1 = true;
        self.ready.notify_all();
        self.room.notify_all();
    }
    /// Next set (`Some(Some)`), nothing within `wait` (`Some(None)`), or `None` once closed
    /// and empty.
    #[allow(clippy::option_option)]
    fn pop_timeout(&self, wait: Duration) -> Option<Option<(FrameSet, Instant)>> {
        let deadline = Instant::now() + wait;
        let mut g = self.inner.lock().expect("queue lock");
        loop {
            if let Some(x) = g.0.pop_front() {
                self.room.notify_one();
                return Some(Some(x));
            }
            if g.1 {
                return None;
            }
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Some(None);
            }
            g = self.ready.wait_timeout(g, left).expect("queue lock").0;
        }
    }
}

async fn run_async(config: Config, opts: LiveOptions, playback: Option<Playback>, feeds: Vec<FeedWriter>) -> Result<()> {
    let started_at = Instant::now();
    // The stop signals are watched before anything starts: one that comes while the page,
    // the tests or the sources start up (systemd may stop a unit at any time) ends the run
    // at the first turn of the loop below, as it does later (last sync, report, recorder
    // drained) — never the default action, which would kill the process where it stands.
    // A closed terminal or a `kill -HUP` ends the run as SIGTERM does.
    let mut stop_signals = StopSignals::watch()?;
    let replaying = playback.is_some();
    // Every hand-off waits instead of dropping (see the module doc).
    let lossless = playback.as_ref().is_some_and(|p| p.pacing == Pacing::AsFast);
    let ncam = config.cameras.len();
    let stop = Arc::new(AtomicBool::new(false));
    let (src_tx, mut src_rx) = mpsc::channel::<SourceEvent>(4 * ncam.max(1));
    let (shutdown_tx, shutdown_rx) = watch::channel(false);

    // Sinks first: an unwritable output is reported before any camera starts.
    let mode = match playback.as_ref().map(|p| p.pacing) {
        None => "live",
        Some(Pacing::Recorded) => "realtime",
        Some(Pacing::AsFast) => "replay",
    };
    let page = Page::start(&config, opts.http, mode).await?;
    let record_dir = opts.record.clone().or_else(|| {
        (!replaying)
            .then(|| config.output.record.as_ref().map(|d| d.join(chrono::Utc::now().format("%Y%m%dT%H%M%SZ").to_string())))
            .flatten()
    });
    let mut outputs = Outputs::build(&config, &opts, replaying, record_dir.as_deref(), feeds, &page)?;
    #[cfg(feature = "mqtt")]
    if let Some(m) = &outputs.mqtt {
        page.on_mqtt(m.stats());
    }
    // The tests (`[output] tests`): their lines are a sink, their control API on the page.
    let tests = match (&config.output.tests, replaying || opts.record_only) {
        (Some(dir), false) => {
            let t = crate::graph::lab_tests::start(&config, dir, &page)?;
            outputs.sinks.push(Box::new(tagdeflect_sinks::lab_test::LabTestSink(t.clone())));
            // The archive knows the tests: each record to `<topic>/labtest/<id>`.
            #[cfg(feature = "mqtt")]
            if let Some(m) = &outputs.mqtt {
                let m = m.clone();
                t.set_on_record(Box::new(move |r| m.publish_lab_test(r)));
            }
            Some(t)
        }
        (None, false) if config.output.auto_test.is_some() => {
            return Err(crate::BadInput::new(
                "[output.auto_test]: automatic tests need the tests' folder: set [output] tests or --tests DIR".to_string(),
            )
            .into())
        }
        _ => None,
    };
    // The recorder (sinks::recorder): retries after write errors; state in every feed line.
    let recorder = match &record_dir {
        Some(dir) => Some(
            Recorder::start(dir, &config, config.output.record_format, 8 * ncam.max(1))
                .with_context(|| format!("cannot record into {}", dir.display()))?,
        ),
        None => None,
    };
    if let Some(dir) = &record_dir {
        tracing::info!("recording into {}", dir.display());
    }
    let rec_tx = recorder.as_ref().map(Recorder::sender);
    let rec_status = recorder.as_ref().map(Recorder::status);
    let frame_drops = Arc::new(FrameDrops::new(ncam));
    if let (Some(dir), Some(st)) = (&record_dir, &rec_status) {
        page.on_recording(dir, st.clone());
    }

    // The measurement is built before any source starts: a detector option it cannot take
    // is a config error (exit 2), never a daemon that captures without measuring.
    let mut measure = if opts.record_only {
        None
    } else {
        Some(
            Measurement::new(&config.measurement(), !opts.full_frame)
                .map_err(|e| crate::BadInput::new(format!("cannot build the measurement: {e}")))?,
        )
    };
    // Smoothing looks ahead: only where nothing waits for the line (an as-fast replay).
    let smooth_lag_sets = opts.smooth_lag_sets.filter(|_| lossless);
    if let (Some(_), Some(m)) = (smooth_lag_sets, measure.as_mut()) {
        m.keep_steps();
    }
    // As fast as it goes: the recording's whole UTM stream is known before its first set.
    if let (Some(pb), Some(m)) = (playback.as_ref().filter(|_| lossless), measure.as_mut()) {
        let hooks = page.handle();
        for s in &pb.rec.utm {
            m.utm_mut().push(*s);
            hooks.on_utm(&UtmEvent::Sample(*s));
        }
    }

    // Cameras (a recording's frames too: `replay --realtime` sets every camera's source to it).
    // `run` keeps retrying a camera that is not there yet; a replay's recording must open.
    // As fast as it goes, one reader hands the recording's frames over in time order.
    let policy = if replaying { OpenPolicy::Require } else { OpenPolicy::Retry };
    let (sources, reader) = match playback.as_ref().filter(|_| lossless) {
        Some(pb) => (None, Some(spawn_reader(&pb.rec, pb.progress, src_tx.clone(), stop.clone())?)),
        None => (Some(crate::graph::sources::start(&config, policy, src_tx.clone(), stop.clone())?), None),
    };
    #[cfg(feature = "sim")]
    let rig = sources.as_ref().and_then(|s| s.rig.clone());
    drop(src_tx);

    // UTM.
    let (utm_tx, mut utm_rx) = mpsc::channel::<UtmEvent>(256);
    #[cfg(feature = "sim")]
    let mut _sim_utm = None;
    // An as-fast replay has its UTM samples already (above) and marks no UTM state.
    // A replay at the recorded pace plays the recording's UTM samples whether or not its
    // config has a `[utm]` (a folder may carry `utm.jsonl` from a UTM configured elsewhere):
    // each set then waits for the sample after it, as in a run.
    let utm_feed = match (&playback, &config.utm) {
        // A recorded stream is up from its first sample: the first set waits for it too.
        (Some(pb), _) if pb.pacing == Pacing::Recorded && !pb.rec.utm.is_empty() => {
            Some(UtmFeed { wait: recorded_utm_wait(&pb.rec), up_at_start: true })
        }
        (Some(_), _) => None,
        (None, Some(u)) => Some(UtmFeed { wait: Duration::from_secs_f64(2.5 / u.poll_hz), up_at_start: false }),
        (None, None) => None,
    };
    if let Some(pb) = &playback {
        match pb.pacing {
            Pacing::Recorded => drop(tokio::spawn(play_utm(pb.rec.clone(), utm_tx))),
            Pacing::AsFast => drop(utm_tx),
        }
    } else if let Some(ucfg) = &config.utm {
        #[cfg(feature = "sim")]
        let ucfg = if ucfg.address.is_sim() {
            let rig = rig.clone().expect("sim rig built");
            let (polled, server) = crate::utm::sim_server::start_sim_utm_with_outage(ucfg, rig.utm_model(), rig.utm_outage())
                .await
                .context("cannot start the simulated UTM")?;
            _sim_utm = Some(server);
            polled
        } else {
            ucfg.clone()
        };
        #[cfg(not(feature = "sim"))]
        let ucfg = if ucfg.address.is_sim() {
            return Err(crate::BadInput::new("utm.address = \"sim\": this build has no simulated UTM: build with the `sim` feature").into());
        } else {
            ucfg.clone()
        };
        let rx = shutdown_rx.clone();
        tokio::spawn(async move {
            if let Err(e) = run_poller(ucfg, utm_tx, rx).await {
                tracing::error!("UTM: {e}");
            }
        });
    } else {
        drop(utm_tx);
    }
    let _ = sd_notify::notify(false, &[sd_notify::NotifyState::Ready]);
    tracing::info!(cameras = ncam, "sources started; measuring");

    // UTM events to the solver (std channel: the solver is a plain thread) and the recorder.
    // Bounded (drop-oldest): memory stays flat while the solver waits, and in `record`
    // (no solver) nothing accumulates.
    let (solver_utm_tx, solver_utm_rx) = relay(UTM_RELAY_SAMPLES);
    let utm_files = crate::graph::utm_file::UtmFiles::for_run(
        config.output.feed.as_deref(),
        outputs.run_report.as_ref().map(|r| r.dir()),
        !replaying && !opts.record_only,
    );
    let forwarder = {
        let rec_tx = rec_tx.clone();
        let fwd_page = page.handle();
        let fwd_tests = tests.clone();
        tokio::spawn(async move {
            while let Some(ev) = utm_rx.recv().await {
                fwd_page.on_utm(&ev);
                if let (UtmEvent::Sample(s), Some(t)) = (&ev, &fwd_tests) {
                    t.on_utm(s);
                }
                if let UtmEvent::Sample(s) = &ev {
                    utm_files.push(s);
                }
                if let (UtmEvent::Sample(s), Some(tx)) = (&ev, &rec_tx) {
                    tx.utm(*s);
                }
                solver_utm_tx.send(ev);
            }
        })
    };

    // Solver thread. It beats `heartbeat` at least once a second while it runs (idle or
    // solving); the watchdog is pinged from the assembler loop while the beat is fresh.
    let queue = Arc::new(SetQueue::new());
    let heartbeat = Arc::new(AtomicU64::new(0));
    let Outputs { sinks, mqtt, run_report } = outputs;
    let overflow = if lossless { Overflow::Wait } else { Overflow::DropOldest };
    let fanout = Arc::new(Fanout::start_with(sinks, overflow).context("cannot start the sinks' thread")?);
    let solver = match measure {
        None => {
            drop(solver_utm_rx);
            None
        }
        Some(measure) => {
            let queue = queue.clone();
            let config = config.clone();
            let heartbeat = heartbeat.clone();
            let status = LineStatus {
                tests: tests.clone(),
                recorder: rec_status.clone(),
                frame_drops: frame_drops.clone(),
                #[cfg(feature = "mqtt")]
                mqtt: mqtt.clone(),
            };
            let fanout = fanout.clone();
            let out = SolverOut { fanout, status: (!lossless).then_some(status) };
            Some(
                std::thread::Builder::new()
                    .name("solver".into())
                    .spawn(move || solver_loop(config, measure, queue, solver_utm_rx, out, utm_feed, heartbeat, smooth_lag_sets))?,
            )
        }
    };
    let started = Instant::now();
    let beat_now = move || started.elapsed().as_millis() as u64 + 1;
    heartbeat.store(beat_now(), Ordering::Relaxed);
    // Pinged at a third of systemd's watchdog interval, at most once a second.
    let watchdog_every = std::env::var("WATCHDOG_USEC")
        .ok()
        .and_then(|v| v.parse::<u64>().ok())
        .map(|us| Duration::from_micros(us / 3).min(Duration::from_secs(1)));
    let mut last_ping: Option<Instant> = None;
    let mut last_clock_check = Instant::now();

    // Assembler: until the sources end or a stop is asked for.
    // Live frames of different cameras may arrive out of order by a frame or two.
    // A recording read in time order closes each set as the next one starts.
    let open_sets = if lossless { 1 } else { 3 };
    let mut assembler = FrameSetAssembler::with_open_sets(ncam, config.sync.tolerance_ms, open_sets);
    // A set waits for its missing cameras at most a frame period (and at least 50 ms).
    let max_fps = config.cameras.iter().filter_map(|c| c.fps).fold(0.0f64, f64::max);
    let set_wait = Duration::from_secs_f64(if max_fps > 0.0 { (1.0 / max_fps).max(0.05) } else { 0.1 });
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
                Some(SourceEvent::Frame(f)) => {
                    frames_seen += 1;
                    if let Some(tx) = &rec_tx {
                        tx.frame(f.clone());
                    }
                    if !opts.record_only {
                        for set in assembler.push(f) {
                            queue.push_by(set, lossless);
                        }
                        frame_drops.set_late(assembler.late_by_camera());
                    }
                }
                Some(SourceEvent::Lost { camera, reason }) => tracing::error!(camera = %config.cameras[camera].name, "camera lost: {reason}; reopening"),
                Some(SourceEvent::Reopened { camera }) => tracing::info!(camera = %config.cameras[camera].name, "camera back"),
                Some(SourceEvent::Dropped { camera, count, why }) => {
                    frame_drops.add_source(camera, count);
                    tracing::debug!(camera = %config.cameras[camera].name, count, "frames dropped: {why:?}");
                }
            },
            _ = tick.tick() => {
                if !replaying {
                    for set in assembler.poll(set_wait) {
                        queue.push(set);
                    }
                }
                if last_clock_check.elapsed() >= Duration::from_secs(1) {
                    last_clock_check = Instant::now();
                    // A stepped wall clock re-maps the one process clock (logged there).
                    let _ = crate::clock::process().check_step();
                }
                // Liveness, not solved sets: the loop runs, sources are read or retried, and
                // the solver is not stuck (a camera unplugged for a minute is not a reason to
                // be killed; a hung solver is).
                let solver_alive = opts.record_only || beat_now().saturating_sub(heartbeat.load(Ordering::Relaxed)) < WATCHDOG_STALE_MS;
                if let Some(every) = watchdog_every {
                    if solver_alive && last_ping.is_none_or(|t| t.elapsed() >= every) {
                        last_ping = Some(Instant::now());
                        let _ = sd_notify::notify(false, &[sd_notify::NotifyState::Watchdog]);
                    }
                }
            }
            why = stop_signals.recv() => { tracing::info!("{why}"); break; }
            _ = until_deadline => { tracing::info!("duration reached: stopping"); break; }
        }
    }
    // Shutdown: stop capture, finish queued sets, flush sinks.
    let _ = sd_notify::notify(false, &[sd_notify::NotifyState::Stopping]);
    stop.store(true, Ordering::SeqCst);
    let _ = shutdown_tx.send(true);
    src_rx.close();
    while let Ok(ev) = src_rx.try_recv() {
        if let (SourceEvent::Frame(f), false) = (ev, opts.record_only) {
            for set in assembler.push(f) {
                queue.push_by(set, lossless);
            }
        }
    }
    for set in assembler.flush() {
        queue.push_by(set, lossless);
    }
    queue.close();
    let threads_done = tokio::task::spawn_blocking(move || {
        if let Some(s) = sources {
            s.join();
        }
        reader.map(|r| r.join().unwrap_or_default())
    });
    let bad_frames = tokio::time::timeout(Duration::from_secs(5), threads_done).await.ok().and_then(|r| r.ok()).flatten();
    let mut solver_panicked = false;
    let mut solved = None;
    if let Some(s) = solver {
        match tokio::task::spawn_blocking(move || s.join()).await {
            Ok(Ok(done)) => solved = Some(done),
            Ok(Err(_)) => solver_panicked = true,
            Err(_) => {}
        }
    }
    // The forwarder holds a sender of the recorder: end it before waiting for the recorder.
    forwarder.abort();
    let _ = forwarder.await;
    drop(rec_tx);
    if let Some(r) = recorder {
        tokio::task::spawn_blocking(move || r.finish()).await.ok();
    }
    // Every queued line reaches every sink before the broker's buffer is drained.
    match Arc::try_unwrap(fanout) {
        Ok(f) => tokio::task::spawn_blocking(move || f.finish()).await.ok(),
        Err(_) => {
            tracing::error!("the sinks are still in use at shutdown");
            None
        }
    };
    #[cfg(feature = "mqtt")]
    if let Some(m) = &mqtt {
        m.finish(Duration::from_secs(5)).await;
    }
    #[cfg(not(feature = "mqtt"))]
    let _ = mqtt;
    let dropped = queue.dropped.load(Ordering::Relaxed);
    let rec_dropped = rec_status.as_ref().map_or(0, |s| s.dropped_frames());
    tracing::info!(frames = frames_seen, dropped_sets = dropped, recorder_dropped = rec_dropped, "stopped");
    if let Some(r) = run_report {
        tokio::task::spawn_blocking(move || r.finish()).await.ok();
    }
    if let (true, Some(done)) = (lossless, &solved) {
        tracing::info!(
            sets = done.sets,
            bad_frames = bad_frames.unwrap_or(0),
            late_frames = assembler.late_frames(),
            full_frame_searches = done.stats.full_frame_searches,
            window_searches = done.stats.window_searches,
            tracked_tags = done.stats.tracked_tags,
            "replay done in {:.2} s",
            started_at.elapsed().as_secs_f64()
        );
        if done.sets == 0 {
            let dir = playback.as_ref().map(|p| p.rec.dir.display().to_string()).unwrap_or_default();
            return Err(crate::BadInput::new(format!("{dir}: no frame could be read, nothing was solved")).into());
        }
    }
    #[cfg(feature = "http")]
    if replaying && page.is_served() {
        page.on_finished();
        crate::pipeline::replay::linger(&mut stop_signals).await?;
    }
    if solver_panicked {
        return Err(anyhow::Error::new(crate::RuntimeFailure::new(
            "the solver thread failed (see the log); frame sets after the failure were not measured",
        )));
    }
    Ok(())
}

/// What a run writes its lines to, built from the config in one place ([`Outputs::build`]):
/// every line sink in order (feed files and stdout, the report's copy of the feed, the live
/// page, the MQTT publisher), and the handles whose end takes more than a flush.
struct Outputs {
    sinks: Vec<Box<dyn LineSink>>,
    #[cfg(feature = "mqtt")]
    mqtt: Option<Arc<crate::sinks::mqtt::MqttPublisher>>,
    #[cfg(not(feature = "mqtt"))]
    mqtt: Option<std::convert::Infallible>,
    run_report: Option<crate::pipeline::run_report::RunReport>,
}

impl Outputs {
    /// Every line sink of a run; an output that cannot be opened stops the run before any
    /// camera starts.
    fn build(
        config: &Config,
        opts: &LiveOptions,
        replaying: bool,
        record_dir: Option<&std::path::Path>,
        mut feeds: Vec<FeedWriter>,
        page: &Page,
    ) -> Result<Outputs> {
        if opts.feed_to_stdout {
            feeds.push(FeedWriter::stdout());
        }
        if let Some(spec) = &config.output.feed {
            if spec == "-" {
                if !opts.feed_to_stdout {
                    feeds.push(FeedWriter::stdout());
                }
            } else {
                feeds.push(
                    FeedWriter::append(std::path::Path::new(spec))
                        .map_err(|e| crate::BadInput::new(format!("cannot open the feed output {spec}: {e}")))?,
                );
            }
        }
        // `[report]`: this run's feed copied into the report folder, the report written at the end.
        let run_report = match !replaying && !opts.record_only {
            true => crate::pipeline::run_report::RunReport::start(config)?.map(|(r, w)| {
                feeds.push(w);
                r
            }),
            false => None,
        };
        let mut sinks: Vec<Box<dyn LineSink>> = feeds.into_iter().map(|f| Box::new(FeedFileSink(f)) as Box<dyn LineSink>).collect();
        if let Some(s) = page.sink()? {
            sinks.push(s);
        }
        // `[output.control]`: the gauge as a control signal (sinks::control).
        if let Some(c) = &config.output.control {
            sinks.push(Box::new(crate::sinks::control::ControlSink::start(c).map_err(|e| crate::BadInput::new(e.to_string()))?));
        }
        // MQTT publisher (live runs only; never on a replay).
        #[cfg(feature = "mqtt")]
        let mqtt = match (&config.output.mqtt, replaying) {
            (Some(m), false) => {
                let p = Arc::new(
                    crate::sinks::mqtt::MqttPublisher::start(
                        m,
                        &config.rig_info(),
                        record_dir,
                        config.output.feed.as_deref().and_then(tagdeflect_core::feed_file::feed_path).as_deref(),
                    )
                    .map_err(crate::BadInput::new)?,
                );
                sinks.push(Box::new(crate::sinks::mqtt::MqttSink(p.clone())));
                Some(p)
            }
            _ => None,
        };
        #[cfg(not(feature = "mqtt"))]
        let mqtt = match (&config.output.mqtt, replaying, record_dir) {
            (Some(_), false, _) => {
                return Err(crate::BadInput::new("[output.mqtt]: this build has no MQTT publisher: build with the `mqtt` feature").into())
            }
            _ => None,
        };
        Ok(Outputs { sinks, mqtt, run_report })
    }
}

/// A solver heartbeat older than this stops the watchdog pings (systemd then restarts the
/// daemon after `WatchdogSec`).
const WATCHDOG_STALE_MS: u64 = 10_000;

/// A UTM feeds the run: each set waits at most `wait` for the sample after it while the UTM
/// is up (`up_at_start`: before its first event — a recorded stream).
#[derive(Debug, Clone, Copy)]
struct UtmFeed {
    wait: Duration,
    up_at_start: bool,
}

/// What the solver did, when it ended.
struct Solved {
    sets: u64,
    stats: crate::pipeline::measure::MeasureStats,
}

/// Closes the queue when the solver ends, even by a panic: a producer waiting for room
/// ([`SetQueue::push_wait`]) is let go.
struct CloseOnDrop(Arc<SetQueue>);

impl Drop for CloseOnDrop {
    fn drop(&mut self) {
        self.0.close();
    }
}

/// SIGINT, SIGTERM and SIGHUP, watched from the moment this is made (a signal that comes
/// before the first `recv` is kept for it).
pub(crate) struct StopSignals {
    int: tokio::signal::unix::Signal,
    term: tokio::signal::unix::Signal,
    hup: tokio::signal::unix::Signal,
}

impl StopSignals {
    /// Watches the three signals (inside a Tokio runtime).
    pub(crate) fn watch() -> Result<Self> {
        use tokio::signal::unix::{signal, SignalKind};
        Ok(Self {
            int: signal(SignalKind::interrupt()).context("cannot watch SIGINT")?,
            term: signal(SignalKind::terminate()).context("cannot watch SIGTERM")?,
            hup: signal(SignalKind::hangup()).context("cannot watch SIGHUP")?,
        })
    }

    /// Waits for the next stop signal; what to log ("SIGTERM: stopping", ...).
    pub(crate) async fn recv(&mut self) -> &'static str {
        tokio::select! {
            _ = self.int.recv() => "SIGINT: stopping",
            _ = self.term.recv() => "SIGTERM: stopping",
            _ = self.hup.recv() => "SIGHUP: stopping as on SIGTERM",
        }
    }
}

#[allow(clippy::too_many_arguments)]
fn solver_loop(
    config: Config,
    mut measure: Measurement,
    queue: Arc<SetQueue>,
    utm_rx: RelayReceiver,
    out: SolverOut,
    utm_feed: Option<UtmFeed>,
    heartbeat: Arc<AtomicU64>,
    smooth_lag_sets: Option<usize>,
) -> Solved {
    let mut smoother = smooth_lag_sets.map(|lag| measure.smoother(lag));
    let SolverOut { fanout, status } = out;
    let _close = CloseOnDrop(queue.clone());
    let started = Instant::now();
    let beat = || heartbeat.store(started.elapsed().as_millis() as u64 + 1, Ordering::Relaxed);
    // A live run keeps a minute of UTM samples; a run's status (`status`) marks a live line.
    let live = status.is_some();
    if live {
        measure.utm_mut().set_window(LIVE_UTM_WINDOW_NS);
    }
    let mut sets = 0u64;
    let mut last_t_ns: Option<i64> = None;
    // A gap worth a warning: ten frame periods of the slowest camera, at least 2 s.
    let min_fps = config.cameras.iter().filter_map(|c| c.fps).fold(f64::INFINITY, f64::min);
    let gap_warn_s = if min_fps.is_finite() && min_fps > 0.0 { (10.0 / min_fps).max(2.0) } else { 2.0 };
    let mut journal = JournalSummary::new(config.cameras.iter().map(|c| c.name.clone()).collect(), SUMMARY_INTERVAL);
    let mut utm_up = utm_feed.is_some_and(|u| u.up_at_start);
    let utm_configured = utm_feed.is_some();
    let utm_wait = utm_feed.map(|u| u.wait).unwrap_or_default();
    let handle = |ev: UtmEvent, m: &mut Measurement, up: &mut bool| match ev {
        UtmEvent::Sample(s) => {
            *up = true;
            m.utm_mut().push(s)
        }
        UtmEvent::Down { reason } => {
            *up = false;
            tracing::warn!("UTM down: {reason}; the feed goes on without load");
        }
        UtmEvent::Up => {
            *up = true;
            tracing::debug!("UTM up"); // the poller logs it at INFO
        }
    };
    loop {
        beat();
        let Some(popped) = queue.pop_timeout(Duration::from_secs(1)) else {
            // The lines the smoother still holds, smoothed with what there is.
            for line in smoother.as_mut().map(|s| s.finish()).unwrap_or_default() {
                fanout.send(Finished { line, set: None, observed: Arc::new(measure.observed()) });
            }
            return Solved { sets, stats: measure.stats().clone() };
        };
        let Some((set, arrived)) = popped else { continue };
        while let Some(ev) = utm_rx.try_recv() {
            handle(ev, &mut measure, &mut utm_up);
        }
        // Wait briefly for a UTM sample after the set's time, so load is interpolated, not
        // extrapolated (and `run` gives the same load as a replay of its recording).
        if utm_configured && utm_up {
            let until = Instant::now() + utm_wait;
            while measure.utm_mut().newest_t_ns().is_none_or(|t| t < set.t_ns) {
                let left = until.saturating_duration_since(Instant::now());
                if left.is_zero() {
                    break;
                }
                match utm_rx.recv_timeout(left) {
                    Some(ev) => handle(ev, &mut measure, &mut utm_up),
                    None => break,
                }
            }
        }
        // A hole in time is a hole whatever the counters say (a stalled process, a suspended
        // machine: SIGSTOP for 20 s gave contiguous seq and no dropped set).
        if let Some(prev) = last_t_ns {
            let gap_s = (set.t_ns as i128 - prev as i128) as f64 * 1e-9;
            if gap_s > gap_warn_s {
                tracing::warn!(gap_s = format!("{gap_s:.1}"), seq = set.seq, "no frame set for {gap_s:.1} s: the feed has a gap here");
            }
        }
        last_t_ns = Some(set.t_ns);
        let (mut line, _) = measure.process(&set);
        sets += 1;
        if utm_configured {
            line.utm = Some(if utm_up { "ok" } else { "down" }.to_string());
        }
        if let Some(status) = &status {
            line.dropped_sets = Some(queue.dropped.load(Ordering::Relaxed));
            line.latency_ms = Some((arrived.elapsed().as_secs_f64() * 1e4).round() / 10.0);
            status.apply(&mut line);
        }
        journal.observe(&line, measure.rejected_views_by_camera());
        // A smoothed line leaves the smoother some sets later: its frames are gone by then.
        if let Some(sm) = smoother.as_mut() {
            if let Some(line) = sm.push(line, measure.last_steps().to_vec()) {
                fanout.send(Finished { line, set: None, observed: Arc::new(measure.observed()) });
            }
            continue;
        }
        // The line is complete: the sinks take it on their own thread.
        fanout.send(Finished { line, set: Some(set), observed: Arc::new(measure.observed()) });
    }
}

/// UTM events live runs hold for the solver at most (drop-oldest; ~80 s at 50 Hz).
const UTM_RELAY_SAMPLES: usize = 4096;
/// UTM samples kept for interpolation in live runs: this far behind the newest.
const LIVE_UTM_WINDOW_NS: i64 = 60_000_000_000;

/// Where the solver's lines go: the run's shared status completes each line, then the sinks'
/// thread takes it.
struct SolverOut {
    fanout: Arc<Fanout>,
    /// A live run's status (absent in an as-fast replay: see the module doc).
    status: Option<LineStatus>,
}

/// What the solver adds to every feed line of a live run besides the measurement: the
/// state the run's other parts share (the recorder's, the cameras' drops, the MQTT buffer's
/// drops), read here so that the line is complete before any sink sees it.
struct LineStatus {
    /// The running test: its id, events and zero (`[output] tests`).
    tests: Option<Arc<tagdeflect_sinks::lab_test::LabTests>>,
    recorder: Option<Arc<RecorderStatus>>,
    frame_drops: Arc<FrameDrops>,
    #[cfg(feature = "mqtt")]
    mqtt: Option<Arc<crate::sinks::mqtt::MqttPublisher>>,
}

impl LineStatus {
    fn apply(&self, line: &mut crate::feed::FeedLine) {
        if let Some(t) = &self.tests {
            t.apply(line);
        }
        self.frame_drops.apply(line);
        if let Some(r) = &self.recorder {
            line.recording = Some(r.state().as_str().to_string());
            line.recorder_dropped = Some(r.dropped_frames());
        }
        #[cfg(feature = "mqtt")]
        if let Some(m) = &self.mqtt {
            line.mqtt_dropped = Some(m.reserve());
        }
    }
}

/// Hands a recording's frames to the assembler in time order, waiting for room
/// ([`Pacing::AsFast`]); a frame that cannot be read is logged and skipped (its set is solved
/// from the other cameras). Returns the frames skipped.
fn spawn_reader(
    rec: &Recording,
    progress: bool,
    tx: mpsc::Sender<SourceEvent>,
    stop: Arc<AtomicBool>,
) -> Result<std::thread::JoinHandle<u64>> {
    let frames = rec.frames();
    let total = rec.frames.len() as u64;
    let reader = std::thread::Builder::new().name("recording".into()).spawn(move || {
        let bar = progress.then(|| {
            let b = indicatif::ProgressBar::new(total);
            b.set_style(indicatif::ProgressStyle::with_template("{bar:40} {pos}/{len} frames  {per_sec}  ETA {eta}").expect("template"));
            b
        });
        let mut bad = 0u64;
        for read in frames {
            if stop.load(Ordering::SeqCst) {
                break;
            }
            if let Some(b) = &bar {
                b.inc(1);
            }
            match read.frame {
                Ok(frame) => {
                    if tx.blocking_send(SourceEvent::Frame(frame)).is_err() {
                        break;
                    }
                }
                Err(e) => {
                    bad += 1;
                    tracing::warn!("frame skipped: {e}");
                }
            }
        }
        if let Some(b) = bar {
            b.finish_and_clear();
        }
        bad
    });
    reader.context("cannot start the recording's reader")
}

/// How long a set waits for the UTM sample after it when a recording's UTM stream is played
/// at its pace: two and a half of its sampling intervals (median), at least 20 ms, at most 1 s.
fn recorded_utm_wait(rec: &Recording) -> Duration {
    let mut gaps: Vec<f64> =
        rec.utm.windows(2).map(|w| (w[1].t_ns as i128 - w[0].t_ns as i128) as f64 * 1e-9).filter(|g| *g > 0.0).collect();
    gaps.sort_by(f64::total_cmp);
    let median = gaps.get(gaps.len() / 2).copied().unwrap_or(0.02);
    Duration::from_secs_f64((2.5 * median).clamp(0.02, 1.0))
}

/// Sends a recording's UTM samples at their recorded pace (relative to its first frame),
/// as a live UTM would (`replay --realtime`).
async fn play_utm(rec: Recording, tx: mpsc::Sender<UtmEvent>) {
    if rec.frames.is_empty() {
        return;
    }
    // The cameras' schedule (long pauses capped alike), started within a few ms of theirs.
    let playhead = tagdeflect_io::sources::recording::Playhead::start_silent(&rec);
    let t0 = tokio::time::Instant::now();
    for s in &rec.utm {
        tokio::time::sleep_until(t0 + playhead.due(s.t_ns)).await;
        if tx.send(UtmEvent::Sample(*s)).await.is_err() {
            break;
        }
    }
}

/// Opens every source of the config and returns the first frame set (one frame of each
/// camera that delivered within `timeout`), then stops the sources (`check --config`).
pub fn grab_frame_set(config: &Config, timeout: Duration) -> Result<FrameSet> {
    runtime()?.block_on(async {
        let stop = Arc::new(AtomicBool::new(false));
        let (tx, mut rx) = mpsc::channel::<SourceEvent>(4 * config.cameras.len().max(1));
        let sources = crate::graph::sources::start(config, OpenPolicy::Require, tx.clone(), stop.clone())?;
        drop(tx);
        let mut frames: Vec<Option<Frame>> = vec![None; config.cameras.len()];
        let deadline = tokio::time::Instant::now() + timeout;
        while frames.iter().any(|f| f.is_none()) {
            match tokio::time::timeout_at(deadline, rx.recv()).await {
                Ok(Some(SourceEvent::Frame(f))) => {
                    let c = f.camera;
                    frames[c].get_or_insert(f);
                }
                Ok(Some(SourceEvent::Lost { camera, reason })) => {
                    tracing::warn!(camera = %config.cameras[camera].name, "camera lost: {reason}")
                }
                Ok(Some(_)) => {}
                Ok(None) | Err(_) => break,
            }
        }
        stop.store(true, Ordering::SeqCst);
        rx.close();
        tokio::task::spawn_blocking(move || sources.join()).await.ok();
        let frames: Vec<Frame> = frames.into_iter().flatten().collect();
        if frames.is_empty() {
            return Err(crate::BadInput::new(format!("no camera delivered a frame within {:.0} s", timeout.as_secs_f64())).into());
        }
        Ok(FrameSet::new(0, frames))
    })
}
