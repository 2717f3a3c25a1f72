//! The measurement over a recording, driven in-process on the caller's thread: what `bench`
//! times stage by stage and what tests read feed lines from.
//!
//! `tagdeflect replay` itself is the graph ([`crate::graph::entry::replay`]: the recording a
//! source, [`crate::graph::playback::Pacing`] its pacing); this driver gives the same lines as the
//! graph's as-fast replay (`tests/it` checks it line for line), without threads between the
//! stages, so each stage's time is its own.
//!
//! [`Recording::frames`] decodes frames ahead on worker threads, in time order (a bad frame is
//! logged and skipped: the frame set is solved from the other cameras); the assembler and the
//! measurement take them in turn; feed lines go to a callback.

use anyhow::{Context, Result};
use std::time::Instant;

use tagdeflect_core::feed::FeedLine;
use tagdeflect_estimate::measure::{MeasureStats, Measurement, StageTimes};
use tagdeflect_io::sync::FrameSetAssembler;

use crate::config::Recording;
use crate::graph::playback::progress_bar;
use crate::graph::smoothing::Smoothing;

/// What a replay did.
#[derive(Debug, Clone, Default)]
pub struct ReplaySummary {
    /// Frame sets solved (feed lines produced).
    pub sets: u64,
    /// Frames that could not be read and were skipped.
    pub bad_frames: u64,
    /// Frames dropped as late by the assembler.
    pub late_frames: u64,
    /// Measurement counters.
    pub stats: MeasureStats,
    /// Total seconds.
    pub wall_s: f64,
    /// Seconds spent decoding images (reader thread).
    pub decode_s: f64,
    /// Each camera's pose at the end (`None`: never posed), in the config's order.
    pub camera_poses: Vec<Option<tagdeflect_core::camera::Pose>>,
}

/// Options of a replay.
#[derive(Debug, Clone, Copy, Default)]
pub struct ReplayOptions {
    /// Force full-frame detection everywhere.
    pub full_frame: bool,
    /// Show a progress bar on stderr (when it is a terminal).
    pub progress: bool,
    /// Smooth the lines with this many frame sets after them (as `replay --smooth`; the
    /// temporal estimator only).
    pub smooth_lag_sets: Option<usize>,
}

pub use crate::graph::playback::open;

/// Replays a recording through the measurement; `on_line(line, stage_times, latency_s)`
/// is called for every frame set in order (latency: frame set complete → line made).
pub fn replay(rec: &Recording, opts: ReplayOptions, mut on_line: impl FnMut(&FeedLine, &StageTimes, f64)) -> Result<ReplaySummary> {
    replay_sets(rec, opts, |line, times, latency| on_line(&line, times, latency))
}

/// [`replay`] handing over each line (smoothed when asked) with its stage times and latency.
fn replay_sets(rec: &Recording, opts: ReplayOptions, mut on_set: impl FnMut(FeedLine, &StageTimes, f64)) -> Result<ReplaySummary> {
    let start = Instant::now();
    let config = &rec.config;
    let mut measure = Measurement::new(&config.measurement(), !opts.full_frame).context("cannot start the tag detector")?;
    // As the graph's solver does: each line leaves the smoother `lag` sets later.
    let mut smoothing = opts.smooth_lag_sets.map(|lag| Smoothing::attach(&mut measure, lag));
    for s in &rec.utm {
        measure.utm_mut().push(*s);
    }
    let mut assembler = FrameSetAssembler::new(config.cameras.len(), config.sync.tolerance_ms);
    let mut summary = ReplaySummary::default();
    let bar = opts.progress.then(|| progress_bar(rec.frames.len() as u64));
    let mut process = |set: tagdeflect_core::frame::FrameSet, ready: Instant, summary: &mut ReplaySummary| {
        let (line, times) = measure.process(&set);
        summary.sets += 1;
        match smoothing.as_mut() {
            Some(sm) => {
                if let Some(out) = sm.push(line, &measure) {
                    on_set(out, &times, ready.elapsed().as_secs_f64());
                }
            }
            None => on_set(line, &times, ready.elapsed().as_secs_f64()),
        }
    };
    let (mut bad, mut decode_s) = (0u64, 0.0);
    let mut newest_ready = Instant::now();
    // Frames decoded ahead on worker threads, in time order (a bad frame is logged and
    // skipped: its set is solved from the other cameras).
    for read in rec.frames() {
        if let Some(b) = &bar {
            b.inc(1);
        }
        decode_s += read.decode_s;
        match read.frame {
            Ok(frame) => {
                newest_ready = Instant::now();
                for set in assembler.push(frame) {
                    process(set, newest_ready, &mut summary);
                }
            }
            Err(e) => {
                bad += 1;
                tracing::warn!("frame skipped: {e}");
            }
        }
    }
    for set in assembler.flush() {
        process(set, newest_ready, &mut summary);
    }
    for line in smoothing.as_mut().map(Smoothing::finish).unwrap_or_default() {
        on_set(line, &StageTimes::default(), 0.0);
    }
    let reader_result = (bad, decode_s);
    if let Some(b) = bar {
        b.finish_and_clear();
    }
    summary.bad_frames = reader_result.0;
    summary.decode_s = reader_result.1;
    summary.late_frames = assembler.late_frames();
    summary.stats = measure.stats().clone();
    summary.camera_poses = measure.camera_poses();
    summary.wall_s = start.elapsed().as_secs_f64();
    if summary.sets == 0 {
        return Err(tagdeflect_core::BadInput::new(format!("{}: no frame could be read, nothing was solved", rec.dir.display())).into());
    }
    Ok(summary)
}
