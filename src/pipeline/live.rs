//! The live pipeline behind `run`, `record`, `demo` and `replay --realtime`.
//!
//! ```text
//! camera threads (v4l2 / aravis / sim / recording player) ──SourceEvent──▶ assembler task
//!   assembler ──frame sets──▶ drop-oldest queue ──▶ solver thread ──feed lines──▶ sinks
//!   assembler ──frames──▶ recorder thread (optional)
//! UTM poller task ──UtmEvent──▶ solver thread (+ recorder)
//! ```
//!
//! Capture never blocks on the solver: camera threads only `try_send`, and the queue in
//! front of the solver holds at most [`QUEUE_SETS`] frame sets — when the solver falls
//! behind, the oldest set is dropped and counted, and every feed line carries the count
//! (`dropped_sets`). SIGTERM/SIGINT (or `--duration-s`) stops capture, lets the solver
//! finish the sets already queued, flushes every sink and returns `Ok` (exit 0).
//!
//! systemd: READY=1 is sent once every source is open; the watchdog is pinged by the
//! solver after each solved frame set, so a pipeline whose frame sets stop flowing is
//! restarted by systemd (`WatchdogSec` in the unit).

use anyhow::{Context, Result};
use std::collections::VecDeque;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{mpsc as std_mpsc, Arc, Condvar, Mutex};
use std::time::{Duration, Instant};
use tokio::sync::{mpsc, watch};

use crate::config::Config;
use crate::frame::{Frame, FrameSet, ImagePool};
use crate::pipeline::measure::Measurement;
use crate::recording::{Recording, RecordingWriter};
use crate::sinks::feed::FeedWriter;
use crate::sources::{clock, spawn_camera, SourceEvent};
use crate::sync::FrameSetAssembler;
use crate::utm::modbus::{run_poller, UtmEvent};
use crate::utm::UtmSample;

/// Frame sets waiting for the solver at most; older ones are dropped first.
pub const QUEUE_SETS: usize = 2;

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
}

/// `run`, `record` and `demo`: live sources from the config.
pub fn run(config: Config, opts: LiveOptions) -> Result<()> {
    runtime()?.block_on(run_async(config, opts, None, Vec::new()))
}

/// `replay --realtime`: the recording's frames at their recorded pace through the live
/// pipeline (same drop policy as `run`, drops counted); the feed goes to stdout.
pub fn replay_realtime(dir: &std::path::Path, config: Option<Config>, full_frame: bool) -> Result<()> {
    let rec = crate::pipeline::replay::open(dir, config)?;
    replay_paced(rec, full_frame, vec![FeedWriter::stdout()])
}

/// A recording's frames at their recorded pace through the live pipeline, the feed to
/// `feeds` (`replay --realtime`, `bench --realtime`).
pub fn replay_paced(rec: Recording, full_frame: bool, feeds: Vec<FeedWriter>) -> Result<()> {
    let mut cfg = rec.config.clone();
    // A replay's feed goes to `feeds` only, never to the recorded run's feed file.
    cfg.output.feed = None;
    let opts = LiveOptions { full_frame, ..LiveOptions::default() };
    runtime()?.block_on(run_async(cfg, opts, Some(rec), feeds))
}

fn runtime() -> Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().context("cannot start the async runtime")
}

/// A bounded queue that drops its oldest entry when full.
struct SetQueue {
    inner: Mutex<(VecDeque<(FrameSet, Instant)>, bool)>,
    ready: Condvar,
    dropped: AtomicU64,
}

