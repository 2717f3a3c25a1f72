//! The queue in front of the solver: at most [`QUEUE_SETS`] frame sets; a live run drops the
//! oldest when the solver falls behind (counted), an as-fast replay waits for room instead.

use std::collections::VecDeque;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

use tagdeflect_core::frame::FrameSet;

/// Frame sets waiting for the solver at most; older ones are dropped first.
pub const QUEUE_SETS: usize = 2;

/// A bounded queue that drops its oldest entry when full.
pub(crate) struct SetQueue {
    inner: Mutex<(VecDeque<(FrameSet, Instant)>, bool)>,
    ready: Condvar,
    /// A set was taken (for [`SetQueue::push_wait`]).
    room: Condvar,
    dropped: AtomicU64,
}

impl SetQueue {
    pub(crate) fn new() -> Self {
        Self { inner: Mutex::new((VecDeque::new(), false)), ready: Condvar::new(), room: Condvar::new(), dropped: AtomicU64::new(0) }
    }

    /// Frame sets dropped so far (the oldest, when full; or queued after the solver ended).
    pub(crate) fn dropped(&self) -> u64 {
        self.dropped.load(Ordering::Relaxed)
    }

    /// Queues `set`, dropping the oldest when full: counted, and said with its seq (a WARN at
    /// the 1st, 2nd, 4th, 8th, ... drop of the run).
    pub(crate) fn push(&self, set: FrameSet) {
        let mut g = self.inner.lock().expect("queue lock");
        // Counted before the newer set is queued: the line of any set solved after it has it.
        let dropped = (g.0.len() >= QUEUE_SETS)
            .then(|| g.0.pop_front())
            .flatten()
            .map(|(old, _)| (old.seq, self.dropped.fetch_add(1, Ordering::Relaxed) + 1));
        g.0.push_back((set, Instant::now()));
        self.ready.notify_one();
        drop(g);
        if let Some((seq, count)) = dropped.filter(|(_, count)| count.is_power_of_two()) {
            tracing::warn!(seq, dropped_sets = count, "frame set dropped: the solver falls behind (its queue holds {QUEUE_SETS} sets); no feed line has this seq, counted in dropped_sets");
        }
    }

    /// Queues `set`, waiting while the queue is full (an as-fast replay: nothing dropped).
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
    pub(crate) fn push_by(&self, set: FrameSet, lossless: bool) {
        if lossless {
            self.push_wait(set)
        } else {
            self.push(set)
        }
    }

    /// No more sets: the solver ends once the queue is empty; a waiting producer is let go.
    pub(crate) fn close(&self) {
        self.inner.lock().expect("queue lock").1 = true;
        self.ready.notify_all();
        self.room.notify_all();
    }

    /// Next set (`Some(Some)`), nothing within `wait` (`Some(None)`), or `None` once closed
    /// and empty.
    #[allow(clippy::option_option)]
    pub(crate) fn pop_timeout(&self, wait: Duration) -> Option<Option<(FrameSet, Instant)>> {
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

/// Closes the queue when the solver ends, even by a panic: a producer waiting for room
/// ([`SetQueue::push_by`] with `lossless`) is let go.
pub(crate) struct CloseOnDrop(pub(crate) Arc<SetQueue>);

impl Drop for CloseOnDrop {
    fn drop(&mut self) {
        self.0.close();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A live run's full queue drops its oldest set and counts it before the newer set is
    /// queued: the solver takes the newest sets, and the line of any set taken after a drop
    /// counts it (the seqs missing from a feed are as many as its last line's `dropped_sets`).
    #[test]
    fn a_full_queue_drops_its_oldest_counted_before_the_newer_is_taken() {
        let q = SetQueue::new();
        for seq in 0..5 {
            q.push(FrameSet { seq, t_ns: 0, frames: Vec::new() });
        }
        assert_eq!(q.dropped(), 3);
        let taken: Vec<u64> = std::iter::from_fn(|| q.pop_timeout(Duration::ZERO).flatten().map(|(s, _)| s.seq)).collect();
        assert_eq!(taken, vec![3, 4]);
    }
}
