//! Frames → frame sets (SPEC `sync.tolerance_ms`).
//!
//! A frame set is anchored at its first frame; a frame of another camera within the
//! tolerance of the anchor joins it. A set closes when every camera has a frame in it,
//! when a frame arrives beyond the tolerance, or when a camera's second frame arrives
//! (a set never holds two frames of one camera: a dropped frame of one camera makes a
//! smaller set). A late frame — one not newer than every frame of a set already closed —
//! is dropped and counted, so frame sets come out in time order, each later than the one
//! before.
//!
//! Clock steps: every frame is stamped on the process clock ([`tagdeflect_core::clock`]), which never
//! goes back (a backwards step of the wall clock is slewed there), so set times keep their
//! order whatever the wall clock does. A frame older than the last closed set — however much
//! older — is a late frame: dropped and counted, never a set out of time order (the feed is in
//! `t_ns` order, SPEC).
//!
//! Live capture closes a set that waited too long for its missing cameras with
//! [`FrameSetAssembler::poll`] (or [`FrameSetAssembler::poll_at`], the time given), counted on
//! the process clock from when the set opened (its first frame arrived). The wait
//! ([`WaitRule`], from the fastest camera's rate):
//!
//! - **base**: a frame period of the fastest camera, at least 50 ms;
//! - **learned**: a live assembler ([`FrameSetAssembler::live`]) learns each camera's arrival
//!   delay — arrival on the process clock minus the frame's `t_ns` — as the 90th percentile of
//!   its last [`DELAY_WINDOW`] frames (counted once it has [`MIN_DELAYS`]). A set missing a
//!   camera waits until its anchor + the tolerance + that camera's delay + a margin of a quarter
//!   base wait, if that is later than the base wait. A camera whose frames steadily arrive late
//!   (a slow pipeline, a busy PC) is so waited for, whatever the phase between the cameras; a
//!   few slow frames (up to 4 of the last 32) do not move the estimate, and more raise it only
//!   while they are in the window;
//! - **bound**: never more than the larger of 1 s and three base waits after the set opened,
//!   so a dead camera never stalls the feed; a camera that sent nothing for twice the bound no
//!   longer counts (the wait falls back to the base) and learns again when it sends. A camera
//!   steadily later than the bound is logged (warn) and not waited for: its frames are
//!   dropped as late.
//!
//! The learned wait is logged (info) when it moves by more than the margin (at most once a
//! minute; every live feed line carries each camera's delay as `cameras[].arrival_delay_ms`).
//! Recordings (read in time order, never polled) learn nothing and read the clock once per
//! set, not per frame.

use serde::{Deserialize, Serialize};
use std::time::Duration;

use tagdeflect_core::clock;
use tagdeflect_core::frame::{Frame, FrameSet};

#[cfg(test)]
mod tests;
mod wait;

pub use wait::{ArrivalDelays, WaitRule, DELAY_WINDOW, MIN_DELAYS, MIN_MAX_WAIT};

/// A frame set still waiting for cameras.
#[derive(Debug)]
struct OpenSet {
    frames: Vec<Frame>,
    /// When its first frame arrived, process clock ns.
    opened_ns: i64,
}

impl OpenSet {
    fn anchor(&self) -> i64 {
        self.frames[0].t_ns
    }
}

/// Groups frames of different cameras into frame sets.
#[derive(Debug)]
pub struct FrameSetAssembler {
    cameras: usize,
    tolerance_ns: i64,
    max_open: usize,
    /// Open sets, oldest anchor first.
    open: Vec<OpenSet>,
    /// Frames at or before this time belong to sets already closed.
    closed_until: Option<i64>,
    next_seq: u64,
    late_frames: u64,
    /// Late frames per camera.
    late_by_camera: Vec<u64>,
    /// Live capture: the cameras' learned arrival delays (`None`: a recording).
    delays: Option<ArrivalDelays>,
}

impl FrameSetAssembler {
    /// An assembler for `cameras` cameras with a tolerance in ms, for frames that arrive in
    /// time order (a recording): one set is open at a time.
    pub fn new(cameras: usize, tolerance_ms: f64) -> Self {
        Self::with_open_sets(cameras, tolerance_ms, 1)
    }

    /// An assembler that keeps up to `max_open` sets open at once (live capture: a camera
    /// whose frames arrive late — slow transfer, busy CPU — still joins its set).
    pub fn with_open_sets(cameras: usize, tolerance_ms: f64, max_open: usize) -> Self {
        Self {
            cameras,
            tolerance_ns: (tolerance_ms * 1e6).round() as i64,
            max_open: max_open.max(1),
            open: Vec::new(),
            closed_until: None,
            next_seq: 0,
            late_frames: 0,
            late_by_camera: vec![0; cameras],
            delays: None,
        }
    }