impl SetQueue {
    fn new() -> Self {
        Self { inner: Mutex::new((VecDeque::new(), false)), ready: Condvar::new(), dropped: AtomicU64::new(0) }
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
    fn close(&self) {
        self.inner.lock().expect("queue lock").1 = true;
        self.ready.notify_all();
    }
    /// Next set, or `None` once closed and empty.
    fn pop(&self) -> Option<(FrameSet, Instant)> {
        let mut g = self.inner.lock().expect("queue lock");
        loop {
            if let Some(x) = g.0.pop_front() {
                return Some(x);
            }
            if g.1 {
                return None;
            }
            g = self.ready.wait(g).expect("queue lock");
        }
    }
}

/// What the recorder thread is given.
enum RecorderMsg {
    Frame(Frame),
    Utm(UtmSample),
}

async fn run_async(config: Config, opts: LiveOptions, recording: Option<Recording>, mut feeds: Vec<FeedWriter>) -> Result<()> {
    let ncam = config.cameras.len();
    let stop = Arc::new(AtomicBool::new(false));
    let (src_tx, mut src_rx) = mpsc::channel::<SourceEvent>(4 * ncam.max(1));
    let (shutdown_tx, shutdown_rx) = watch::channel(false);

    // Sinks first: an unwritable output is reported before any camera starts.
    if opts.feed_to_stdout {
        feeds.push(FeedWriter::stdout());
    }
    if let Some(spec) = &config.output.feed {
        if spec == "-" {
            if !opts.feed_to_stdout {
                feeds.push(FeedWriter::stdout());
            }
        } else {
            feeds.push(FeedWriter::append(std::path::Path::new(spec)).with_context(|| format!("cannot open the feed output {spec}"))?);
        }
    }
    // `[report]`: this run's feed copied into the report folder, the report written at the end.
    let run_report = match recording.is_none() && !opts.record_only {
        true => crate::report::live::RunReport::start(&config)?.map(|(r, w)| {
            feeds.push(w);
            r
        }),
        false => None,
    };
    let record_dir = opts.record.clone().or_else(|| {
        (recording.is_none())
            .then(|| config.output.record.as_ref().map(|d| d.join(chrono::Utc::now().format("%Y%m%dT%H%M%SZ").to_string())))
            .flatten()
    });
    let (rec_tx, recorder) = match &record_dir {
        Some(dir) => {
            let mut writer = RecordingWriter::create(dir, &config)
                .with_context(|| format!("cannot record into {}", dir.display()))?
                .with_format(config.output.record_format);
            tracing::info!("recording into {}", dir.display());
            let (tx, rx) = std_mpsc::sync_channel::<RecorderMsg>(8 * ncam.max(1));
            let names: Vec<String> = config.cameras.iter().map(|c| c.name.clone()).collect();
            let handle = std::thread::Builder::new().name("recorder".into()).spawn(move || {
                let mut failed = false;
                for msg in rx {
                    if failed {
                        continue;
                    }
                    let res = match msg {
                        RecorderMsg::Frame(f) => writer.write_frame(&names[f.camera], f.seq, f.t_ns, &f.image),
                        RecorderMsg::Utm(s) => writer.write_utm(&s),
                    };
                    if let Err(e) = res {
                        tracing::error!("recording stopped: {e}; the feed goes on, everything recorded so far is kept");
                        failed = true;
                    }
                }
                if let Err(e) = writer.finish() {
                    tracing::error!("recording: {e}");
                }
            })?;
            (Some(tx), Some(handle))
        }
        None => (None, None),
    };
    let recorder_drops = Arc::new(AtomicU64::new(0));

    // The simulated rig, when any part of the config asks for it.
    let wants_sim = config.cameras.iter().any(|c| c.source == "sim") || config.utm.as_ref().is_some_and(|u| u.address == "sim");
    let start_ns = clock::now_epoch_ns();
    let rig = if wants_sim && recording.is_none() {
        Some(Arc::new(crate::sources::sim::LiveRig::new(&config, start_ns).context("cannot build the simulated rig")?))
    } else {
        None
    };

    // Cameras.
    let mut threads: Vec<std::thread::JoinHandle<()>> = Vec::new();
    let mut live_cams = Vec::new();
    match &recording {
        Some(rec) => threads.push(spawn_player(rec.clone(), src_tx.clone(), stop.clone())),
        None => {
            for (i, cam) in config.cameras.iter().enumerate() {
                if cam.source == "sim" {
                    let rig = rig.clone().expect("sim rig built");
                    threads.push(crate::sources::sim::spawn_live_camera(rig, i, src_tx.clone(), stop.clone()));
                } else {
                    let c = spawn_camera(i, cam, src_tx.clone(), stop.clone()).inspect_err(|_| stop.store(true, Ordering::SeqCst))?;
                    live_cams.push(c);
                }
            }
        }
    }
    drop(src_tx);

    // UTM.
    let (utm_tx, mut utm_rx) = mpsc::channel::<UtmEvent>(256 + recording.as_ref().map_or(0, |r| r.utm.len()));
    let mut _sim_utm = None;
    let utm_configured = config.utm.is_some();
    if let Some(rec) = &recording {
        for s in &rec.utm {
            let _ = utm_tx.try_send(UtmEvent::Sample(*s));
        }
        drop(utm_tx);
    } else if let Some(ucfg) = &config.utm {
        let ucfg = if ucfg.address == "sim" {
            let rig = rig.clone().expect("sim rig built");
            let (polled, server) =
                crate::utm::sim_server::start_sim_utm(ucfg, rig.utm_model()).await.context("cannot start the simulated UTM")?;
            _sim_utm = Some(server);
            polled
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
    tracing::info!(cameras = ncam, "sources open; measuring");

    // UTM events to the solver (std channel: the solver is a plain thread) and the recorder.
    let (solver_utm_tx, solver_utm_rx) = std_mpsc::channel::<UtmEvent>();
    let forwarder = {
        let rec_tx = rec_tx.clone();
        let drops = recorder_drops.clone();
        tokio::spawn(async move {
            while let Some(ev) = utm_rx.recv().await {
                if let (UtmEvent::Sample(s), Some(tx)) = (&ev, &rec_tx) {
                    if tx.try_send(RecorderMsg::Utm(*s)).is_err() {
                        drops.fetch_add(1, Ordering::Relaxed);
                    }
                }
                if solver_utm_tx.send(ev).is_err() {
                    break;
                }
            }
        })
    };

    // Solver thread.
    let queue = Arc::new(SetQueue::new());
    let solver = if opts.record_only {
        None
    } else {
        let queue = queue.clone();
        let config = config.clone();
        let full_frame = opts.full_frame;
        Some(
            std::thread::Builder::new()
                .name("solver".into())
                .spawn(move || solver_loop(config, full_frame, queue, solver_utm_rx, feeds, utm_configured))?,
        )
    };

    // Assembler: until the sources end or a stop is asked for.
    // Live frames of different cameras may arrive out of order by a frame or two.
    let mut assembler = FrameSetAssembler::with_open_sets(ncam, config.sync.tolerance_ms, 3);
    // A set waits for its missing cameras at most a frame period (and at least 50 ms).
    let max_fps = config.cameras.iter().filter_map(|c| c.fps).fold(0.0f64, f64::max);
    let set_wait = Duration::from_secs_f64(if max_fps > 0.0 { (1.0 / max_fps).max(0.05) } else { 0.1 });
    let mut tick = tokio::time::interval(Duration::from_millis(((config.sync.tolerance_ms as u64) / 2).max(5)));
    let deadline = opts.duration_s.map(|s| tokio::time::Instant::now() + Duration::from_secs_f64(s));
    let mut sigterm = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()).context("cannot watch SIGTERM")?;
    let mut frames_seen = 0u64;
    loop {
        let until_deadline = async {
            match deadline {
                Some(d) => tokio::time::sleep_until(d).await,
                None => std::future::pending().await,
            }
        };
        tokio::select! {
            ev = src_rx.recv() => match ev {
                None => break, // every source ended (a recording was played out)
                Some(SourceEvent::Frame(f)) => {
                    frames_seen += 1;
                    if let Some(tx) = &rec_tx {
                        if tx.try_send(RecorderMsg::Frame(f.clone())).is_err() {
                            recorder_drops.fetch_add(1, Ordering::Relaxed);
                        }
                    }
                    if !opts.record_only {
                        for set in assembler.push(f) {
                            queue.push(set);
                        }
                    }
                }
                Some(SourceEvent::Lost { camera, reason }) => tracing::error!(camera = %config.cameras[camera].name, "camera lost: {reason}; reopening"),
                Some(SourceEvent::Reopened { camera }) => tracing::info!(camera = %config.cameras[camera].name, "camera back"),
                Some(SourceEvent::Dropped { camera, count, why }) => tracing::warn!(camera = %config.cameras[camera].name, count, "frames dropped: {why:?}"),
            },
            _ = tick.tick() => {
                if recording.is_none() {
                    for set in assembler.poll(set_wait) {
                        queue.push(set);
                    }
                }
            }
            _ = tokio::signal::ctrl_c() => { tracing::info!("SIGINT: stopping"); break; }
            _ = sigterm.recv() => { tracing::info!("SIGTERM: stopping"); break; }
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
                queue.push(set);
            }
        }
    }
    for set in assembler.flush() {
        queue.push(set);
    }
    queue.close();
    let threads_done = tokio::task::spawn_blocking(move || {
        for t in threads {
            let _ = t.join();
        }
        for c in live_cams {
            c.join();
        }
    });
    let _ = tokio::time::timeout(Duration::from_secs(5), threads_done).await;
    if let Some(s) = solver {
        tokio::task::spawn_blocking(move || s.join()).await.ok();
    }
    // The forwarder holds a sender of the recorder: end it before waiting for the recorder.
    forwarder.abort();
    let _ = forwarder.await;
    drop(rec_tx);
    if let Some(r) = recorder {
        tokio::task::spawn_blocking(move || r.join()).await.ok();
    }
    let dropped = queue.dropped.load(Ordering::Relaxed);
    let rec_dropped = recorder_drops.load(Ordering::Relaxed);
    tracing::info!(frames = frames_seen, dropped_sets = dropped, recorder_dropped = rec_dropped, "stopped");
    if let Some(r) = run_report {
        tokio::task::spawn_blocking(move || r.finish()).await.ok();
    }
    Ok(())
}

fn solver_loop(
    config: Config,
    full_frame: bool,
    queue: Arc<SetQueue>,
    utm_rx: std_mpsc::Receiver<UtmEvent>,
    mut feeds: Vec<FeedWriter>,
    utm_configured: bool,
) {
    let mut measure = match Measurement::new(&config, !full_frame) {
        Ok(m) => m,
        Err(e) => {
            tracing::error!("cannot start the tag detector: {e}");
            return;
        }
    };
    let mut utm_up = false;
    let utm_wait = config.utm.as_ref().map(|u| Duration::from_secs_f64(2.5 / u.poll_hz)).unwrap_or_default();
    let watchdog = std::env::var_os("WATCHDOG_USEC").is_some();
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
            tracing::info!("UTM up");
        }
    };
    while let Some((set, arrived)) = queue.pop() {
        while let Ok(ev) = utm_rx.try_recv() {
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
                    Ok(ev) => handle(ev, &mut measure, &mut utm_up),
                    Err(_) => break,
                }
            }
        }
        let (mut line, _) = measure.process(&set);
        if utm_configured {
            line.utm = Some(if utm_up { "ok" } else { "down" }.to_string());
        }
        line.dropped_sets = Some(queue.dropped.load(Ordering::Relaxed));
        line.latency_ms = Some((arrived.elapsed().as_secs_f64() * 1e4).round() / 10.0);
        for f in feeds.iter_mut() {
            if let Err(e) = f.write(&line) {
                tracing::error!("{e}");
            }
        }
        if watchdog {
            let _ = sd_notify::notify(false, &[sd_notify::NotifyState::Watchdog]);
        }
    }
}

