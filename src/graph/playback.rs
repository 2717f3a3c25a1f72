//! A recording as the graph's source, and how it is played ([`Pacing`]; see [`crate::graph::run`]).

use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicI64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use anyhow::{Context, Result};
use tokio::sync::mpsc;

use tagdeflect_core::utm_sample::UtmSample;
use tagdeflect_io::sources::playback::ElasticClock;
use tagdeflect_io::sources::SourceEvent;
use tagdeflect_io::utm::modbus::UtmEvent;

use crate::config::{Config, Recording};

/// How a recording is played through the graph (see [`crate::graph::run`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Pacing {
    /// At its recorded pace, one player per camera, as a run would have met it: a set the
    /// pipeline is too late for is dropped and counted (SPEC's live drop policy). The players
    /// hand the recording's UTM samples over with the frames
    /// ([`tagdeflect_io::sources::playback::UtmInStep`]), so every line that goes out carries
    /// the load recorded around its time (`replay --realtime`, `bench --realtime`).
    Recorded,
    /// As fast as the measurement goes, in time order, nothing dropped.
    AsFast,
    /// At its recorded pace on one clock for its frames and its UTM samples, in time order,
    /// nothing dropped: when the pipeline falls behind, the replay plays slower
    /// ([`tagdeflect_io::sources::playback::ElasticClock`]); each set's load is joined from the
    /// samples recorded around its time whatever the machine's load (`demo --c1609`: a
    /// simulated test played as a live one).
    Paced,
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
            if !hand_over_frame(read.frame, &tx, &mut bad) {
                break;
            }
        }
        if let Some(b) = bar {
            b.finish_and_clear();
        }
        bad
    });
    reader.context("cannot start the recording's reader")
}

/// Hands one read frame to the assembler, waiting for room; an unreadable one is logged,
/// counted in `bad` and skipped. False when the assembler has gone (the replay ends).
fn hand_over_frame(
    frame: Result<tagdeflect_core::frame::Frame, tagdeflect_io::recording::RecordingError>,
    tx: &mpsc::Sender<SourceEvent>,
    bad: &mut u64,
) -> bool {
    match frame {
        Ok(frame) => tx.blocking_send(SourceEvent::Frame(frame)).is_ok(),
        Err(e) => {
            *bad += 1;
            tracing::warn!("frame skipped: {e}");
            true
        }
    }
}

/// The UTM samples of a replay at its recorded pace, handed over with its frames: the
/// forwarder's channel, and the recorded time of the newest sample handed over (`i64::MIN`
/// before the first), which the solver waits to have received
/// ([`crate::graph::solver::UtmFeed::in_step`]).
pub struct PacedUtm {
    /// To the run's UTM forwarder.
    pub tx: mpsc::Sender<UtmEvent>,
    /// The recorded time of the newest sample handed over.
    pub sent: Arc<AtomicI64>,
}

/// Hands a recording's frames and UTM samples over in time order at its recorded pace
/// ([`Pacing::Paced`]), waiting for room instead of dropping: before each frame, the samples
/// recorded before it at their own times, then the first one at or after it (the frame's line
/// interpolates between the two) — so every sample a set's load needs was handed over before
/// the set's frames. Returns the frames skipped (unreadable: logged, as [`spawn_reader`]).
pub(crate) fn spawn_paced_reader(
    rec: &Recording,
    tx: mpsc::Sender<SourceEvent>,
    utm: Option<PacedUtm>,
    stop: Arc<AtomicBool>,
) -> Result<std::thread::JoinHandle<u64>> {
    let frames = rec.frames();
    let times: Vec<i64> = rec.frames.iter().map(|f| f.t_ns).collect();
    let samples = rec.utm.clone();
    let mut clock = ElasticClock::start(rec);
    let reader = std::thread::Builder::new().name("recording".into()).spawn(move || {
        let mut utm = utm.map(|u| (u, samples.into_iter()));
        let mut bad = 0u64;
        for read in frames {
            let t_ns = times[read.index];
            if let Some((u, next)) = utm.as_mut() {
                if !hand_over_utm_to(t_ns, u, next, &mut clock, &stop) {
                    utm = None;
                }
            }
            if !clock.wait_until_due(t_ns, &stop) {
                break;
            }
            if !hand_over_frame(read.frame, &tx, &mut bad) {
                break;
            }
        }
        let (slip, slips) = clock.slipped();
        if slips > 0 {
            tracing::info!(slips, "the replay fell behind its recorded pace {slips} time(s) and played {:.1} s slower", slip.as_secs_f64());
        }
        bad
    });
    reader.context("cannot start the recording's reader")
}

/// The UTM samples a frame at `t_ns` needs, handed over (see [`spawn_paced_reader`]); false
/// when nobody takes them any more (or a stop was asked for).
fn hand_over_utm_to(
    t_ns: i64,
    u: &PacedUtm,
    next: &mut std::vec::IntoIter<UtmSample>,
    clock: &mut ElasticClock,
    stop: &AtomicBool,
) -> bool {
    // Samples already handed over up to one at or after `t_ns`: nothing more is needed.
    if u.sent.load(Ordering::SeqCst) >= t_ns {
        return true;
    }
    for s in next.by_ref() {
        let after = s.t_ns >= t_ns;
        // The one after the frame goes with the frame, ahead of its own time.
        if !clock.wait_until_due(s.t_ns.min(t_ns), stop) || u.tx.blocking_send(UtmEvent::Sample(s)).is_err() {
            return false;
        }
        u.sent.store(s.t_ns, Ordering::SeqCst);
        if after {
            break;
        }
    }
    true
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
