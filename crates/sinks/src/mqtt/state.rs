//! The publisher's state behind its one lock: the lines owed to the archive (in memory,
//! read back, to send, delivered), the publishes in flight, the archive's last word and the
//! status; and [`Shared`], what the publisher's tasks share, with the steps that move lines
//! along: pump into the client, the broker's acknowledgements, the archive's.

use std::collections::{BTreeMap, HashMap, VecDeque};
use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use rumqttc::{AsyncClient, QoS};

use super::feed_source::FeedSource;
use super::lab_test::LabOut;
use super::MqttStats;
use crate::status::RigStatus;
use tagdeflect_wire::{ArchiveAck, RunHeld, SeqRanges};

/// Who an outgoing publish belongs to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Sent {
    Line(u64),
    Status,
    /// A lab test's record, by the serial number of that publish.
    Lab(u64),
}

/// A line acknowledged by the broker is sent again only if the archive still lacks it this
/// long after (the archive's view may be a moment older than the broker's acknowledgement).
pub(super) const RESEND_AFTER: Duration = Duration::from_secs(1);
/// At the end of a run, the lines the archive has not confirmed (those past its high
/// water: a broker that lost them leaves no later line to show the gap) are sent again
/// after this long without progress.
pub(super) const TAIL_RESEND_AFTER: Duration = Duration::from_secs(2);

pub(super) struct State {
    pub(super) connected: bool,
    pub(super) stopping: bool,
    /// The newest unconfirmed lines, by seq (at most `cap`).
    pub(super) mem: BTreeMap<u64, Vec<u8>>,
    /// Older lines read back from the feed file to be sent.
    pub(super) loaded: BTreeMap<u64, Vec<u8>>,
    /// Seqs to send: never sent, or sent again because the archive lacks them.
    pub(super) todo: SeqRanges,
    /// Seqs the broker acknowledged that the archive has not confirmed.
    pub(super) delivered: SeqRanges,
    /// Seqs acknowledged by the broker within [`RESEND_AFTER`], with when.
    pub(super) recent: VecDeque<(u64, Instant)>,
    /// Publishes handed to the client, in order, awaiting their packet id.
    pub(super) order: VecDeque<Sent>,
    /// Packet id → publish awaiting its acknowledgement.
    pub(super) pkids: HashMap<u16, Sent>,
    /// A publish parked by the client on a packet-id collision.
    pub(super) collided: Option<(u16, Sent)>,
    pub(super) status: RigStatus,
    /// Lines the archive will never get from this rig (left memory unsent, not in a feed file).
    pub(super) dropped: u64,
    /// Lines handed over in this run.
    pub(super) made: u64,
    /// `t_ns` of this run's first line (tells this run from earlier ones of the same test id).
    pub(super) first_t_ns: Option<i64>,
    /// What the archive last said it holds of this run.
    pub(super) archive: Option<RunHeld>,
    /// When the archive's confirmations last advanced.
    pub(super) archive_progress: Option<Instant>,
    /// The feed file loader wants to run.
    pub(super) want_load: bool,
    /// The lab tests' records, oldest first.
    pub(super) lab: Vec<LabOut>,
    /// Serial number of the last lab record publish.
    pub(super) lab_serial: u64,
}

impl State {
    /// Nothing owed yet, not connected; the status to publish.
    pub(super) fn new(status: RigStatus) -> State {
        State {
            connected: false,
            stopping: false,
            mem: BTreeMap::new(),
            loaded: BTreeMap::new(),
            todo: SeqRanges::new(),
            delivered: SeqRanges::new(),
            recent: VecDeque::new(),
            order: VecDeque::new(),
            pkids: HashMap::new(),
            collided: None,
            status,
            dropped: 0,
            made: 0,
            first_t_ns: None,
            archive: None,
            archive_progress: None,
            want_load: false,
            lab: Vec::new(),
            lab_serial: 0,
        }
    }

    pub(super) fn in_flight(&self) -> usize {
        self.order.len() + self.pkids.len() + usize::from(self.collided.is_some())
    }

    /// Lines not confirmed by the archive (to send, in flight or delivered).
    pub(super) fn unconfirmed(&self) -> u64 {
        let flying = self.order.iter().chain(self.pkids.values()).chain(self.collided.iter().map(|c| &c.1));
        self.todo.len() + self.delivered.len() + flying.filter(|w| matches!(w, Sent::Line(_))).count() as u64
    }

    /// Lines not acknowledged by the broker (to send or in flight).
    pub(super) fn undelivered(&self) -> u64 {
        let flying = self.order.iter().chain(self.pkids.values()).chain(self.collided.iter().map(|c| &c.1));
        self.todo.len() + flying.filter(|w| matches!(w, Sent::Line(_))).count() as u64
    }
}

pub(super) struct Shared {
    pub(super) state: Mutex<State>,
    pub(super) stats: Arc<MqttStats>,
    pub(super) client: AsyncClient,
    pub(super) feed_topic: String,
    pub(super) status_topic: String,
    pub(super) ack_topic: String,
    /// `<topic>`, for `<topic>/labtest/<id>`.
    pub(super) base_topic: String,
    pub(super) rig: String,
    pub(super) qos: QoS,
    pub(super) window: usize,
    pub(super) cap: usize,
    pub(super) feed: Option<Mutex<FeedSource>>,
    pub(super) load: tokio::sync::Notify,
}