/// Plays a recording's frames at their recorded pace (same timestamps) as a live source.
fn spawn_player(rec: Recording, tx: mpsc::Sender<SourceEvent>, stop: Arc<AtomicBool>) -> std::thread::JoinHandle<()> {
    std::thread::Builder::new()
        .name("player".into())
        .spawn(move || {
            let Some(first) = rec.frames.first().map(|f| f.t_ns) else { return };
            let t0 = Instant::now();
            let mut dropped = 0u64;
            let (mut pool, mut scratch) = (ImagePool::default(), Vec::new());
            for entry in &rec.frames {
                if stop.load(Ordering::Relaxed) {
                    break;
                }
                let due = Duration::from_nanos((entry.t_ns - first).max(0) as u64);
                if let Some(wait) = due.checked_sub(t0.elapsed()) {
                    std::thread::sleep(wait);
                }
                let image = match pool.fill(|img| rec.load_image_into(entry, img, &mut scratch)) {
                    Ok(i) => i,
                    Err(e) => {
                        tracing::warn!("frame skipped: {e}");
                        continue;
                    }
                };
                let camera = rec.config.camera_index(&entry.camera).expect("checked on open");
                let frame = Frame { camera, seq: entry.seq, t_ns: entry.t_ns, image };
                match tx.try_send(SourceEvent::Frame(frame)) {
                    Ok(()) => {}
                    Err(mpsc::error::TrySendError::Full(_)) => dropped += 1,
                    Err(mpsc::error::TrySendError::Closed(_)) => break,
                }
            }
            if dropped > 0 {
                tracing::warn!(dropped, "player: frames dropped (the pipeline was behind)");
            }
        })
        .expect("player thread")
}

