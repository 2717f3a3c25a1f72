//! Where finished lines go: every sink behind one trait ([`LineSink`]), fed by one thread of
//! their own ([`Fanout`]) so that no sink — a feed file on a slow disk, a live page, a broker
//! — ever holds the measurement back.
//!
//! The measurement hands each finished frame set to [`Fanout::send`], which never waits: the
//! line goes into a queue of at most [`QUEUE_LINES`] lines (at 30 frame sets/s, over five
//! minutes), and the frame set's images ride along only while the queue is short (at most
//! [`QUEUE_SETS_WITH_IMAGES`] sets), so a stalled sink costs little memory. Should the queue
//! ever fill, the oldest line is dropped, counted ([`Fanout::dropped`]) and logged: that is a
//! sink stalled for minutes, which its own error reporting has said by then.
//!
//! A replay as fast as it goes ([`Overflow::Wait`]) wants the opposite: every line, however
//! slow the reader of its stdout; there `send` waits for room instead of dropping.
//!
//! Every sink sees the lines in order, complete: status counters (recorder state, drops,
//! `mqtt_dropped`) are written into the line before it leaves the measurement, never by a
//! sink, so the order of sinks cannot change the output.

use std::collections::VecDeque;
use std::sync::{Arc, Condvar, Mutex};
use std::thread::JoinHandle;

use tagdeflect_core::feed::FeedLine;
use tagdeflect_core::frame::FrameSet;
use tagdeflect_core::observed::Observed;

/// Lines queued for the sinks at most.
pub(crate) const QUEUE_LINES: usize = 10_000;
/// Queued lines that keep their frame set's images (for the live page's thumbnails).
pub(crate) const QUEUE_SETS_WITH_IMAGES: usize = 4;

/// A finished frame set as the sinks receive it.
#[derive(Debug, Clone)]
pub struct Finished {
    /// The complete feed line.
    pub line: FeedLine,
    /// The frame set's images (absent when the queue was long: the live page then skips
    /// that set's thumbnails).
    pub set: Option<FrameSet>,
    /// What the measurement saw in the set: tags per camera and the cameras' poses.
    pub observed: Arc<Observed>,
}

/// A sink of finished lines.
pub trait LineSink: Send {
    /// What it is, for logs.
    fn name(&self) -> String;
    /// Takes one finished frame set (in order). A sink whose output fails reports and
    /// retries on its own; it never panics on a bad output.
    fn accept(&mut self, finished: &Finished);
    /// The run ended: flush (a sink whose end takes time — a broker — finishes on its own
    /// handle, see the graph).
    fn finish(&mut self) {}
}

struct Queue {
    lines: VecDeque<Finished>,
    closed: bool,
    dropped: u64,
}

/// What [`Fanout::send`] does when [`QUEUE_LINES`] lines wait.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Overflow {
    /// Drop the oldest line and count it: the measurement never waits (live runs).
    #[default]
    DropOldest,
    /// Wait until the sinks have taken a line: nothing is lost and the producer slows to the
    /// sinks' pace (a replay as fast as it goes, which has no camera to keep up with).
    Wait,
}

/// The sinks' thread and its queue.
pub struct Fanout {
    shared: Arc<Shared>,
    overflow: Overflow,
    thread: Option<JoinHandle<Vec<Box<dyn LineSink>>>>,
}

struct Shared {
    queue: Mutex<Queue>,
    /// A line was queued, or the queue closed.
    ready: Condvar,
    /// A line was taken ([`Overflow::Wait`]).
    room: Condvar,
}

impl Fanout {
    /// Starts the thread that feeds `sinks`, in this order; a full queue drops its oldest line.
    pub fn start(sinks: Vec<Box<dyn LineSink>>) -> std::io::Result<Fanout> {
        Self::start_with(sinks, Overflow::DropOldest)
    }

