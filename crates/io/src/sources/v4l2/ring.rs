//! The ring of memory-mapped V4L2 buffers: when a buffer is waited for, dequeued and
//! requeued ([`ring_next`], a small state machine over [`BufferRing`]), so that a camera that
//! pauses is never reported lost for a buffer queued twice. Tested against a model of the
//! kernel's buffer queue (videobuf2) in the unit tests below.

use std::io;
use std::time::Duration;

use v4l::io::mmap::Stream as MmapStream;
use v4l::io::traits::CaptureStream;

/// One dequeued buffer as [`ring_next`] hands it over.
#[derive(Debug, Clone, Copy)]
pub(crate) struct RawBuffer<'a> {
    /// The whole mapping of the buffer.
    pub data: &'a [u8],
    /// Bytes of `data` the driver filled.
    pub bytesused: u32,
    /// `v4l2_buffer.flags`.
    pub flags: u32,
    /// Driver timestamp, seconds.
    pub sec: i64,
    /// Driver timestamp, microseconds.
    pub usec: i64,
}

/// The calls [`ring_next`] makes on a memory-mapped V4L2 buffer ring: the `v4l` crate's
/// stream (on a non-blocking fd), or a model of the kernel's queue in tests.
pub(crate) trait BufferRing {
    /// `VIDIOC_QBUF` of buffer `index`.
    fn queue(&mut self, index: usize) -> io::Result<()>;
    /// `VIDIOC_STREAMON`.
    fn start(&mut self) -> io::Result<()>;
    /// `VIDIOC_DQBUF` (non-blocking: `WouldBlock` when no buffer is done); the stream
    /// remembers the index as the one to requeue next.
    fn dequeue(&mut self) -> io::Result<usize>;
    /// `poll(POLLIN)` for up to `timeout`: true when a buffer is done or the device reports
    /// an error condition (unplugged: the next call fails with `ENODEV`).
    fn ready(&mut self, timeout: Duration) -> io::Result<bool>;
    /// The crate's `CaptureStream::next`: requeues the buffer dequeued last, dequeues the
    /// next and hands it to `f`.
    fn requeue_and_next<T>(&mut self, f: impl FnOnce(RawBuffer<'_>) -> T) -> io::Result<T>;
}

/// Where a buffer ring stands between two [`ring_next`] calls.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum RingState {
    /// Buffers allocated, none queued, not streaming.
    Fresh,
    /// Streaming; every buffer is with the driver.
    Streaming,
    /// Streaming; the buffer dequeued last is held by us (the stream requeues it next).
    Holding,
}

/// What one [`ring_next`] call produced.
#[derive(Debug)]
pub(crate) enum RingNext<T> {
    /// A buffer, handed to the closure, and what it returned.
    Buffer(T),
    /// No buffer within the timeout (or the ring's first buffer, which is requeued unread).
    Timeout,
    /// The device failed (unplugged: `ENODEV`).
    Failed(io::Error),
}

/// Waits up to `timeout` for the next filled buffer of `ring` and hands it to `f`.
///
/// The `v4l` crate's `CaptureStream::next` requeues the buffer it handed out last *before*
/// waiting; when its wait times out that buffer is already back with the driver, and the
/// following `next` queues it a second time: `VIDIOC_QBUF` fails with `EINVAL` and a camera
/// that merely paused for longer than the wait (a slow or triggered camera, a frame rate
/// below 2 fps, a busy machine) was reported lost and reopened. Here the wait comes first
/// (`poll`), and the crate's `next` is only called once a buffer is done, so a timeout never
/// requeues anything. The crate's `next` also cannot start a stream without blocking on its
/// first buffer, so the ring is started here (`n` buffers queued, `STREAMON`) and its first
/// buffer is dequeued by hand (and requeued unread: the crate gives no access to a buffer
/// it did not hand out itself).
pub(crate) fn ring_next<R: BufferRing, T>(
    ring: &mut R,
    state: &mut RingState,
    n: usize,
    timeout: Duration,
    f: impl FnOnce(RawBuffer<'_>) -> T,
) -> RingNext<T> {
    if *state == RingState::Fresh {
        for i in 0..n.max(1) {
            match ring.queue(i) {
                Ok(()) => {}
                // The driver gave fewer buffers than asked for.
                Err(e) if i > 0 && e.raw_os_error() == Some(libc::EINVAL) => break,
                Err(e) => return RingNext::Failed(e),
            }
        }
        if let Err(e) = ring.start() {
            return RingNext::Failed(e);
        }
        *state = RingState::Streaming;
    }
    match ring.ready(timeout) {
        Ok(true) => {}
        Ok(false) => return RingNext::Timeout,
        Err(e) => return RingNext::Failed(e),
    }
    if *state == RingState::Streaming {
        return match ring.dequeue() {
            Ok(_) => {
                *state = RingState::Holding;
                RingNext::Timeout
            }
            Err(e) if e.kind() == io::ErrorKind::WouldBlock => RingNext::Timeout,
            Err(e) => RingNext::Failed(e),
        };
    }
    match ring.requeue_and_next(f) {
        Ok(t) => RingNext::Buffer(t),
        // Requeued, then nothing to dequeue after all: every buffer is with the driver.
        Err(e) if matches!(e.kind(), io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut) => {
            *state = RingState::Streaming;
            RingNext::Timeout
        }
        Err(e) => RingNext::Failed(e),
    }
}

impl BufferRing for MmapStream<'static> {
    fn queue(&mut self, index: usize) -> io::Result<()> {
        CaptureStream::queue(self, index)
    }

    fn start(&mut self) -> io::Result<()> {
        v4l::io::traits::Stream::start(self)
    }

    fn dequeue(&mut self) -> io::Result<usize> {
        CaptureStream::dequeue(self)
    }

    fn ready(&mut self, timeout: Duration) -> io::Result<bool> {
        let ms = i32::try_from(timeout.as_millis()).unwrap_or(i32::MAX);
        Ok(self.handle().poll(libc::POLLIN, ms)? > 0)
    }

    // `time_t` is i64 on 64-bit Linux, i32 on some 32-bit targets.
    #[allow(clippy::useless_conversion)]
    fn requeue_and_next<T>(&mut self, f: impl FnOnce(RawBuffer<'_>) -> T) -> io::Result<T> {
        let (buf, meta) = CaptureStream::next(self)?;
        Ok(f(RawBuffer {
            data: buf,
            bytesused: meta.bytesused,
            flags: meta.flags.bits(),
            sec: i64::from(meta.timestamp.sec),
            usec: i64::from(meta.timestamp.usec),
        }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sources::v4l2::TIMESTAMP_MONOTONIC;

    /// A model of the kernel's buffer queue (videobuf2) as the `v4l` crate drives it:
    /// `QBUF` of a buffer already queued or done is `EINVAL`, `DQBUF` on the non-blocking
    /// fd is `EAGAIN` when none is done, and `requeue_and_next` is the crate's `next`
    /// (requeue the buffer dequeued last, wait with the crate's timeout, dequeue).
    /// `arrivals` scripts the camera: per wait, whether a frame is captured during it.
    struct ModelQueue {
        n: usize,
        queued: std::collections::VecDeque<usize>,
        done: std::collections::VecDeque<(usize, u8)>,
        held: Option<(usize, u8)>,
        last: usize,
        streaming: bool,
        arrivals: std::collections::VecDeque<bool>,
        captured: u8,
    }

    impl ModelQueue {
        fn new(n: usize, arrivals: &[bool]) -> Self {
            Self {
                n,
                queued: Default::default(),
                done: Default::default(),
                held: None,
                last: 0,
                streaming: false,
                arrivals: arrivals.iter().copied().collect(),
                captured: 0,
            }
        }

        /// One wait: the camera fills the oldest queued buffer if the script says so.
        fn wait(&mut self) -> bool {
            if self.arrivals.pop_front().unwrap_or(false) {
                if let Some(i) = self.queued.pop_front() {
                    self.captured += 1;
                    self.done.push_back((i, self.captured));
                }
            }
            !self.done.is_empty()
        }
    }

    fn errno(e: i32) -> io::Error {
        io::Error::from_raw_os_error(e)
    }

    impl BufferRing for ModelQueue {
        fn queue(&mut self, index: usize) -> io::Result<()> {
            let busy = self.queued.contains(&index) || self.done.iter().any(|(i, _)| *i == index);
            if index >= self.n || busy {
                return Err(errno(libc::EINVAL));
            }
            if self.held.is_some_and(|(i, _)| i == index) {
                self.held = None;
            }
            self.queued.push_back(index);
            Ok(())
        }

        fn start(&mut self) -> io::Result<()> {
            self.streaming = true;
            Ok(())
        }

        fn dequeue(&mut self) -> io::Result<usize> {
            let (i, content) = self.done.pop_front().ok_or_else(|| errno(libc::EAGAIN))?;
            self.held = Some((i, content));
            self.last = i;
            Ok(i)
        }

        fn ready(&mut self, _timeout: Duration) -> io::Result<bool> {
            Ok(self.wait())
        }

        fn requeue_and_next<T>(&mut self, f: impl FnOnce(RawBuffer<'_>) -> T) -> io::Result<T> {
            // The crate: queue(arena_index)?, then its own poll with the timeout, then DQBUF.
            let last = self.last;
            self.queue(last)?;
            if self.done.is_empty() && !self.wait() {
                return Err(io::Error::new(io::ErrorKind::TimedOut, "VIDIOC_DQBUF"));
            }
            self.dequeue()?;
            let content = [self.held.map_or(0, |(_, c)| c)];
            Ok(f(RawBuffer { data: &content, bytesused: 1, flags: TIMESTAMP_MONOTONIC, sec: 1, usec: 0 }))
        }
    }

    #[test]
    fn a_camera_that_pauses_is_not_lost_for_a_buffer_queued_twice() {
        // Four frames, a pause longer than three waits, four frames, a pause, two frames.
        let script = [true, true, true, true, false, false, false, true, true, true, true, false, true, true];
        let mut ring = ModelQueue::new(4, &script);
        let mut state = RingState::Fresh;
        let mut got = Vec::new();
        for _ in 0..script.len() {
            match ring_next(&mut ring, &mut state, 4, Duration::from_millis(1), |b| b.data[0]) {
                RingNext::Buffer(c) => got.push(c),
                RingNext::Timeout => {}
                RingNext::Failed(e) => panic!("failed after frames {got:?}: {e}"),
            }
        }
        // Frame 1 starts the ring (requeued unread); every later frame is delivered in order.
        assert_eq!(got, vec![2, 3, 4, 5, 6, 7, 8, 9, 10]);
        assert!(ring.streaming);
    }

    #[test]
    fn the_crates_next_after_a_timeout_queues_a_queued_buffer() {
        // What the capture did before `ring_next`: the crate's `next` straight away. After
        // its wait times out once, the next call queues the same buffer again: EINVAL, and
        // the camera was reported lost (seen on the vivid driver in a VM).
        let mut ring = ModelQueue::new(4, &[true, true, false, true]);
        for i in 0..4 {
            ring.queue(i).expect("queue");
        }
        ring.start().expect("start");
        assert!(ring.wait());
        ring.dequeue().expect("first buffer");
        assert!(ring.requeue_and_next(|b| b.data[0]).is_ok());
        let timed_out = ring.requeue_and_next(|b| b.data[0]).err().map(|e| e.kind());
        assert_eq!(timed_out, Some(io::ErrorKind::TimedOut));
        let again = ring.requeue_and_next(|b| b.data[0]).err().and_then(|e| e.raw_os_error());
        assert_eq!(again, Some(libc::EINVAL));
    }

    #[test]
    fn an_unplugged_ring_fails_instead_of_waiting() {
        struct Gone;
        impl BufferRing for Gone {
            fn queue(&mut self, _: usize) -> io::Result<()> {
                Err(errno(libc::ENODEV))
            }
            fn start(&mut self) -> io::Result<()> {
                Err(errno(libc::ENODEV))
            }
            fn dequeue(&mut self) -> io::Result<usize> {
                Err(errno(libc::ENODEV))
            }
            fn ready(&mut self, _: Duration) -> io::Result<bool> {
                Ok(true) // POLLERR | POLLHUP
            }
            fn requeue_and_next<T>(&mut self, _: impl FnOnce(RawBuffer<'_>) -> T) -> io::Result<T> {
                Err(errno(libc::ENODEV))
            }
        }
        for mut state in [RingState::Fresh, RingState::Streaming, RingState::Holding] {
            let got = ring_next(&mut Gone, &mut state, 4, Duration::from_millis(1), |_| ());
            assert!(matches!(got, RingNext::Failed(e) if e.raw_os_error() == Some(libc::ENODEV)), "{state:?}");
        }
    }
}
