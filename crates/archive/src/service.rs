//! The archive running: the broker's connection, the database's, retries with a backoff,
//! and the stop on SIGTERM/SIGINT (the writing itself: [`crate::writer`]).

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use rumqttc::{AsyncClient, Event, EventLoop, Packet, Publish, QoS};
use tagdeflect_core::backoff::Backoff;
use tagdeflect_wire::Kind;
use tokio::sync::{mpsc, watch};

use crate::db::{self, Db};
use crate::options::check_options;
use crate::writer::{write_loop, WriteCtx};
use crate::{backfill, ArchiveCommand, ArchiveError, ArchiveOptions};

/// The largest packet the archive reads off the connection (MQTT's own limit), so that no
/// message, however big, can break the connection and come back forever.
const MAX_PACKET_BYTES: usize = 268_435_455;

/// An error with its causes, `a: b: c` (what `tokio_postgres`'s "db error" hides).
pub fn chain(e: &dyn std::error::Error) -> String {
    let mut s = e.to_string();
    let mut cur = e.source();
    while let Some(c) = cur {
        let m = c.to_string();
        if !s.ends_with(&m) {
            s.push_str(": ");
            s.push_str(&m);
        }
        cur = c.source();
    }
    s
}

/// Counters of a running archive.
#[derive(Debug, Default)]
pub(crate) struct ArchiveStats {
    /// Feed lines newly stored.
    pub inserted: AtomicU64,
    /// Feed lines received again and already stored.
    pub duplicates: AtomicU64,
    /// Messages skipped as malformed (or refused by the database as bad data).
    pub malformed: AtomicU64,
    /// Status messages stored.
    pub statuses: AtomicU64,
    /// Transactions committed.
    pub batches: AtomicU64,
    /// Failed database attempts (retried).
    pub db_retries: AtomicU64,
}

/// `tagdeflect archive`: runs until SIGTERM/SIGINT, then commits what it holds and exits.
pub fn run(opts: ArchiveOptions) -> Result<(), ArchiveError> {
    if let Some(ArchiveCommand::Backfill(b)) = &opts.command {
        return backfill::run(b);
    }
    check_options(&opts)?;
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().map_err(ArchiveError::Runtime)?;
    rt.block_on(async move {
        let (stop_tx, stop_rx) = watch::channel(false);
        tokio::spawn(async move {
            let mut term = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()).expect("SIGTERM handler");
            tokio::select! {
                _ = tokio::signal::ctrl_c() => tracing::info!("SIGINT: stopping"),
                _ = term.recv() => tracing::info!("SIGTERM: stopping"),
            }
            let _ = stop_tx.send(true);
        });
        let stats = Arc::new(ArchiveStats::default());
        run_until(opts, stats, stop_rx).await
    })
}

/// The archive on the current runtime until `stop` turns true.
pub(crate) async fn run_until(opts: ArchiveOptions, stats: Arc<ArchiveStats>, mut stop: watch::Receiver<bool>) -> Result<(), ArchiveError> {
    let (layout, mqtt, postgres) = check_options(&opts)?;
    let client_id = opts.client_id.clone().unwrap_or_else(|| format!("tagdeflect-archive-{}", tagdeflect_wire::hostname()));
    let tls = match &opts.ca_file {
        Some(ca) => Some(archive_tls(&mqtt, ca)?),
        None => None,
    };
    let mut mo = tagdeflect_wire::mqtt_options(&mqtt, &client_id, None, None, tls).map_err(|m| ArchiveError::BadOption(m.to_string()))?;
    // Read any message off the connection, however big; a too big one is skipped as malformed.
    mo.set_max_packet_size(MAX_PACKET_BYTES, 1 << 20);
    mo.set_clean_session(false);
    mo.set_manual_acks(true);
    mo.set_keep_alive(Duration::from_secs(15));
    let (client, eventloop) = AsyncClient::new(mo, 4 * opts.batch.max(64));
    let subs: Vec<String> = [Kind::Feed, Kind::Status, Kind::LabTest]
        .iter()
        .map(|k| match &opts.group {
            Some(g) => format!("$share/{g}/{}", layout.filter(*k)),
            None => layout.filter(*k),
        })
        .collect();
    tracing::info!(client_id = %client_id, subscriptions = ?subs, "archive: {mqtt} -> PostgreSQL");

    // Unbounded on purpose: the connection task must never wait for room. It did, under a
    // burst (4 rigs x 3000 lines at full speed, `archive-bench`): the connection waited for the
    // write loop to take a batch, the write loop for the connection to take its
    // acknowledgements, and the broker dropped the silent connection (keep-alive) with
    // thousands of lines unacknowledged. What waits here is bounded by the broker: with manual
    // acknowledgements it sends at most `max_inflight_messages` unacknowledged messages (see
    // docs/archive.md, "Broker settings").
    let (tx, rx) = mpsc::unbounded_channel::<Publish>();
    let reconnected = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let mqtt_task = tokio::spawn(drive_mqtt(eventloop, client.clone(), subs, tx, reconnected.clone()));

    // The database: retried until it answers (a service may start before it).
    let shared = opts.group.is_some();
    let mut db = match connect_db(&postgres, shared, &stats, &mut stop).await {
        Some(db) => db,
        None => {
            mqtt_task.abort();
            return Ok(());
        }
    };
    tracing::info!("archive: database ready (schema version {})", db::MIGRATIONS.last().map_or(0, |m| m.0));
    let ctx = WriteCtx { postgres: postgres.clone(), shared, batch: opts.batch, layout, reconnected };
    write_loop(&ctx, &client, rx, &mut db, &stats, &mut stop).await;
    let _ = client.try_disconnect();
    tokio::time::sleep(Duration::from_millis(100)).await;
    mqtt_task.abort();
    tracing::info!(
        inserted = stats.inserted.load(Ordering::Relaxed),
        duplicates = stats.duplicates.load(Ordering::Relaxed),
        malformed = stats.malformed.load(Ordering::Relaxed),
        "archive: stopped"
    );
    Ok(())
}

