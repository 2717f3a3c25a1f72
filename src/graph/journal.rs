//! What a live run tells the journal: per-frame events are logged at DEBUG only; once per
//! [`SUMMARY_INTERVAL`] one INFO line sums them up per camera, and a camera whose pose
//! turns stale (or fresh again) is logged once at the change, not once per frame set.

use std::time::{Duration, Instant};

use tagdeflect_core::feed::FeedLine;

/// How often the INFO summary is logged.
pub const SUMMARY_INTERVAL: Duration = Duration::from_secs(60);

#[derive(Debug, Default, Clone)]
struct CamCounts {
    frames: u64,
    stale_sets: u64,
    unposed_sets: u64,
    bumps: u64,
}

/// Counts per camera between two summaries.
#[derive(Debug)]
pub struct JournalSummary {
    names: Vec<String>,
    interval: Duration,
    since: Instant,
    sets: u64,
    sets_without_tags: u64,
    counts: Vec<CamCounts>,
    stale: Vec<bool>,
    last_rejected: Vec<u64>,
    last_dropped: Vec<u64>,
    last_dropped_sets: u64,
}

impl JournalSummary {
    /// A summary for these cameras, logged every `interval`.
    pub fn new(names: Vec<String>, interval: Duration) -> Self {
        let n = names.len();
        Self {
            names,
            interval,
            since: Instant::now(),
            sets: 0,
            sets_without_tags: 0,
            counts: vec![CamCounts::default(); n],
            stale: vec![false; n],
            last_rejected: vec![0; n],
            last_dropped: vec![0; n],
            last_dropped_sets: 0,
        }
    }

    /// Takes one written feed line and the cumulative outlier rejections per camera; logs
    /// stale-pose changes at once and the summary when it is due. Returns the summary line
    /// when one was logged.
    pub fn observe(&mut self, line: &FeedLine, rejected_by_camera: &[u64]) -> Option<String> {
        self.sets += 1;
        if line.tags.is_empty() {
            self.sets_without_tags += 1;
        }
        for (i, c) in line.cameras.iter().enumerate().take(self.names.len()) {
            let k = &mut self.counts[i];
            k.frames += c.frame as u64;
            k.stale_sets += c.stale_pose as u64;
            k.unposed_sets += (c.frame && !c.posed) as u64;
            k.bumps += c.bumped as u64;
            if c.stale_pose != self.stale[i] {
                self.stale[i] = c.stale_pose;
                if c.stale_pose {
                    tracing::warn!(camera = %c.name, seq = line.seq, "no background tag confirms this camera's pose: it is held (stale_pose in the feed)");
                } else {
                    tracing::info!(camera = %c.name, seq = line.seq, "camera pose confirmed by background tags again");
                }
            }
        }
        (self.since.elapsed() >= self.interval).then(|| self.emit(line, rejected_by_camera))
    }

    fn emit(&mut self, line: &FeedLine, rejected_by_camera: &[u64]) -> String {
        let secs = self.since.elapsed().as_secs_f64();
        let mut parts = Vec::new();
        for (i, name) in self.names.iter().enumerate() {
            let k = &self.counts[i];
            let rejected = rejected_by_camera.get(i).copied().unwrap_or(0);
            let dropped = line.cameras.get(i).and_then(|c| c.dropped_frames).unwrap_or(0);
            parts.push(format!(
                "{name}: {} frames, {} dropped, {} stale-pose sets, {} unposed, {} bumps, {} outlier views",
                k.frames,
                dropped.saturating_sub(self.last_dropped[i]),
                k.stale_sets,
                k.unposed_sets,
                k.bumps,
                rejected.saturating_sub(self.last_rejected[i])
            ));
            self.last_rejected[i] = rejected;
            self.last_dropped[i] = dropped;
        }
        let dropped_sets = line.dropped_sets.unwrap_or(0);
        let text = format!(
            "last {secs:.0} s: {} frame sets ({} dropped, {} without a solved tag); {}",
            self.sets,
            dropped_sets.saturating_sub(self.last_dropped_sets),
            self.sets_without_tags,
            parts.join("; ")
        );
        tracing::info!("{text}");
        self.last_dropped_sets = dropped_sets;
        self.sets = 0;
        self.sets_without_tags = 0;
        self.counts.iter_mut().for_each(|k| *k = CamCounts::default());
        self.since = Instant::now();
        text
    }
}

/// Frames dropped per camera in a live run, shared by the assembler (which sees the
/// sources' drop reports and its own late frames) and the solver (which puts the totals in
/// every feed line as `cameras[].dropped_frames`, with the learned `arrival_delay_ms`).
#[derive(Debug)]
pub struct FrameDrops {
    source: Vec<std::sync::atomic::AtomicU64>,
    late: Vec<std::sync::atomic::AtomicU64>,
    /// Each camera's learned arrival delay, µs ([`NO_DELAY`]: none).
    delay_us: Vec<std::sync::atomic::AtomicI64>,
}

/// No learned arrival delay.
const NO_DELAY: i64 = i64::MIN;

impl FrameDrops {
    /// Counters for `cameras` cameras.
    pub fn new(cameras: usize) -> Self {
        Self {
            source: (0..cameras).map(|_| Default::default()).collect(),
            late: (0..cameras).map(|_| Default::default()).collect(),
            delay_us: (0..cameras).map(|_| std::sync::atomic::AtomicI64::new(NO_DELAY)).collect(),
        }
    }

    /// A source reported `count` frames of `camera` dropped (queue full, incomplete buffer).
    pub fn add_source(&self, camera: usize, count: u64) {
        if let Some(c) = self.source.get(camera) {
            c.fetch_add(count, std::sync::atomic::Ordering::Relaxed);
        }
    }

    /// The assembler's late frames of each camera so far.
    pub fn set_late(&self, late_by_camera: &[u64]) {
        for (c, n) in self.late.iter().zip(late_by_camera) {
            c.store(*n, std::sync::atomic::Ordering::Relaxed);
        }
    }

    /// The assembler's learned arrival delays at `now_ns` (a live run).
    pub fn set_delays(&self, delays: &tagdeflect_io::sync::ArrivalDelays, now_ns: i64) {
        for (c, slot) in self.delay_us.iter().enumerate() {
            let us = delays.steady_delay_ns(c, now_ns).map_or(NO_DELAY, |d| d / 1_000);
            slot.store(us, std::sync::atomic::Ordering::Relaxed);
        }
    }

    /// Frames of `camera` dropped so far.
    pub fn total(&self, camera: usize) -> u64 {
        let get = |v: &[std::sync::atomic::AtomicU64]| v.get(camera).map_or(0, |c| c.load(std::sync::atomic::Ordering::Relaxed));
        get(&self.source) + get(&self.late)
    }

    /// Writes the totals into a feed line's `cameras[].dropped_frames`.
    pub fn apply(&self, line: &mut FeedLine) {
        for (i, c) in line.cameras.iter_mut().enumerate() {
            c.dropped_frames = Some(self.total(i));
            let us = self.delay_us.get(i).map_or(NO_DELAY, |d| d.load(std::sync::atomic::Ordering::Relaxed));
            c.arrival_delay_ms = (us != NO_DELAY).then_some(us as f64 / 1e3);
        }
    }
}