/// Opens every source of the config and returns the first frame set (one frame of each
/// camera that delivered within `timeout`), then stops the sources (`check --config`).
pub fn grab_frame_set(config: &Config, timeout: Duration) -> Result<FrameSet> {
    runtime()?.block_on(async {
        let stop = Arc::new(AtomicBool::new(false));
        let (tx, mut rx) = mpsc::channel::<SourceEvent>(4 * config.cameras.len().max(1));
        let mut threads = Vec::new();
        let mut live = Vec::new();
        let wants_sim = config.cameras.iter().any(|c| c.source == "sim");
        let rig = if wants_sim { Some(Arc::new(crate::sources::sim::LiveRig::new(config, clock::now_epoch_ns())?)) } else { None };
        for (i, cam) in config.cameras.iter().enumerate() {
            if cam.source == "sim" {
                threads.push(crate::sources::sim::spawn_live_camera(rig.clone().expect("sim rig"), i, tx.clone(), stop.clone()));
            } else {
                match spawn_camera(i, cam, tx.clone(), stop.clone()) {
                    Ok(c) => live.push(c),
                    Err(e) => {
                        stop.store(true, Ordering::SeqCst);
                        return Err(anyhow::Error::new(e));
                    }
                }
            }
        }
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
        tokio::task::spawn_blocking(move || {
            threads.into_iter().for_each(|t| {
                let _ = t.join();
            });
            live.into_iter().for_each(|c| c.join());
        })
        .await
        .ok();
        let frames: Vec<Frame> = frames.into_iter().flatten().collect();
        if frames.is_empty() {
            anyhow::bail!("no camera delivered a frame within {:.0} s", timeout.as_secs_f64());
        }
        Ok(FrameSet::new(0, frames))
    })
}
