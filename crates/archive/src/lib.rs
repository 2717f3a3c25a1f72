//! `tagdeflect archive --mqtt URL --postgres URL` (SPEC "Archive"): subscribes to the
//! feeds that rigs publish (`[output.mqtt]`) and keeps every line in PostgreSQL.
//!
//! ```text
//! broker ──<topic>/feed──▶ MQTT task ──▶ writer: batch ─▶ one transaction ─▶ PUBACKs
//! ```
//!
//! - **At least once, never twice.** The session is persistent (`clean_session = false`,
//!   a fixed client id) and acknowledgements are manual: a message is acknowledged only
//!   after the transaction holding it has committed. Whatever was received but not
//!   committed when the archive, the broker or the database went away is redelivered by
//!   the broker; rows are upserted on (rig, test, seq), so a redelivery never makes a
//!   duplicate.
//! - **Batches** form by themselves: while one transaction commits, the next messages
//!   queue up and go into the next one (up to `--batch` lines).
//! - **Several archives** can share the load (`--group NAME`): they subscribe to the same
//!   MQTT shared subscription `$share/<group>/...` (each with its own `--client-id`), so
//!   the broker hands each message to one of them. One archive alone uses a plain
//!   persistent subscription: Mosquitto 2.0 restores those after its own restart, not
//!   shared ones (lines published between the broker's restart and the archives'
//!   reconnection would be lost to a shared group).
//! - **Bad messages** (not JSON, not a feed line, a topic that does not fit the template)
//!   are logged, acknowledged and skipped; the database refusing a row as bad data skips
//!   that row only.
//! - **Outages**: the MQTT connection and the database connection are retried with a
//!   backoff (0.2 s doubling to 2 s); while the database is away nothing is acknowledged
//!   and the broker holds the backlog.
//!
//! Errors are [`ArchiveError`]s, which tell bad input from runtime failures.

pub mod backfill;
pub mod bench;
mod db;
mod error;
pub mod local;

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use rumqttc::{AsyncClient, Event, EventLoop, Packet, Publish, QoS};
use tokio::sync::{mpsc, watch};

use db::{Db, LabTestRow, LineRow, StatusRow};
pub use error::ArchiveError;
use tagdeflect_core::backoff::Backoff;
use tagdeflect_core::feed::FeedLine;

/// Options of `tagdeflect archive`.
#[derive(Debug, Clone)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
#[cfg_attr(feature = "clap", command(subcommand_negates_reqs = true, args_conflicts_with_subcommands = true))]
pub struct ArchiveOptions {
    /// `backfill`: load a feed file into the archive instead of running it.
    #[cfg_attr(feature = "clap", command(subcommand))]
    pub command: Option<ArchiveCommand>,
    /// The broker: mqtt://[user[:password]@]host[:port] or mqtts://... (TLS).
    #[cfg_attr(feature = "clap", arg(long, required = true))]
    pub mqtt: Option<String>,
    /// The database: a libpq URL or key=value string, e.g. postgresql://user@host:5432/db.
    #[cfg_attr(feature = "clap", arg(long, required = true))]
    pub postgres: Option<String>,
    /// The rigs' topic template (as in `[output.mqtt] topic`).
    #[cfg_attr(feature = "clap", arg(long, default_value = "tagdeflect/{rig}/{test}"))]
    pub topic: String,
    /// Share the load with other archives: subscribe through the MQTT shared subscription
    /// `$share/<GROUP>/...`, so the broker hands each message to one archive of the group.
    /// Without it, a plain persistent subscription (what one archive needs; Mosquitto 2.0
    /// does not restore shared subscriptions after its own restart, plain ones it does).
    #[cfg_attr(feature = "clap", arg(long))]
    pub group: Option<String>,
    /// The MQTT client id; keep it fixed across restarts (the broker keeps the session),
    /// and different for each archive (default: tagdeflect-archive-<host>).
    #[cfg_attr(feature = "clap", arg(long))]
    pub client_id: Option<String>,
    /// TLS: PEM file of the CA certificates of the broker (mqtts://).
    #[cfg_attr(feature = "clap", arg(long))]
    pub ca_file: Option<std::path::PathBuf>,
    /// Feed lines per transaction at most.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 1000))]
    pub batch: usize,
}