impl Shared {
    /// Hands lines to the client while connected and the in-flight window allows, oldest
    /// first (lines the archive lacks come before new ones).
    pub(super) fn pump(&self, st: &mut State) {
        while st.connected && st.in_flight() < self.window {
            let Some((seq, _)) = st.todo.iter().next() else { break };
            let bytes = match st.mem.get(&seq).or_else(|| st.loaded.get(&seq)) {
                Some(b) => b.clone(),
                None if self.feed.is_some() => {
                    st.want_load = true;
                    self.load.notify_one();
                    break;
                }
                None => {
                    // Left memory with no feed file to read it back from.
                    self.forget(st, seq);
                    continue;
                }
            };
            match self.client.try_publish(self.feed_topic.clone(), self.qos, false, bytes) {
                Ok(()) => {
                    st.todo.remove(seq);
                    st.order.push_back(Sent::Line(seq));
                }
                Err(_) => break,
            }
        }
        self.update_stats(st);
    }

    pub(super) fn update_stats(&self, st: &State) {
        self.stats.buffered.store(st.mem.len() as u64, Ordering::Relaxed);
        self.stats.unconfirmed.store(st.unconfirmed(), Ordering::Relaxed);
        if let Some(a) = &st.archive {
            self.stats.archive_high.store(a.high, Ordering::Relaxed);
            self.stats.archive_confirmed.store(a.lines, Ordering::Relaxed);
            self.stats.archive_lag.store(st.made.saturating_sub(a.lines), Ordering::Relaxed);
        }
    }

    /// A line that can no longer be sent: lost for the archive if the broker never had it.
    pub(super) fn forget(&self, st: &mut State, seq: u64) {
        st.loaded.remove(&seq);
        if st.todo.contains(seq) {
            st.todo.remove(seq);
            if !st.archive.as_ref().is_some_and(|a| a.held().contains(seq)) {
                st.dropped += 1;
                self.stats.dropped.fetch_add(1, Ordering::Relaxed);
            }
        } else if st.delivered.contains(seq) {
            // The broker has it; whether the archive gets it is out of this rig's hands.
            st.delivered.remove(seq);
            self.stats.evicted_unconfirmed.fetch_add(1, Ordering::Relaxed);
        }
    }

    pub(super) fn send_status(&self, st: &mut State) {
        st.status.mqtt_dropped = st.dropped;
        st.status.archive_lag = st.archive.as_ref().map(|a| st.made.saturating_sub(a.lines));
        let payload = serde_json::to_vec(&st.status).expect("status serialises");
        if self.client.try_publish(self.status_topic.clone(), QoS::AtLeastOnce, true, payload).is_ok() {
            st.order.push_back(Sent::Status);
        }
    }

    pub(super) fn acked(&self, st: &mut State, who: Sent) {
        if let Sent::Lab(serial) = who {
            if let Some(l) = st.lab.iter_mut().find(|l| l.serial == serial) {
                l.delivered = true;
            }
        }
        if let Sent::Line(seq) = who {
            self.stats.published.fetch_add(1, Ordering::Relaxed);
            st.loaded.remove(&seq);
            if st.archive.as_ref().is_some_and(|a| a.held().contains(seq)) {
                return;
            }
            st.delivered.insert(seq);
            let now = Instant::now();
            st.recent.push_back((seq, now));
            while st.recent.front().is_some_and(|(_, t)| now.duration_since(*t) > RESEND_AFTER) {
                st.recent.pop_front();
            }
        }
    }

    /// The archive's retained acknowledgement of this test: forgets what it holds of this
    /// run, sends again what the broker acknowledged but the archive lacks below its high
    /// water.
    pub(super) fn archive_acked(&self, st: &mut State, payload: &[u8]) {
        let ack: ArchiveAck = match serde_json::from_slice(payload) {
            Ok(a) => a,
            Err(e) => {
                tracing::warn!(topic = %self.ack_topic, "MQTT: the archive's acknowledgement is not readable ({e}); ignored");
                return;
            }
        };
        let Some(first) = st.first_t_ns else { return };
        let Some(run) = ack.run_of(first).cloned() else { return };
        let held = run.held();
        let before = st.unconfirmed();
        for (a, b) in held.iter() {
            st.todo.remove_range(a, b);
            st.delivered.remove_range(a, b);
        }
        st.mem.retain(|k, _| !held.contains(*k));
        st.loaded.retain(|k, _| !held.contains(*k));
        // Delivered, missing below the high water and not just acknowledged: lost on the way.
        let now = Instant::now();
        let recent: std::collections::HashSet<u64> =
            st.recent.iter().filter(|(_, t)| now.duration_since(*t) <= RESEND_AFTER).map(|(s, _)| *s).collect();
        let mut again = 0u64;
        for &(a, b) in &run.gaps {
            let hits: Vec<(u64, u64)> = st.delivered.iter().filter(|&(s, e)| s <= b && e >= a).map(|(s, e)| (s.max(a), e.min(b))).collect();
            for (s, e) in hits {
                for seq in s..=e {
                    if !recent.contains(&seq) {
                        st.delivered.remove(seq);
                        st.todo.insert(seq);
                        again += 1;
                    }
                }
            }
        }
        if again > 0 {
            tracing::info!(
                lines = again,
                archive_high = run.high,
                "MQTT: the archive lacks lines the broker acknowledged; sending them again"
            );
        }
        if st.archive.as_ref().is_none_or(|a| a.lines != run.lines) || st.unconfirmed() < before {
            st.archive_progress = Some(now);
        }
        st.archive = Some(run);
        self.pump(st);
    }
}
