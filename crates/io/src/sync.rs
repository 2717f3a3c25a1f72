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
//! [`FrameSetAssembler::poll`], measured from when the set was opened on the wall clock —
//! not from the frames' timestamps, because transfer latency varies between cameras.

use serde::{Deserialize, Serialize};
use std::time::{Duration, Instant};

use tagdeflect_core::clock;
use tagdeflect_core::frame::{Frame, FrameSet};

/// A frame set still waiting for cameras.
#[derive(Debug)]
struct OpenSet {
    frames: Vec<Frame>,
    opened_at: Instant,
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
        }
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

    /// Adds a frame; returns the sets it completes, in time order.
    pub fn push(&mut self, frame: Frame) -> Vec<FrameSet> {
        let mut done = Vec::new();
        // How old the frame is when it reaches the assembler (capture and transfer latency):
        // with TAGDEFLECT_LOG=tagdeflect_io::sync=trace, per frame; late frames at debug.
        let age_ms = (clock::now_epoch_ns() as i128 - frame.t_ns as i128) as f64 / 1e6;
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
                self.open.insert(i, OpenSet { frames: vec![frame], opened_at: Instant::now() });
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

    /// Closes the sets that have waited longer than `wait` (wall clock) for their missing
    /// cameras, with every older set (live capture: a camera whose frame never comes must
    /// not hold the others back).
    pub fn poll(&mut self, wait: Duration) -> Vec<FrameSet> {
        match self.open.iter().rposition(|s| s.opened_at.elapsed() > wait) {
            Some(i) => self.close_through(i),
            None => Vec::new(),
        }
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

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Arc;
    use tagdeflect_core::frame::GrayImage;

    fn f(camera: usize, t_ms: i64) -> Frame {
        Frame { camera, seq: 0, t_ns: 1_700_000_000_000_000_000 + t_ms * 1_000_000, image: Arc::new(GrayImage::new(1, 1)) }
    }

    fn run(frames: Vec<Frame>) -> Vec<Vec<usize>> {
        let mut a = FrameSetAssembler::new(3, 10.0);
        let mut out: Vec<FrameSet> = frames.into_iter().flat_map(|fr| a.push(fr)).collect();
        out.extend(a.flush());
        out.iter().map(|s| s.frames.iter().map(|f| f.camera).collect()).collect()
    }

    #[test]
    fn groups_within_tolerance_and_closes_when_complete() {
        let sets = run(vec![f(0, 0), f(1, 3), f(2, 5), f(0, 100), f(1, 104), f(2, 98)]);
        assert_eq!(sets, vec![vec![0, 1, 2], vec![0, 1, 2]]);
    }

    #[test]
    fn dropped_frame_makes_a_smaller_set_never_two_of_one_camera() {
        // camera 2 dropped its first frame; camera 0 comes twice close together.
        let sets = run(vec![f(0, 0), f(1, 2), f(0, 100), f(1, 101), f(2, 102), f(0, 200), f(0, 205)]);
        assert_eq!(sets, vec![vec![0, 1], vec![0, 1, 2], vec![0], vec![0]]);
    }

    #[test]
    fn far_apart_frames_form_separate_sets_and_late_frames_are_counted() {
        let mut a = FrameSetAssembler::new(2, 10.0);
        assert!(a.push(f(0, 0)).is_empty());
        let s = a.push(f(1, 50));
        assert_eq!(s.len(), 1);
        assert_eq!(s[0].frames.len(), 1);
        assert!(a.push(f(0, 20)).is_empty()); // older than the open set's anchor - tolerance
        assert!(a.push(f(1, 0)).is_empty()); // not newer than the closed first set
        assert_eq!(a.late_frames(), 2);
        let set = a.flush().pop().unwrap();
        assert_eq!(set.seq, 1);
        assert_eq!(set.t_ns, f(1, 50).t_ns);
    }

    #[test]
    fn poll_closes_a_stale_set_and_mean_time_is_used() {
        let mut a = FrameSetAssembler::new(3, 10.0);
        a.push(f(0, 0));
        a.push(f(1, 4));
        assert!(a.poll(std::time::Duration::from_secs(60)).is_empty());
        std::thread::sleep(std::time::Duration::from_millis(5));
        let set = a.poll(std::time::Duration::from_millis(1)).pop().unwrap();
        assert_eq!(set.t_ns, f(0, 2).t_ns);
        // A late frame of camera 2 does not start an earlier set.
        assert!(a.push(f(2, 3)).is_empty());
        assert_eq!(a.late_frames(), 1);
        // A frame just after the closed set's newest frame starts the next set.
        assert!(a.push(f(2, 5)).is_empty());
        assert_eq!(a.flush().pop().unwrap().frames.len(), 1);
    }

    #[test]
    fn live_assembler_lets_a_lagging_camera_join_its_set() {
        let mut a = FrameSetAssembler::with_open_sets(3, 10.0, 3);
        let mut sets = Vec::new();
        // Camera 2 lags by more than a frame period behind cameras 0 and 1.
        for (c, t) in [(0, 0), (1, 1), (0, 100), (1, 101), (2, 2), (0, 200), (2, 99), (1, 199), (2, 201)] {
            sets.extend(a.push(f(c, t)));
        }
        let cams: Vec<Vec<usize>> = sets.iter().map(|s| s.frames.iter().map(|f| f.camera).collect()).collect();
        assert_eq!(cams, vec![vec![0, 1, 2], vec![0, 1, 2], vec![0, 1, 2]]);
        assert_eq!(a.late_frames(), 0);
    }

    #[test]
    fn frame_set_times_never_go_back() {
        let mut a = FrameSetAssembler::new(3, 10.0);
        let mut times = Vec::new();
        // Cameras arrive out of order and late, some sets closed early.
        for (i, (c, t)) in [(0, 0), (2, 8), (1, 30), (0, 35), (2, 9), (1, 2), (2, 40), (0, 70), (1, 69), (2, 75)].into_iter().enumerate() {
            for s in a.push(f(c, t)) {
                times.push(s.t_ns);
            }
            if i == 3 {
                times.extend(a.flush().iter().map(|s| s.t_ns));
            }
        }
        times.extend(a.flush().iter().map(|s| s.t_ns));
        assert!(times.windows(2).all(|w| w[1] > w[0]), "{times:?}");
    }

    #[test]
    fn frames_far_older_than_the_last_set_never_make_a_set_out_of_order() {
        // Times that jump back by 5 s (a device clock's glitch): late frames, never a set
        // older than one already closed (the process clock itself never goes back).
        let mut a = FrameSetAssembler::with_open_sets(2, 10.0, 3);
        let mut sets = Vec::new();
        for t in [0, 33, 66, 100, 133 - 5000, 166 - 5000, 200, 233] {
            sets.extend(a.push(f(0, t)));
            sets.extend(a.push(f(1, t + 1)));
        }
        sets.extend(a.flush());
        assert!(sets.windows(2).all(|w| w[1].t_ns > w[0].t_ns));
        assert_eq!(sets.len(), 6);
        assert_eq!(a.late_frames(), 4);
    }

    #[test]
    fn extreme_times_do_not_overflow() {
        let mut a = FrameSetAssembler::with_open_sets(2, 10.0, 3);
        for t in [i64::MAX, i64::MIN, 0, i64::MAX - 1, i64::MIN + 1] {
            let fr = Frame { camera: 0, seq: 0, t_ns: t, image: Arc::new(GrayImage::new(1, 1)) };
            let _ = a.push(fr);
        }
        let _ = a.flush();
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