    /// A live assembler for the cameras named `names` (in `[[cameras]]` order): it learns
    /// each camera's arrival delay and waits for a steadily late camera (module doc), with
    /// as many open sets as the rule's bound needs.
    pub fn live(names: Vec<String>, tolerance_ms: f64, rule: WaitRule) -> Self {
        let mut a = Self::with_open_sets(names.len(), tolerance_ms, rule.open_sets().max(3));
        a.delays = Some(ArrivalDelays::new(names, rule));
        a
    }

    /// The cameras' learned arrival delays (a live assembler).
    pub fn arrival_delays(&self) -> Option<&ArrivalDelays> {
        self.delays.as_ref()
    }

    /// Frames dropped because their set had already been closed.
    pub fn late_frames(&self) -> u64 {
        self.late_frames
    }

    /// Late frames of each camera so far.
    pub fn late_by_camera(&self) -> &[u64] {
        &self.late_by_camera
    }

    fn count_late(&mut self, camera: usize) {
        self.late_frames += 1;
        if let Some(c) = self.late_by_camera.get_mut(camera) {
            *c += 1;
        }
    }

    /// Adds a frame that arrived now; returns the sets it completes, in time order. The clock
    /// is read for every frame only by a live assembler (or when debug logging is on).
    pub fn push(&mut self, frame: Frame) -> Vec<FrameSet> {
        let arrival = (self.delays.is_some() || tracing::enabled!(tracing::Level::DEBUG)).then(clock::now_epoch_ns);
        self.push_arrived(frame, arrival)
    }

    /// Adds a frame that arrived at `arrival_ns` (process clock); returns the sets it completes.
    pub fn push_at(&mut self, frame: Frame, arrival_ns: i64) -> Vec<FrameSet> {
        self.push_arrived(frame, Some(arrival_ns))
    }

    fn push_arrived(&mut self, frame: Frame, arrival: Option<i64>) -> Vec<FrameSet> {
        let mut done = Vec::new();
        if let (Some(d), Some(at)) = (&mut self.delays, arrival) {
            d.record(frame.camera, frame.t_ns, at);
        }
        // How old the frame is when it reaches the assembler (capture and transfer latency):
        // with TAGDEFLECT_LOG=tagdeflect_io::sync=trace, per frame; late frames at debug.
        let age_ms = arrival.map_or(f64::NAN, |a| (a as i128 - frame.t_ns as i128) as f64 / 1e6);
        tracing::trace!(camera = frame.camera, t_ns = frame.t_ns, age_ms, open = self.open.len(), "frame in");
        if let Some(c) = self.closed_until.filter(|&c| frame.t_ns <= c) {
            let behind_ms = (c as i128 - frame.t_ns as i128) as f64 / 1e6;
            tracing::debug!(camera = frame.camera, t_ns = frame.t_ns, age_ms, behind_ms, "late frame: a newer set has closed");
            self.count_late(frame.camera);
            return done;
        }
        let tol = self.tolerance_ns;
        let joins = self.open.iter().position(|s| {
            (frame.t_ns as i128 - s.anchor() as i128).abs() <= tol as i128 && !s.frames.iter().any(|f| f.camera == frame.camera)
        });
        let index = match joins {
            Some(i) => {
                self.open[i].frames.push(frame);
                i
            }
            None => {
                if self.open.first().is_some_and(|s| frame.t_ns < s.anchor().saturating_sub(tol)) && self.open.len() >= self.max_open {
                    // Older than every open set and no room: it can only be late.
                    tracing::debug!(camera = frame.camera, t_ns = frame.t_ns, age_ms, "late frame: older than every open set, no room");
                    self.count_late(frame.camera);
                    return done;
                }
                let i = self.open.partition_point(|s| s.anchor() <= frame.t_ns);
                let opened_ns = arrival.unwrap_or_else(clock::now_epoch_ns);
                self.open.insert(i, OpenSet { frames: vec![frame], opened_ns });
                i
            }
        };
        if self.open[index].frames.len() >= self.cameras {
            // Complete: close it, and every older set with it (sets leave in time order).
            done.extend(self.close_through(index));
        }
        while self.open.len() > self.max_open {
            done.extend(self.close_through(0));
        }
        done
    }

