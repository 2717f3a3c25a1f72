//! The publisher's counters, readable at any time (`/metrics`, the page's status).

use std::sync::atomic::AtomicU64;

/// Counters of the publisher, readable at any time (e.g. by `/metrics`).
#[derive(Debug, Default)]
pub struct MqttStats {
    /// Feed lines the archive will never get from this rig (they left the memory buffer
    /// unsent with no feed file to read them back from, or the feed file lost them).
    pub dropped: AtomicU64,
    /// Feed lines acknowledged by the broker (at QoS 0: written to the connection), sent
    /// again ones included.
    pub published: AtomicU64,
    /// Feed lines held in memory now (not confirmed by the archive).
    pub buffered: AtomicU64,
    /// Feed lines not confirmed by the archive (in memory or only in the feed file).
    pub unconfirmed: AtomicU64,
    /// Lines of this run made but not (yet) held by the archive, as it last said: its lag.
    pub archive_lag: AtomicU64,
    /// The archive's high-water seq of this run, as it last said.
    pub archive_high: AtomicU64,
    /// Lines of this run the archive holds, as it last said.
    pub archive_confirmed: AtomicU64,
    /// Lines that left memory after the broker acknowledged them but before the archive
    /// confirmed them, with no feed file to send them again from.
    pub evicted_unconfirmed: AtomicU64,
    /// 1 while connected to the broker.
    pub connected: AtomicU64,
    /// Successful connections after the first.
    pub reconnects: AtomicU64,
}
