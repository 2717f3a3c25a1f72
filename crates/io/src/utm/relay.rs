//! The bounded hand-over of UTM events from the poller to the solver thread.
//!
//! A plain channel grows without bound while its receiver does not read (a solver waiting
//! for frame sets that stopped, or no solver at all in `record`). This relay holds at most
//! `capacity` samples and drops the *oldest* sample when full (the newest are the ones the
//! next frame sets need); link events (`Up`/`Down`) are never dropped. Sending to a relay
//! whose receiver is gone is a cheap no-op.

use std::collections::VecDeque;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

use crate::utm::modbus::UtmEvent;

struct Shared {
    /// Events, receiver alive, samples among the events.
    queue: Mutex<(VecDeque<UtmEvent>, bool, usize)>,
    ready: Condvar,
    capacity: usize,
    dropped: AtomicU64,
}

/// The poller's side.
#[derive(Clone)]
pub struct RelaySender(Arc<Shared>);

/// The solver's side; dropping it makes later sends no-ops (and frees what is queued).
pub struct RelayReceiver(Arc<Shared>);

/// A relay holding at most `capacity` samples (at least 1).
pub fn relay(capacity: usize) -> (RelaySender, RelayReceiver) {
    let shared = Arc::new(Shared {
        queue: Mutex::new((VecDeque::new(), true, 0)),
        ready: Condvar::new(),
        capacity: capacity.max(1),
        dropped: AtomicU64::new(0),
    });
    (RelaySender(shared.clone()), RelayReceiver(shared))
}

impl RelaySender {
    /// Queues an event; returns `false` when the receiver is gone (the event is discarded).
    pub fn send(&self, ev: UtmEvent) -> bool {
        let mut g = self.0.queue.lock().expect("relay lock");
        if !g.1 {
            return false;
        }
        if matches!(ev, UtmEvent::Sample(_)) {
            if g.2 >= self.0.capacity {
                if let Some(i) = g.0.iter().position(|e| matches!(e, UtmEvent::Sample(_))) {
                    g.0.remove(i);
                    g.2 -= 1;
                    self.0.dropped.fetch_add(1, Ordering::Relaxed);
                }
            }
            g.2 += 1;
        }
        g.0.push_back(ev);
        self.0.ready.notify_one();
        true
    }

    /// Samples dropped because the receiver lagged.
    pub fn dropped(&self) -> u64 {
        self.0.dropped.load(Ordering::Relaxed)
    }
}

impl RelayReceiver {
    /// The next event, if one is queued.
    pub fn try_recv(&self) -> Option<UtmEvent> {
        Self::pop(&mut self.0.queue.lock().expect("relay lock"))
    }

    fn pop(g: &mut (VecDeque<UtmEvent>, bool, usize)) -> Option<UtmEvent> {
        let ev = g.0.pop_front()?;
        if matches!(ev, UtmEvent::Sample(_)) {
            g.2 -= 1;
        }
        Some(ev)
    }

    /// The next event, waiting at most `timeout`.
    pub fn recv_timeout(&self, timeout: Duration) -> Option<UtmEvent> {
        let until = Instant::now() + timeout;
        let mut g = self.0.queue.lock().expect("relay lock");
        loop {
            if let Some(ev) = Self::pop(&mut g) {
                return Some(ev);
            }
            let left = until.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return None;
            }
            g = self.0.ready.wait_timeout(g, left).expect("relay lock").0;
        }
    }

    /// Events queued.
    pub fn len(&self) -> usize {
        self.0.queue.lock().expect("relay lock").0.len()
    }

    /// True when nothing is queued.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

impl Drop for RelayReceiver {
    fn drop(&mut self) {
        let mut g = self.0.queue.lock().expect("relay lock");
        g.1 = false;
        g.0.clear();
        g.2 = 0;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::utm::UtmSample;

    fn sample(t: i64) -> UtmEvent {
        UtmEvent::Sample(UtmSample { t_ns: t, load_kn: 0.0, stroke_mm: None })
    }

    #[test]
    fn bounded_drop_oldest_keeps_link_events() {
        let (tx, rx) = relay(3);
        tx.send(UtmEvent::Down { reason: "x".into() });
        for t in 0..10 {
            assert!(tx.send(sample(t)));
        }
        assert_eq!(rx.len(), 4);
        assert_eq!(tx.dropped(), 7);
        assert!(matches!(rx.try_recv(), Some(UtmEvent::Down { .. })));
        assert!(matches!(rx.try_recv(), Some(UtmEvent::Sample(s)) if s.t_ns == 7));
        drop(rx);
        assert!(!tx.send(sample(11)), "no receiver: discarded");
    }

    #[test]
    fn recv_timeout_wakes_on_send() {
        let (tx, rx) = relay(8);
        let t = std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(20));
            tx.send(sample(1));
        });
        assert!(rx.recv_timeout(Duration::from_secs(5)).is_some());
        assert!(rx.recv_timeout(Duration::from_millis(5)).is_none());
        t.join().unwrap();
    }
}