fn archive_tls(url: &str, ca: &std::path::Path) -> Result<Arc<rustls::ClientConfig>, ArchiveError> {
    if !tagdeflect_wire::BrokerUrl::parse(url).map_err(|m| ArchiveError::BadOption(m.to_string()))?.tls {
        return Err(ArchiveError::BadOption(format!("--ca-file is for mqtts:// brokers; {url} is not one")));
    }
    tagdeflect_wire::tls_config_for(Some(ca), None, None).map_err(|m| ArchiveError::BadOption(format!("--ca-file: {m}")))
}

/// Resolves when `stop` is (or becomes) true.
pub(crate) async fn stopped(stop: &mut watch::Receiver<bool>) {
    loop {
        if *stop.borrow_and_update() {
            return;
        }
        if stop.changed().await.is_err() {
            std::future::pending::<()>().await;
        }
    }
}

/// The retry delays of the broker and the database connections and of a commit: 0.2 s
/// doubling to 2 s.
pub(crate) fn retry_backoff() -> Backoff {
    Backoff::new(Duration::from_millis(200), Duration::from_secs(2))
}

pub(crate) async fn connect_db(url: &str, shared: bool, stats: &ArchiveStats, stop: &mut watch::Receiver<bool>) -> Option<Db> {
    let mut backoff = retry_backoff();
    let mut last = String::new();
    loop {
        match Db::connect(url, shared).await {
            Ok(db) => return Some(db),
            Err(e) => {
                stats.db_retries.fetch_add(1, Ordering::Relaxed);
                let msg = chain(&e);
                if msg != last {
                    tracing::warn!("archive: database unreachable ({msg}); retrying");
                    last = msg;
                }
            }
        }
        tokio::select! {
            _ = tokio::time::sleep(backoff.next_delay()) => {}
            _ = stopped(stop) => return None,
        }
    }
}

/// Drives the MQTT connection; subscribes on every connection (idempotent).
async fn drive_mqtt(
    mut eventloop: EventLoop,
    client: AsyncClient,
    subs: Vec<String>,
    tx: mpsc::UnboundedSender<Publish>,
    reconnected: Arc<std::sync::atomic::AtomicBool>,
) {
    let mut backoff = retry_backoff();
    let mut last_error = String::new();
    loop {
        match eventloop.poll().await {
            Ok(Event::Incoming(Packet::ConnAck(c))) => {
                backoff.reset();
                last_error.clear();
                tracing::info!(session_present = c.session_present, "archive: connected to the broker");
                // A broker restarted without persistence lost the retained acknowledgements.
                reconnected.store(true, Ordering::Relaxed);
                // Subscribe on every connection: a broker restored from its persistence
                // may present the session without its shared subscriptions (Mosquitto 2.0).
                {
                    for s in &subs {
                        if let Err(e) = client.try_subscribe(s.clone(), QoS::AtLeastOnce) {
                            tracing::error!("archive: cannot subscribe to {s}: {e}");
                        }
                    }
                }
            }
            Ok(Event::Incoming(Packet::SubAck(s))) => {
                if s.return_codes.iter().any(|c| matches!(c, rumqttc::SubscribeReasonCode::Failure)) {
                    tracing::error!("archive: the broker refused a subscription ({:?})", s.return_codes);
                } else {
                    tracing::info!(pkid = s.pkid, "archive: subscribed");
                }
            }
            Ok(Event::Incoming(Packet::Publish(p))) => {
                if tx.send(p).is_err() {
                    return;
                }
            }
            Ok(_) => {}
            Err(e) => {
                let msg = e.to_string();
                if msg != last_error {
                    tracing::warn!("archive: broker unreachable ({msg}); retrying");
                    last_error = msg;
                }
                tokio::time::sleep(backoff.next_delay()).await;
            }
        }
    }
}