    /// Closes the sets that have waited long enough for their missing cameras — `wait` (the
    /// base wait) from their opening, or a live assembler's learned wait (module doc) — with
    /// every older set (a camera whose frame never comes must not hold the others back).
    pub fn poll(&mut self, wait: Duration) -> Vec<FrameSet> {
        self.poll_at(clock::now_epoch_ns(), wait)
    }

    /// [`Self::poll`] at `now_ns` (process clock).
    pub fn poll_at(&mut self, now_ns: i64, wait: Duration) -> Vec<FrameSet> {
        let base_ns = i64::try_from(wait.as_nanos()).unwrap_or(i64::MAX);
        match self.open.iter().rposition(|s| now_ns > self.deadline_ns(s, base_ns, now_ns)) {
            Some(i) => self.close_through(i),
            None => Vec::new(),
        }
    }

    /// When `set` is closed without its missing cameras, process clock ns.
    fn deadline_ns(&self, set: &OpenSet, base_ns: i64, now_ns: i64) -> i64 {
        let Some(d) = &self.delays else { return set.opened_ns.saturating_add(base_ns) };
        let missing = (0..self.cameras).filter(|&c| !set.frames.iter().any(|f| f.camera == c));
        d.deadline_ns(set.anchor(), set.opened_ns, base_ns, self.tolerance_ns, missing, now_ns)
    }

    /// Closes every open set (end of a recording or shutdown).
    pub fn flush(&mut self) -> Vec<FrameSet> {
        match self.open.len() {
            0 => Vec::new(),
            n => self.close_through(n - 1),
        }
    }

    /// Closes the open sets `0..=index`, oldest first.
    fn close_through(&mut self, index: usize) -> Vec<FrameSet> {
        let closing: Vec<OpenSet> = self.open.drain(..=index).collect();
        let mut out = Vec::with_capacity(closing.len());
        for mut set in closing {
            // Later sets hold only frames newer than every frame of this one, so set times
            // (means) strictly increase. Sets closed together are checked too: a frame not
            // newer than what was just closed (a repeated timestamp) is late.
            if let Some(until) = self.closed_until {
                let before: Vec<usize> = set.frames.iter().filter(|f| f.t_ns <= until).map(|f| f.camera).collect();
                set.frames.retain(|f| f.t_ns > until);
                if !before.is_empty() {
                    tracing::debug!(cameras = ?before, "late frames: not newer than a set closed with theirs");
                }
                for c in before {
                    self.count_late(c);
                }
                if set.frames.is_empty() {
                    continue;
                }
            }
            let newest = set.frames.iter().map(|f| f.t_ns).max().expect("open sets hold a frame");
            self.closed_until = Some(self.closed_until.map_or(newest, |c| c.max(newest)));
            out.push(FrameSet::new(self.next_seq, set.frames));
            self.next_seq += 1;
        }
        // A remaining open set whose anchor is not newer than what was closed would break
        // the time order: its frames that are too old are dropped as late.
        let until = self.closed_until.unwrap_or(i64::MIN);
        let mut late_cams = Vec::new();
        for s in &mut self.open {
            s.frames.retain(|f| {
                let keep = f.t_ns > until;
                if !keep {
                    late_cams.push(f.camera);
                }
                keep
            });
        }
        self.open.retain(|s| !s.frames.is_empty());
        self.open.sort_by_key(|s| s.anchor());
        if !late_cams.is_empty() {
            tracing::debug!(cameras = ?late_cams, until_ns = until, "late frames: in an open set, not newer than the sets just closed");
        }
        for c in late_cams {
            self.count_late(c);
        }
        out
    }
}

/// Largest frame-set tolerance accepted, ms.
pub const MAX_TOLERANCE_MS: f64 = 10_000.0;

/// `[sync]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SyncConfig {
    /// Frames of different cameras closer than this form one frame set.
    pub tolerance_ms: f64,
}

impl Default for SyncConfig {
    fn default() -> Self {
        Self { tolerance_ms: 10.0 }
    }
}

impl SyncConfig {
    /// Checks `[sync]`; keys relative to it.
    pub fn validate(&self) -> Result<(), tagdeflect_core::Problem> {
        let t = self.tolerance_ms;
        if !(t.is_finite() && t > 0.0 && t <= MAX_TOLERANCE_MS) {
            return Err(tagdeflect_core::Problem::new(
                "tolerance_ms",
                format!("must be a positive number of milliseconds up to {MAX_TOLERANCE_MS}, got {t}"),
            ));
        }
        Ok(())
    }
}