    /// Starts the thread that feeds `sinks`, in this order, with the given overflow policy.
    pub fn start_with(sinks: Vec<Box<dyn LineSink>>, overflow: Overflow) -> std::io::Result<Fanout> {
        let shared = Arc::new(Shared {
            queue: Mutex::new(Queue { lines: VecDeque::new(), closed: false, dropped: 0 }),
            ready: Condvar::new(),
            room: Condvar::new(),
        });
        let s = shared.clone();
        let thread = std::thread::Builder::new().name("sinks".into()).spawn(move || run(&s, sinks))?;
        Ok(Fanout { shared, overflow, thread: Some(thread) })
    }

    /// Queues a finished set for every sink. With [`Overflow::DropOldest`] it never waits;
    /// with [`Overflow::Wait`] it waits while the queue is full (see the module doc).
    pub fn send(&self, mut finished: Finished) {
        let mut q = self.shared.queue.lock().expect("sink queue");
        if self.overflow == Overflow::Wait {
            // `closed`: the sinks' thread has ended (it failed); drop-oldest from there on.
            while q.lines.len() >= QUEUE_LINES && !q.closed {
                q = self.shared.room.wait(q).expect("sink queue");
            }
        }
        if q.lines.len() >= QUEUE_SETS_WITH_IMAGES {
            finished.set = None;
        }
        if q.lines.len() >= QUEUE_LINES {
            q.lines.pop_front();
            q.dropped += 1;
            if q.dropped.is_power_of_two() {
                tracing::error!(dropped = q.dropped, "the sinks are stalled: {QUEUE_LINES} lines wait; the oldest are dropped");
            }
        }
        q.lines.push_back(finished);
        self.shared.ready.notify_one();
    }

    /// Lines dropped because the sinks were stalled.
    pub fn dropped(&self) -> u64 {
        self.shared.queue.lock().expect("sink queue").dropped
    }

    /// Lets the sinks take every queued line, finishes each and ends the thread.
    pub fn finish(mut self) {
        self.close_and_join();
    }

    fn close_and_join(&mut self) {
        {
            self.shared.queue.lock().expect("sink queue").closed = true;
            self.shared.ready.notify_all();
        }
        if let Some(t) = self.thread.take() {
            match t.join() {
                Ok(mut sinks) => sinks.iter_mut().for_each(|s| s.finish()),
                Err(_) => tracing::error!("the sinks' thread failed; lines after the failure were not written"),
            }
        }
    }
}

impl Drop for Fanout {
    fn drop(&mut self) {
        self.close_and_join();
    }
}

/// Marks the queue closed when the sinks' thread ends, even by a panic, so that a sender
/// waiting for room ([`Overflow::Wait`]) is let go.
struct CloseOnExit<'a>(&'a Shared);

impl Drop for CloseOnExit<'_> {
    fn drop(&mut self) {
        if let Ok(mut q) = self.0.queue.lock() {
            q.closed = true;
        }
        self.0.room.notify_all();
    }
}

fn run(shared: &Shared, mut sinks: Vec<Box<dyn LineSink>>) -> Vec<Box<dyn LineSink>> {
    let _close = CloseOnExit(shared);
    loop {
        let next = {
            let mut q = shared.queue.lock().expect("sink queue");
            loop {
                if let Some(f) = q.lines.pop_front() {
                    shared.room.notify_one();
                    break Some(f);
                }
                if q.closed {
                    break None;
                }
                q = shared.ready.wait(q).expect("sink queue");
            }
        };
        let Some(f) = next else { return sinks };
        for s in sinks.iter_mut() {
            s.accept(&f);
        }
    }
}

/// A feed file (or stdout) as a sink: every line written and flushed in order
/// ([`tagdeflect_core::feed_file::FeedWriter`] holds lines back and retries while its output
/// fails).
pub struct FeedFileSink(pub tagdeflect_core::feed_file::FeedWriter);