/// What `tagdeflect archive` does instead of running.
#[derive(Debug, Clone)]
#[cfg_attr(feature = "clap", derive(clap::Subcommand))]
pub enum ArchiveCommand {
    /// Load a rig's feed file (or a test folder holding `feed.jsonl`) into the archive,
    /// idempotently: lines already held are left as they are (rigs that were away from the
    /// broker for longer than their buffer).
    Backfill(backfill::BackfillOptions),
}

/// The largest message the archive takes (a feed line of a big rig is a few kB); a bigger
/// one is malformed: acknowledged, logged, counted, skipped.
pub const MAX_MESSAGE_BYTES: usize = 1 << 20;

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

/// Which message a topic carries.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    /// `<topic>/feed`: a feed line.
    Feed,
    /// `<topic>/status`: the rig's status.
    Status,
    /// `<topic>/labtest/<id>`: a lab test's record (its id is the last level).
    LabTest,
}

/// The topic template of the rigs, to subscribe and to read rig and test from a topic.
#[derive(Debug, Clone)]
pub struct TopicLayout {
    levels: Vec<String>,
    rig: usize,
    test: usize,
}

impl TopicLayout {
    /// Parses a template such as `tagdeflect/{rig}/{test}`.
    pub fn new(template: &str) -> Result<TopicLayout, String> {
        tagdeflect_sinks::mqtt::check_topic_template(template)?;
        let levels: Vec<String> = template.split('/').map(str::to_string).collect();
        let rig = levels.iter().position(|l| l == "{rig}").expect("checked");
        let test = levels.iter().position(|l| l == "{test}").expect("checked");
        Ok(TopicLayout { levels, rig, test })
    }

    /// The subscription filter of one kind of message (placeholders become `+`).
    pub fn filter(&self, kind: Kind) -> String {
        let mut f: Vec<&str> = self.levels.iter().map(|l| if l == "{rig}" || l == "{test}" { "+" } else { l.as_str() }).collect();
        match kind {
            Kind::Feed => f.push("feed"),
            Kind::Status => f.push("status"),
            Kind::LabTest => f.extend([tagdeflect_sinks::mqtt::LABTEST_SUFFIX, "+"]),
        }
        f.join("/")
    }

    /// The base topic of a rig and test (the template filled in).
    pub fn topic_of(&self, rig: &str, test: &str) -> String {
        let v: Vec<&str> = self
            .levels
            .iter()
            .enumerate()
            .map(|(i, l)| {
                if i == self.rig {
                    rig
                } else if i == self.test {
                    test
                } else {
                    l.as_str()
                }
            })
            .collect();
        v.join("/")
    }

    /// Rig and test of the template's levels of `parts`, or `None` when they do not fit.
    fn base(&self, parts: &[&str]) -> Option<(String, String)> {
        for (i, l) in self.levels.iter().enumerate() {
            if i != self.rig && i != self.test && parts.get(i) != Some(&l.as_str()) {
                return None;
            }
        }
        let (rig, test) = (*parts.get(self.rig)?, *parts.get(self.test)?);
        if rig.is_empty() || test.is_empty() {
            return None;
        }
        Some((rig.to_string(), test.to_string()))
    }

    /// Rig, test and kind of a topic, or `None` when it does not fit the template (a lab
    /// test's topic: [`TopicLayout::parse_lab`]).
    pub fn parse(&self, topic: &str) -> Option<(String, String, Kind)> {
        let parts: Vec<&str> = topic.split('/').collect();
        if parts.len() != self.levels.len() + 1 {
            return None;
        }
        let kind = match parts[self.levels.len()] {
            "feed" => Kind::Feed,
            "status" => Kind::Status,
            _ => return None,
        };
        let (rig, test) = self.base(&parts)?;
        Some((rig, test, kind))
    }

