//! The sending side of a camera thread: delivery with `try_send` only, drop counting, and
//! connection events and drop counts kept until the channel takes them.

use std::collections::VecDeque;
use std::sync::atomic::Ordering;
use std::sync::Arc;

use tokio::sync::mpsc::error::TrySendError;
use tokio::sync::mpsc::Sender;

use super::{CaptureStats, DropReason, SourceEvent};
use tagdeflect_core::frame::Frame;

/// The sending side of one camera thread: never blocks, counts what it cannot deliver.
#[derive(Debug)]
pub(crate) struct Emitter {
    camera: usize,
    tx: Sender<SourceEvent>,
    pub(super) stats: Arc<CaptureStats>,
    /// Connection events not yet delivered (channel was full), oldest first.
    pending: VecDeque<SourceEvent>,
    /// Undelivered drop counts per reason.
    unreported: [u64; 3],
    closed: bool,
}

fn reason_index(r: DropReason) -> usize {
    match r {
        DropReason::ChannelFull => 0,
        DropReason::Incomplete => 1,
        DropReason::BadBuffer => 2,
    }
}

const REASONS: [DropReason; 3] = [DropReason::ChannelFull, DropReason::Incomplete, DropReason::BadBuffer];

impl Emitter {
    /// An emitter for camera `camera` with its counters.
    pub fn new(camera: usize, tx: Sender<SourceEvent>, stats: Arc<CaptureStats>) -> Self {
        Self { camera, tx, stats, pending: VecDeque::new(), unreported: [0; 3], closed: false }
    }

    /// The camera index.
    pub fn camera(&self) -> usize {
        self.camera
    }

    /// Whether the receiver is gone (the thread should end).
    pub fn is_closed(&self) -> bool {
        self.closed || self.tx.is_closed()
    }

    /// Delivers a frame, or drops and counts it if the channel is full.
    pub fn frame(&mut self, frame: Frame) {
        self.flush();
        if !self.pending.is_empty() {
            // Control events still waiting: keep their order, drop the frame.
            self.dropped(DropReason::ChannelFull, 1);
            return;
        }
        match self.tx.try_send(SourceEvent::Frame(frame)) {
            Ok(()) => {
                self.stats.delivered.fetch_add(1, Ordering::Relaxed);
            }
            Err(TrySendError::Full(_)) => self.dropped(DropReason::ChannelFull, 1),
            Err(TrySendError::Closed(_)) => self.closed = true,
        }
    }

    /// Counts `count` dropped frames; they are reported with the next delivery.
    pub fn dropped(&mut self, why: DropReason, count: u64) {
        let counter = match why {
            DropReason::ChannelFull => &self.stats.dropped_full,
            DropReason::Incomplete => &self.stats.incomplete,
            DropReason::BadBuffer => &self.stats.bad_buffers,
        };
        counter.fetch_add(count, Ordering::Relaxed);
        self.unreported[reason_index(why)] += count;
    }

    /// Reports the camera lost.
    pub fn lost(&mut self, reason: String) {
        tracing::warn!(camera = self.camera, %reason, "camera lost");
        self.stats.lost.fetch_add(1, Ordering::Relaxed);
        self.pending.push_back(SourceEvent::Lost { camera: self.camera, reason });
        self.flush();
    }

    /// Reports the camera streaming again.
    pub fn reopened(&mut self) {
        tracing::info!(camera = self.camera, "camera reopened");
        self.stats.reopened.fetch_add(1, Ordering::Relaxed);
        self.pending.push_back(SourceEvent::Reopened { camera: self.camera });
        self.flush();
    }

    /// Tries to deliver pending connection events and drop counts, in order.
    pub fn flush(&mut self) {
        while let Some(ev) = self.pending.pop_front() {
            match self.tx.try_send(ev) {
                Ok(()) => {}
                Err(TrySendError::Full(ev)) => {
                    self.pending.push_front(ev);
                    return;
                }
                Err(TrySendError::Closed(_)) => {
                    self.closed = true;
                    return;
                }
            }
        }
        for why in REASONS {
            let i = reason_index(why);
            let count = self.unreported[i];
            if count == 0 {
                continue;
            }
            match self.tx.try_send(SourceEvent::Dropped { camera: self.camera, count, why }) {
                Ok(()) => self.unreported[i] = 0,
                Err(TrySendError::Full(_)) => return,
                Err(TrySendError::Closed(_)) => {
                    self.closed = true;
                    return;
                }
            }
        }
    }
}