impl LineSink for FeedFileSink {
    fn name(&self) -> String {
        format!("feed {}", self.0.target())
    }
    fn accept(&mut self, finished: &Finished) {
        if let Err(e) = self.0.write(&finished.line) {
            tracing::error!("{e}");
        }
    }
    fn finish(&mut self) {
        if let Err(e) = self.0.finish() {
            tracing::error!(output = %self.0.target(), "feed output: {e}");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::{AtomicBool, Ordering};

    struct Slow {
        seen: Arc<Mutex<Vec<(u64, bool)>>>,
        gate: Arc<AtomicBool>,
        finished: Arc<AtomicBool>,
    }

    impl LineSink for Slow {
        fn name(&self) -> String {
            "slow".into()
        }
        fn accept(&mut self, f: &Finished) {
            while !self.gate.load(Ordering::SeqCst) {
                std::thread::sleep(std::time::Duration::from_millis(1));
            }
            self.seen.lock().unwrap().push((f.line.seq, f.set.is_some()));
        }
        fn finish(&mut self) {
            self.finished.store(true, Ordering::SeqCst);
        }
    }

    fn finished(seq: u64) -> Finished {
        let line = FeedLine { seq, ..FeedLine::default() };
        Finished { line, set: Some(FrameSet::new(seq, Vec::new())), observed: Arc::new(Observed::default()) }
    }

    #[test]
    fn a_stalled_sink_never_blocks_the_sender_and_loses_nothing_within_the_queue() {
        let seen = Arc::new(Mutex::new(Vec::new()));
        let gate = Arc::new(AtomicBool::new(false));
        let done = Arc::new(AtomicBool::new(false));
        let sink = Slow { seen: seen.clone(), gate: gate.clone(), finished: done.clone() };
        let fan = Fanout::start(vec![Box::new(sink)]).unwrap();
        // The sink is stalled: 100 sends return at once.
        for k in 0..100 {
            fan.send(finished(k));
        }
        assert_eq!(fan.dropped(), 0);
        gate.store(true, Ordering::SeqCst);
        fan.finish();
        let seen = seen.lock().unwrap();
        assert_eq!(seen.iter().map(|s| s.0).collect::<Vec<_>>(), (0..100).collect::<Vec<_>>(), "every line, in order");
        // Images rode along only while the queue was short.
        let with_images = seen.iter().filter(|s| s.1).count();
        assert!((1..=QUEUE_SETS_WITH_IMAGES + 1).contains(&with_images), "{with_images} sets kept their images");
        assert!(done.load(Ordering::SeqCst), "finish reached the sink");
    }

    #[test]
    fn with_overflow_wait_a_full_queue_slows_the_sender_and_drops_nothing() {
        let seen = Arc::new(Mutex::new(Vec::new()));
        let gate = Arc::new(AtomicBool::new(false));
        let done = Arc::new(AtomicBool::new(false));
        let sink = Slow { seen: seen.clone(), gate: gate.clone(), finished: done.clone() };
        let fan = Arc::new(Fanout::start_with(vec![Box::new(sink)], Overflow::Wait).unwrap());
        let total = QUEUE_LINES as u64 + 50;
        let sender = {
            let fan = fan.clone();
            std::thread::spawn(move || (0..total).for_each(|k| fan.send(finished(k))))
        };
        // The sender fills the queue and then waits: it cannot finish while the sink is stalled.
        while fan.shared.queue.lock().unwrap().lines.len() < QUEUE_LINES {
            std::thread::yield_now();
        }
        assert!(!sender.is_finished(), "the sender waits for room");
        gate.store(true, Ordering::SeqCst);
        sender.join().unwrap();
        let fan = Arc::try_unwrap(fan).ok().expect("one owner left");
        assert_eq!(fan.dropped(), 0);
        fan.finish();
        let seen = seen.lock().unwrap();
        assert_eq!(seen.iter().map(|s| s.0).collect::<Vec<_>>(), (0..total).collect::<Vec<_>>(), "every line, in order");
    }
}
