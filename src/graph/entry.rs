//! The graph's entry points, one per way to run it: `run`/`record`/`demo` ([`run`]), `replay`
//! as fast as it goes ([`replay`], [`replay_smoothed`]), at its recorded pace
//! ([`replay_realtime`], [`replay_paced`]), and the first frame set of a config's cameras
//! ([`grab_frame_set`], for `check --config`).

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use anyhow::{Context, Result};
use tokio::sync::mpsc;

use tagdeflect_core::feed_file::FeedWriter;
use tagdeflect_core::frame::{Frame, FrameSet};
use tagdeflect_core::BadInput;
use tagdeflect_io::sources::{OpenPolicy, SourceEvent};

use crate::config::{CameraSource, Config};
use crate::graph::page::HttpOptions;
use crate::graph::playback::{open, Pacing, Playback};

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
    /// A replay that keeps its config's `[output] tests` (and `[output.auto_test]`): a
    /// simulated test played as a live one (`demo --c1609`); other replays make no tests.
    pub tests_in_replay: bool,
    /// A replay ends with its recording even when the page is served (`demo --c1609 --no-http`,
    /// whose page only carries the tests' control API).
    pub no_linger: bool,
}

/// `run`, `record` and `demo`: live sources from the config.
pub fn run(config: Config, opts: LiveOptions) -> Result<()> {
    runtime()?.block_on(crate::graph::run::run_async(config, opts, None, Vec::new()))
}

/// `replay DIR [--http ADDR]` (without `--realtime`): the recording as fast as it goes
/// ([`Pacing::AsFast`]), the feed to stdout; with the page, it stays up after the recording is
/// consumed until SIGINT/SIGTERM.
pub fn replay(dir: &Path, config: Option<Config>, full_frame: bool, http: Option<HttpOptions>) -> Result<()> {
    replay_smoothed(dir, config, full_frame, http, None)
}

/// [`replay`], the lines smoothed with `smooth_lag_sets` frame sets after them when given
/// (`replay --smooth`; needs `[measure] estimator = "temporal"`).
pub fn replay_smoothed(
    dir: &Path,
    config: Option<Config>,
    full_frame: bool,
    http: Option<HttpOptions>,
    smooth_lag_sets: Option<usize>,
) -> Result<()> {
    let rec = open(dir, config)?;
    if smooth_lag_sets.is_some() && rec.config.measure.estimator != tagdeflect_estimate::temporal::Estimator::Temporal {
        return Err(BadInput::new(format!(
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
pub fn replay_realtime(dir: &Path, config: Option<Config>, full_frame: bool) -> Result<()> {
    replay_realtime_http(dir, config, full_frame, None)
}

/// `replay --realtime [--http ADDR]`: as [`replay_realtime`], serving the live page; with
/// the page, it stays up after the recording is consumed until SIGINT/SIGTERM.
pub fn replay_realtime_http(dir: &Path, config: Option<Config>, full_frame: bool, http: Option<HttpOptions>) -> Result<()> {
    let rec = open(dir, config)?;
    let playback = Playback { rec, pacing: Pacing::Recorded, progress: false };
    play(playback, LiveOptions { full_frame, http, ..LiveOptions::default() }, vec![FeedWriter::stdout()])
}

/// `demo --c1609`: a simulated test's recording at its pace (see
/// [`tagdeflect_io::sources::playback::set_playback_speed`]) through the live pipeline with
/// the config's tests' folder and automatic start and stop; the feed to stdout. Paced without
/// dropping ([`Pacing::Paced`]): on a machine too busy for the pace the test plays slower, its
/// frame sets and their loads are the recording's.
/// `linger`: the page stays up after the recording until a signal.
pub fn replay_as_test(dir: &Path, config: Config, http: Option<HttpOptions>, linger: bool) -> Result<()> {
    let rec = open(dir, Some(config))?;
    let playback = Playback { rec, pacing: Pacing::Paced, progress: false };
    let opts = LiveOptions { http, tests_in_replay: true, no_linger: !linger, ..LiveOptions::default() };
    play(playback, opts, vec![FeedWriter::stdout()])
}

/// A recording's frames at their recorded pace through the live pipeline, the feed to
/// `feeds` (`replay --realtime`, `bench --realtime`).
pub fn replay_paced(rec: crate::config::Recording, full_frame: bool, feeds: Vec<FeedWriter>) -> Result<()> {
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
    runtime()?.block_on(crate::graph::run::run_async(cfg, opts, Some(playback), feeds))
}

fn runtime() -> Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().context("cannot start the async runtime")
}

/// Opens every source of the config and returns the first frame set (one frame of each
/// camera that delivered within `timeout`), then stops the sources (`check --config`).
pub fn grab_frame_set(config: &Config, timeout: Duration) -> Result<FrameSet> {
    runtime()?.block_on(async {
        let stop = Arc::new(AtomicBool::new(false));
        let (tx, mut rx) = mpsc::channel::<SourceEvent>(4 * config.cameras.len().max(1));
        let sources = crate::graph::sources::start(config, OpenPolicy::Require, tx.clone(), stop.clone(), None)?;
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
            return Err(BadInput::new(format!("no camera delivered a frame within {:.0} s", timeout.as_secs_f64())).into());
        }
        Ok(FrameSet::new(0, frames))
    })
}
