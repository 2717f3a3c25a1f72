//! A recording as the graph's source, and how it is played ([`Pacing`]; see [`crate::graph::run`]).

use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use anyhow::{Context, Result};
use tokio::sync::mpsc;

use tagdeflect_io::sources::SourceEvent;
use tagdeflect_io::utm::modbus::UtmEvent;

use crate::config::{Config, Recording};

/// How a recording is played through the graph (see [`crate::graph::run`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Pacing {
    /// At its recorded pace, one player per camera, as a run would have met it.
    Recorded,
    /// As fast as the measurement goes, in time order, nothing dropped.
    AsFast,
}

/// A recording as the graph's source.
pub(crate) struct Playback {
    pub(crate) rec: Recording,
    pub(crate) pacing: Pacing,
    /// A progress bar on stderr ([`Pacing::AsFast`], when stderr is a terminal).
    pub(crate) progress: bool,
}

/// Opens a recording, with an optional config override.
pub fn open(dir: &Path, config: Option<Config>) -> Result<Recording> {
    let rec = match config {
        Some(c) => Recording::open_with(dir, c),
        None => Recording::open(dir),
    };
    rec.with_context(|| format!("cannot replay {}", dir.display()))
}

/// Hands a recording's frames to the assembler in time order, waiting for room
/// ([`Pacing::AsFast`]); a frame that cannot be read is logged and skipped (its set is solved
/// from the other cameras). Returns the frames skipped.
pub(crate) fn spawn_reader(
    rec: &Recording,
    progress: bool,
    tx: mpsc::Sender<SourceEvent>,
    stop: Arc<AtomicBool>,
) -> Result<std::thread::JoinHandle<u64>> {
    let frames = rec.frames();
    let total = rec.frames.len() as u64;
    let reader = std::thread::Builder::new().name("recording".into()).spawn(move || {
        let bar = progress.then(|| progress_bar(total));
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

/// The progress bar of a replay on stderr: `total` frames.
pub(crate) fn progress_bar(total: u64) -> indicatif::ProgressBar {
    let b = indicatif::ProgressBar::new(total);
    b.set_style(indicatif::ProgressStyle::with_template("{bar:40} {pos}/{len} frames  {per_sec}  ETA {eta}").expect("template"));
    b
}

/// How long a set waits for the UTM sample after it when a recording's UTM stream is played
/// at its pace: two and a half of its sampling intervals (median), at least 20 ms, at most 1 s.
pub(crate) fn recorded_utm_wait(rec: &Recording) -> Duration {
    let mut gaps: Vec<f64> =
        rec.utm.windows(2).map(|w| (w[1].t_ns as i128 - w[0].t_ns as i128) as f64 * 1e-9).filter(|g| *g > 0.0).collect();
    gaps.sort_by(f64::total_cmp);
    let median = gaps.get(gaps.len() / 2).copied().unwrap_or(0.02);
    Duration::from_secs_f64((2.5 * median).clamp(0.02, 1.0))
}

/// Sends a recording's UTM samples at their recorded pace (relative to its first frame),
/// as a live UTM would (`replay --realtime`).
pub(crate) async fn play_utm(rec: Recording, tx: mpsc::Sender<UtmEvent>) {
    if rec.frames.is_empty() {
        return;
    }
    // The cameras' schedule (long pauses capped alike), started within a few ms of theirs.
    let playhead = tagdeflect_io::sources::playback::Playhead::start_silent(&rec);
    let t0 = tokio::time::Instant::now();
    for s in &rec.utm {
        tokio::time::sleep_until(t0 + playhead.due(s.t_ns)).await;
        if tx.send(UtmEvent::Sample(*s)).await.is_err() {
            break;
        }
    }
}