    /// Rig, run (the topic's test) and lab test id of a `<topic>/labtest/<id>` topic.
    pub fn parse_lab(&self, topic: &str) -> Option<(String, String, String)> {
        let parts: Vec<&str> = topic.split('/').collect();
        let n = self.levels.len();
        if parts.len() != n + 2 || parts[n] != tagdeflect_sinks::mqtt::LABTEST_SUFFIX || parts[n + 1].is_empty() {
            return None;
        }
        let (rig, run) = self.base(&parts)?;
        Some((rig, run, parts[n + 1].to_string()))
    }
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

/// Checks the options before anything connects (bad input: exit 2).
fn check_options(opts: &ArchiveOptions) -> Result<(TopicLayout, String, String), ArchiveError> {
    let mqtt = opts.mqtt.clone().ok_or_else(|| ArchiveError::BadOption("--mqtt URL is needed".into()))?;
    let postgres = opts.postgres.clone().ok_or_else(|| ArchiveError::BadOption("--postgres URL is needed".into()))?;
    tagdeflect_sinks::mqtt::BrokerUrl::parse(&mqtt).map_err(|m| ArchiveError::BadOption(format!("--mqtt: {m}")))?;
    let _: tokio_postgres::Config = postgres.parse().map_err(|e| ArchiveError::BadOption(format!("--postgres \"{postgres}\": {e}")))?;
    let layout = TopicLayout::new(&opts.topic).map_err(|m| ArchiveError::BadOption(format!("--topic: {m}")))?;
    if let Some(g) = &opts.group {
        tagdeflect_sinks::mqtt::check_level_name("--group", g).map_err(ArchiveError::BadOption)?;
    }
    if opts.batch == 0 {
        return Err(ArchiveError::BadOption("--batch must be at least 1".into()));
    }
    Ok((layout, mqtt, postgres))
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
    let client_id = opts.client_id.clone().unwrap_or_else(|| format!("tagdeflect-archive-{}", tagdeflect_sinks::mqtt::hostname()));
    let tls = match &opts.ca_file {
        Some(ca) => Some(archive_tls(&mqtt, ca)?),
        None => None,
    };
    let mut mo = tagdeflect_sinks::mqtt::mqtt_options(&mqtt, &client_id, None, None, tls).map_err(ArchiveError::BadOption)?;
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
    if !tagdeflect_sinks::mqtt::BrokerUrl::parse(url).map_err(ArchiveError::BadOption)?.tls {
        return Err(ArchiveError::BadOption(format!("--ca-file is for mqtts:// brokers; {url} is not one")));
    }
    tagdeflect_sinks::mqtt::tls_config_for(Some(ca), None, None).map_err(|m| ArchiveError::BadOption(format!("--ca-file: {m}")))
}

/// Resolves when `stop` is (or becomes) true.
async fn stopped(stop: &mut watch::Receiver<bool>) {
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
fn retry_backoff() -> Backoff {
    Backoff::new(Duration::from_millis(200), Duration::from_secs(2))
}

async fn connect_db(url: &str, shared: bool, stats: &ArchiveStats, stop: &mut watch::Receiver<bool>) -> Option<Db> {
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

/// What one message turned out to be.
enum Parsed {
    Line(LineRow),
    Status(StatusRow),
    LabTest(Box<LabTestRow>),
    Skip,
}

/// Checks one message as the archive would take it: `Ok` when it would be stored, else
/// why it is malformed (what the fuzz target drives).
pub fn check_message(layout: &TopicLayout, topic: &str, payload: &[u8]) -> Result<(), String> {
    parse_message(layout, topic, payload).map(|_| ())
}

fn parse_message(layout: &TopicLayout, topic: &str, payload: &[u8]) -> Result<Parsed, String> {
    if let Some((rig, run, id)) = layout.parse_lab(topic) {
        let m = tagdeflect_sinks::mqtt::LabTestMessage::parse(payload, &rig, &run, &id)?;
        return Ok(Parsed::LabTest(Box::new(LabTestRow { rig, run, message: m })));
    }
    let Some((rig, test, kind)) = layout.parse(topic) else {
        return Err(format!("topic {topic} does not fit the template"));
    };
    if payload.len() > MAX_MESSAGE_BYTES {
        return Err(format!("{} bytes, more than the {} a feed line or status may have", payload.len(), MAX_MESSAGE_BYTES));
    }
    let value: serde_json::Value = serde_json::from_slice(payload).map_err(|e| format!("not JSON: {e}"))?;
    match kind {
        Kind::Feed => {
            let line: FeedLine = serde_json::from_value(value.clone()).map_err(|e| format!("not a feed line: {e}"))?;
            let seq = i64::try_from(line.seq).map_err(|_| "seq out of range".to_string())?;
            let mut ids = std::collections::HashSet::new();
            if line.tags.iter().any(|t| !ids.insert(t.id)) {
                return Err("a tag id appears twice".into());
            }
            if let Some(g) = value.get("gauges") {
                let ok = g.as_object().is_some_and(|m| {
                    m.values().all(|v| {
                        v.is_object()
                            && v.get("value").is_none_or(|x| x.is_number() || x.is_null())
                            && v.get("sigma").is_none_or(|x| x.is_number() || x.is_null())
                    })
                });
                if !ok {
                    return Err("`gauges` is not an object of {value, sigma, unit}".into());
                }
            }
            Ok(Parsed::Line(LineRow { rig, test, seq, t_ns: line.t_ns, line: value }))
        }
        Kind::Status => {
            if !value.is_object() {
                return Ok(Parsed::Skip);
            }
            // A status names its rig and test: one that claims another than its topic's is
            // someone else's writing over this rig's (set the broker's ACLs).
            for (key, want) in [("rig", &rig), ("test", &test)] {
                if let Some(v) = value.get(key) {
                    if v.as_str() != Some(want.as_str()) {
                        return Err(format!(
                            "a status for {key} {v} on the topic of {key} \"{want}\" (rejected: it would overwrite that rig's status)"
                        ));
                    }
                }
            }
            Ok(Parsed::Status(StatusRow { rig, test, status: value }))
        }
        // `parse` never says LabTest: a lab test's topic has its id (`parse_lab`, above).
        Kind::LabTest => Err(format!("topic {topic}: a lab test record needs its id as the last level")),
    }
}

/// What the write loop needs besides the connections.
struct WriteCtx {
    postgres: String,
    shared: bool,
    batch: usize,
    layout: TopicLayout,
    reconnected: Arc<std::sync::atomic::AtomicBool>,
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
            let ack = tagdeflect_sinks::mqtt::ArchiveAck {
                rig: a.rig.clone(),
                test: a.test.clone(),
                runs: h.ack_runs(),
                at_ns: tagdeflect_core::clock::now_epoch_ns(),
            };
            let topic = format!("{}/{}", layout.topic_of(&a.rig, &a.test), tagdeflect_sinks::mqtt::ACK_SUFFIX);
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

async fn write_loop(
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
                let n = stats.inserted.load(Ordering::Relaxed);
                if n != last_inserted {
                    tracing::info!(inserted = n, duplicates = stats.duplicates.load(Ordering::Relaxed), malformed = stats.malformed.load(Ordering::Relaxed), "archive: {} feed lines in the last 10 s", n - last_inserted);
                    last_inserted = n;
                }
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
        let mut lines = Vec::with_capacity(batch.len());
        let mut statuses: Vec<StatusRow> = Vec::new();
        let mut labs: Vec<LabTestRow> = Vec::new();
        let mut seen = std::collections::HashSet::new();
        for p in &batch {
            match parse_message(&ctx.layout, &p.topic, &p.payload) {
                Ok(Parsed::Line(l)) => {
                    if seen.insert((l.rig.clone(), l.test.clone(), l.seq, l.t_ns)) {
                        lines.push(l);
                    } else {
                        stats.duplicates.fetch_add(1, Ordering::Relaxed);
                    }
                }
                Ok(Parsed::Status(s)) => {
                    statuses.retain(|x| !(x.rig == s.rig && x.test == s.test));
                    statuses.push(s);
                }
                Ok(Parsed::LabTest(l)) => labs.push(*l),
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
        // Commit, retrying through database outages; nothing is acknowledged before.
        let mut backoff = retry_backoff();
        let mut logged = false;
        loop {
            if db.is_closed() {
                match connect_db(&ctx.postgres, ctx.shared, stats, stop).await {
                    Some(d) => {
                        *db = d;
                        tracing::info!("archive: database back");
                    }
                    None => return, // stopping: the batch stays unacknowledged
                }
            }
            match db.write_or_skip(&lines, &statuses, &labs).await {
                Ok(w) => {
                    stats.inserted.fetch_add(w.inserted, Ordering::Relaxed);
                    stats.duplicates.fetch_add(w.duplicates, Ordering::Relaxed);
                    stats.malformed.fetch_add(w.rejected, Ordering::Relaxed);
                    stats.statuses.fetch_add(statuses.len() as u64, Ordering::Relaxed);
                    stats.batches.fetch_add(1, Ordering::Relaxed);
                    acks.touch(&w.touched);
                    break;
                }
                Err(e) => {
                    stats.db_retries.fetch_add(1, Ordering::Relaxed);
                    if !logged {
                        tracing::warn!("archive: cannot commit {} feed lines ({}); retrying, nothing acknowledged", lines.len(), chain(&e));
                        logged = true;
                    }
                    tokio::select! {
                        _ = tokio::time::sleep(backoff.next_delay()) => {}
                        _ = stopped(stop) => return,
                    }
                    if !db.is_closed() {
                        // A failed transaction on a live connection: start afresh.
                        if let Some(d) = connect_db(&ctx.postgres, ctx.shared, stats, stop).await {
                            *db = d;
                        } else {
                            return;
                        }
                    }
                }
            }
        }
        if logged {
            tracing::info!("archive: committed after the database came back");
        }
        for p in &batch {
            if client.ack(p).await.is_err() {
                break; // the MQTT task ended; unacknowledged messages will be redelivered
            }
        }
        acks.publish(&ctx.layout, client, db);
    }
}

/// The fuzz target `archive_message` (`fuzz/`, `scripts/fuzz.sh`): arbitrary bytes as a
/// message on a feed, status or acknowledgement topic. The archive's check of a message
/// and the rig's reading of an acknowledgement must return without a panic; what an
/// acknowledgement claims is always inside `0..=high`; runs given the lines of a message
/// keep every seq they were given.
pub fn fuzz_message(data: &[u8]) {
    let layout = TopicLayout::new("tagdeflect/{rig}/{test}").expect("a valid template");
    let (sel, payload) = data.split_first().unwrap_or((&0, &[]));
    let topic = match sel % 5 {
        0 => "tagdeflect/r/t/feed",
        1 => "tagdeflect/r/t/status",
        2 => "tagdeflect/r/t/archive",
        3 => "tagdeflect/r/t/labtest/20261202T101500Z-B12",
        _ => "tagdeflect/r/t/x/feed",
    };
    let _ = check_message(&layout, topic, payload);
    if let Ok(ack) = serde_json::from_slice::<tagdeflect_sinks::mqtt::ArchiveAck>(payload) {
        for r in ack.runs.iter().take(4) {
            if r.high < 1 << 20 && r.gaps.len() <= 64 {
                let held = r.held();
                assert!(held.bounds().is_none_or(|(_, hi)| hi <= r.high));
            }
        }
        let _ = ack.run_of(i64::MIN);
    }
    // Runs from (seq, t_ns) pairs read off the bytes.
    let mut h = db::Holdings::default();
    let mut given = Vec::new();
    for c in payload.chunks_exact(3).take(256) {
        let seq = u64::from(c[0]) % 64;
        let t = i64::from(c[1]) * 256 + i64::from(c[2]);
        let (run, _) = h.assign(seq, t);
        given.push((run, seq));
    }
    for (run, seq) in given {
        assert!(h.run(run).is_some_and(|r| r.held.contains(seq)), "run {run} lost seq {seq}");
    }
}
