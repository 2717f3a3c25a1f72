//! The write loop: batches of messages into one transaction each, acknowledged to the
//! broker only after the commit; the archive's acknowledgements to the rigs.

use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Duration;

use rumqttc::{AsyncClient, Publish, QoS};
use tagdeflect_wire::TopicLayout;
use tokio::sync::{mpsc, watch};

use crate::db::{Db, LabTestRow, LineRow, StatusRow};
use crate::message::{parse_message, Parsed};
use crate::service::{chain, connect_db, retry_backoff, stopped, ArchiveStats};

/// What the write loop needs besides the connections.
pub(crate) struct WriteCtx {
    pub(crate) postgres: String,
    pub(crate) shared: bool,
    pub(crate) batch: usize,
    pub(crate) layout: TopicLayout,
    pub(crate) reconnected: Arc<std::sync::atomic::AtomicBool>,
}

/// The acknowledgements to publish: per test, when last published and whether it changed since.
#[derive(Default)]
struct Acks {
    tests: std::collections::HashMap<i64, AckState>,
}

struct AckState {
    rig: String,
    test: String,
    last: Option<tokio::time::Instant>,
    dirty: bool,
}

/// At most one acknowledgement per test this often (a committed batch marks it due).
const ACK_EVERY: Duration = Duration::from_millis(100);

impl Acks {
    fn touch(&mut self, touched: &[(String, String, i64)]) {
        for (rig, test, id) in touched {
            self.tests.entry(*id).or_insert_with(|| AckState { rig: rig.clone(), test: test.clone(), last: None, dirty: true }).dirty =
                true;
        }
    }

    /// Publishes the due acknowledgements (retained) on `<topic>/archive`.
    fn publish(&mut self, layout: &TopicLayout, client: &AsyncClient, db: &Db) {
        let now = tokio::time::Instant::now();
        for (id, a) in self.tests.iter_mut() {
            if !a.dirty || a.last.is_some_and(|t| now.duration_since(t) < ACK_EVERY) {
                continue;
            }
            let Some(h) = db.holdings(*id) else { continue };
            let ack = tagdeflect_wire::ArchiveAck {
                rig: a.rig.clone(),
                test: a.test.clone(),
                runs: h.ack_runs(),
                at_ns: tagdeflect_core::clock::now_epoch_ns(),
            };
            let topic = format!("{}/{}", layout.topic_of(&a.rig, &a.test), tagdeflect_wire::ACK_SUFFIX);
            let payload = serde_json::to_vec(&ack).expect("ack serialises");
            match client.try_publish(topic, QoS::AtLeastOnce, true, payload) {
                Ok(()) => {
                    a.dirty = false;
                    a.last = Some(now);
                }
                Err(e) => tracing::debug!("archive: acknowledgement not sent yet ({e})"),
            }
        }
    }
}

/// Takes the subscription's messages in batches (up to `ctx.batch`), commits each batch and
/// only then acknowledges its messages; publishes the archive's acknowledgements and logs
/// the throughput every 10 s. Returns when stopping (an uncommitted batch stays
/// unacknowledged, to be redelivered).
pub(crate) async fn write_loop(
    ctx: &WriteCtx,
    client: &AsyncClient,
    mut rx: mpsc::UnboundedReceiver<Publish>,
    db: &mut Db,
    stats: &ArchiveStats,
    stop: &mut watch::Receiver<bool>,
) {
    let mut report = tokio::time::interval(Duration::from_secs(10));
    report.tick().await;
    let mut ack_tick = tokio::time::interval(ACK_EVERY);
    let mut acks = Acks::default();
    let mut last_inserted = 0;
    loop {
        let first = tokio::select! {
            p = rx.recv() => p,
            _ = stopped(stop) => None,
            _ = ack_tick.tick() => {
                if ctx.reconnected.swap(false, Ordering::Relaxed) {
                    for a in acks.tests.values_mut() {
                        a.dirty = true;
                        a.last = None;
                    }
                }
                acks.publish(&ctx.layout, client, db);
                continue;
            }
            _ = report.tick() => {
                log_throughput(stats, &mut last_inserted);
                continue;
            }
        };
        let Some(first) = first else { return };
        let mut batch = vec![first];
        while batch.len() < ctx.batch {
            match rx.try_recv() {
                Ok(p) => batch.push(p),
                Err(_) => break,
            }
        }
        let rows = parse_batch(&ctx.layout, &batch, stats);
        if !commit(ctx, db, &rows, stats, stop, &mut acks).await {
            return; // stopping: the batch stays unacknowledged
        }
        for p in &batch {
            if client.ack(p).await.is_err() {
                break; // the MQTT task ended; unacknowledged messages will be redelivered
            }
        }
        acks.publish(&ctx.layout, client, db);
    }
}

/// The feed lines inserted in the last 10 s, when any.
fn log_throughput(stats: &ArchiveStats, last_inserted: &mut u64) {
    let n = stats.inserted.load(Ordering::Relaxed);
    if n != *last_inserted {
        tracing::info!(
            inserted = n,
            duplicates = stats.duplicates.load(Ordering::Relaxed),
            malformed = stats.malformed.load(Ordering::Relaxed),
            "archive: {} feed lines in the last 10 s",
            n - *last_inserted
        );
        *last_inserted = n;
    }
}

/// One batch's rows: its feed lines (a line repeated within the batch once), the newest
/// status of each test, its lab-test records.
struct BatchRows {
    lines: Vec<LineRow>,
    statuses: Vec<StatusRow>,
    labs: Vec<LabTestRow>,
}

/// A batch's messages parsed into rows; a malformed one is counted and logged, not kept.
fn parse_batch(layout: &TopicLayout, batch: &[Publish], stats: &ArchiveStats) -> BatchRows {
    let mut rows = BatchRows { lines: Vec::with_capacity(batch.len()), statuses: Vec::new(), labs: Vec::new() };
    let mut seen = std::collections::HashSet::new();
    for p in batch {
        match parse_message(layout, &p.topic, &p.payload) {
            Ok(Parsed::Line(l)) => {
                if seen.insert((l.rig.clone(), l.test.clone(), l.seq, l.t_ns)) {
                    rows.lines.push(l);
                } else {
                    stats.duplicates.fetch_add(1, Ordering::Relaxed);
                }
            }
            Ok(Parsed::Status(s)) => {
                rows.statuses.retain(|x| !(x.rig == s.rig && x.test == s.test));
                rows.statuses.push(s);
            }
            Ok(Parsed::LabTest(l)) => rows.labs.push(*l),
            Ok(Parsed::Skip) => {}
            Err(why) => {
                stats.malformed.fetch_add(1, Ordering::Relaxed);
                let head: String = String::from_utf8_lossy(&p.payload[..p.payload.len().min(80)]).chars().take(80).collect();
                // MQTT 3.1.1 does not say who published a message: the topic is all there is.
                tracing::warn!(
                    topic = %p.topic, bytes = p.payload.len(), retained = p.retain,
                    "archive: malformed message skipped: {why} (topic {}, publisher unknown to the archive: MQTT 3.1.1 does not name it; payload starts {head:?})",
                    p.topic
                );
            }
        }
    }
    rows
}

/// Commits a batch, retrying through database outages (reconnecting; one warning per
/// outage); false when stopping before it is committed.
async fn commit(
    ctx: &WriteCtx,
    db: &mut Db,
    rows: &BatchRows,
    stats: &ArchiveStats,
    stop: &mut watch::Receiver<bool>,
    acks: &mut Acks,
) -> bool {
    let mut backoff = retry_backoff();
    let mut logged = false;
    loop {
        if db.is_closed() {
            match connect_db(&ctx.postgres, ctx.shared, stats, stop).await {
                Some(d) => {
                    *db = d;
                    tracing::info!("archive: database back");
                }
                None => return false,
            }
        }
        match db.write_or_skip(&rows.lines, &rows.statuses, &rows.labs).await {
            Ok(w) => {
                stats.inserted.fetch_add(w.inserted, Ordering::Relaxed);
                stats.duplicates.fetch_add(w.duplicates, Ordering::Relaxed);
                stats.malformed.fetch_add(w.rejected, Ordering::Relaxed);
                stats.statuses.fetch_add(rows.statuses.len() as u64, Ordering::Relaxed);
                stats.batches.fetch_add(1, Ordering::Relaxed);
                acks.touch(&w.touched);
                break;
            }
            Err(e) => {
                stats.db_retries.fetch_add(1, Ordering::Relaxed);
                if !logged {
                    tracing::warn!(
                        "archive: cannot commit {} feed lines ({}); retrying, nothing acknowledged",
                        rows.lines.len(),
                        chain(&e)
                    );
                    logged = true;
                }
                tokio::select! {
                    _ = tokio::time::sleep(backoff.next_delay()) => {}
                    _ = stopped(stop) => return false,
                }
                if !db.is_closed() {
                    // A failed transaction on a live connection: start afresh.
                    match connect_db(&ctx.postgres, ctx.shared, stats, stop).await {
                        Some(d) => *db = d,
                        None => return false,
                    }
                }
            }
        }
    }
    if logged {
        tracing::info!("archive: committed after the database came back");
    }
    true
}
