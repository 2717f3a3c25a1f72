//! The publisher: the buffer of feed lines, the task that drives the connection and pumps
//! the buffer into it, and the publisher as a sink (see the module doc of [`super`]).

use std::collections::{BTreeMap, HashMap, VecDeque};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use rumqttc::{AsyncClient, Event, EventLoop, LastWill, Outgoing, Packet, QoS};
use serde::Serialize;

use super::ack::{ArchiveAck, RunHeld, SeqRanges, ACK_SUFFIX};
use super::client::{mqtt_options, topic_for, BrokerUrl};
use super::MqttConfig;
use crate::RigInfo;
use tagdeflect_core::backoff::Backoff;
use tagdeflect_core::feed::FeedLine;

fn qos_of(q: u8) -> QoS {
    match q {
        0 => QoS::AtMostOnce,
        1 => QoS::AtLeastOnce,
        _ => QoS::ExactlyOnce,
    }
}

/// A new test id: the UTC start time and four random hex digits.
fn new_test_id() -> String {
    format!("{}-{:04x}", chrono::Utc::now().format("%Y%m%dT%H%M%SZ"), rand::random::<u16>())
}

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

/// What a retained status message says.
#[derive(Debug, Clone, Serialize)]
struct Status {
    state: &'static str,
    rig: String,
    test: String,
    version: &'static str,
    started_ns: i64,
    cameras: Vec<CameraStatus>,
    #[serde(skip_serializing_if = "Option::is_none")]
    utm: Option<UtmStatus>,
    recording: Option<String>,
    last_seq: Option<u64>,
    last_t_ns: Option<i64>,
    mqtt_dropped: u64,
    /// Lines of this run the archive does not hold yet, as it last said.
    #[serde(skip_serializing_if = "Option::is_none")]
    archive_lag: Option<u64>,
}

#[derive(Debug, Clone, Serialize)]
struct CameraStatus {
    name: String,
    source: String,
    /// Contributed a frame to the last frame set.
    #[serde(skip_serializing_if = "Option::is_none")]
    frame: Option<bool>,
}

#[derive(Debug, Clone, Serialize)]
struct UtmStatus {
    address: String,
    #[serde(skip_serializing_if = "Option::is_none")]
    state: Option<String>,
}

/// Who an outgoing publish belongs to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Sent {
    Line(u64),
    Status,
    /// A lab test's record, by the serial number of that publish.
    Lab(u64),
}

/// A lab test's record to keep on the broker (see [`super::labtest`]).
#[derive(Debug)]
struct LabOut {
    id: String,
    payload: Vec<u8>,
    /// The serial number of its latest publish.
    serial: u64,
    /// The broker acknowledged its latest version.
    delivered: bool,
}

/// Lab test records kept to send again on every connection (the newest; a day has a dozen).
const LAB_RECORDS: usize = 64;

/// A line acknowledged by the broker is sent again only if the archive still lacks it this
/// long after (the archive's view may be a moment older than the broker's acknowledgement).
const RESEND_AFTER: Duration = Duration::from_secs(1);
/// At the end of a run, the lines the archive has not confirmed (those past its high
/// water: a broker that lost them leaves no later line to show the gap) are sent again
/// after this long without progress.
const TAIL_RESEND_AFTER: Duration = Duration::from_secs(2);

struct State {
    connected: bool,
    stopping: bool,
    /// The newest unconfirmed lines, by seq (at most `cap`).
    mem: BTreeMap<u64, Vec<u8>>,
    /// Older lines read back from the feed file to be sent.
    loaded: BTreeMap<u64, Vec<u8>>,
    /// Seqs to send: never sent, or sent again because the archive lacks them.
    todo: SeqRanges,
    /// Seqs the broker acknowledged that the archive has not confirmed.
    delivered: SeqRanges,
    /// Seqs acknowledged by the broker within [`RESEND_AFTER`], with when.
    recent: VecDeque<(u64, Instant)>,
    /// Publishes handed to the client, in order, awaiting their packet id.
    order: VecDeque<Sent>,
    /// Packet id → publish awaiting its acknowledgement.
    pkids: HashMap<u16, Sent>,
    /// A publish parked by the client on a packet-id collision.
    collided: Option<(u16, Sent)>,
    status: Status,
    /// Lines the archive will never get from this rig (left memory unsent, not in a feed file).
    dropped: u64,
    /// Lines handed over in this run.
    made: u64,
    /// `t_ns` of this run's first line (tells this run from earlier ones of the same test id).
    first_t_ns: Option<i64>,
    /// What the archive last said it holds of this run.
    archive: Option<RunHeld>,
    /// When the archive's confirmations last advanced.
    archive_progress: Option<Instant>,
    /// The feed file loader wants to run.
    want_load: bool,
    /// The lab tests' records, oldest first.
    lab: Vec<LabOut>,
    /// Serial number of the last lab record publish.
    lab_serial: u64,
}

impl State {
    fn in_flight(&self) -> usize {
        self.order.len() + self.pkids.len() + usize::from(self.collided.is_some())
    }

    /// Lines not confirmed by the archive (to send, in flight or delivered).
    fn unconfirmed(&self) -> u64 {
        let flying = self.order.iter().chain(self.pkids.values()).chain(self.collided.iter().map(|c| &c.1));
        self.todo.len() + self.delivered.len() + flying.filter(|w| matches!(w, Sent::Line(_))).count() as u64
    }

    /// Lines not acknowledged by the broker (to send or in flight).
    fn undelivered(&self) -> u64 {
        let flying = self.order.iter().chain(self.pkids.values()).chain(self.collided.iter().map(|c| &c.1));
        self.todo.len() + flying.filter(|w| matches!(w, Sent::Line(_))).count() as u64
    }
}

/// Lines read back from the feed file (seq, bytes), and the largest seq the file holds so far.
type ReadBack = (Vec<(u64, Vec<u8>)>, Option<u64>);

/// This run's lines in the feed file (`[output] feed`): read back for lines that left the
/// memory buffer before the archive confirmed them.
struct FeedSource {
    path: PathBuf,
    /// Where this run's lines start (the file's length when the run started: the feed file
    /// is appended to, earlier runs' lines come before).
    start: u64,
    /// Where the last read stopped, and the seq of the last line read before it.
    pos: u64,
    last_seq: Option<u64>,
}

impl FeedSource {
    /// Reads the lines of `wanted` (ascending) from the file; also says the largest seq the
    /// file holds so far (a wanted seq below it that was not found is not in the file).
    fn read(&mut self, wanted: &[u64]) -> std::io::Result<ReadBack> {
        use std::io::{BufRead, Seek, SeekFrom};
        #[derive(serde::Deserialize)]
        struct SeqOnly {
            seq: u64,
        }
        let Some(&first) = wanted.first() else { return Ok((Vec::new(), self.last_seq)) };
        let last_wanted = *wanted.last().expect("non-empty");
        if self.last_seq.is_none_or(|l| first <= l) {
            self.pos = self.start;
            self.last_seq = None;
        }
        let mut f = std::io::BufReader::new(std::fs::File::open(&self.path)?);
        f.seek(SeekFrom::Start(self.pos))?;
        let want: std::collections::HashSet<u64> = wanted.iter().copied().collect();
        let mut out = Vec::new();
        let mut buf = Vec::new();
        let mut max_seen = self.last_seq;
        loop {
            buf.clear();
            let n = f.read_until(b'\n', &mut buf)?;
            if n == 0 || buf.last() != Some(&b'\n') {
                break; // the end, or a line still being written
            }
            let line = &buf[..buf.len() - 1];
            let Ok(SeqOnly { seq }) = serde_json::from_slice::<SeqOnly>(line) else {
                self.pos += n as u64;
                continue;
            };
            max_seen = Some(max_seen.map_or(seq, |m| m.max(seq)));
            if want.contains(&seq) {
                out.push((seq, line.to_vec()));
            }
            self.pos += n as u64;
            self.last_seq = Some(seq);
            if seq >= last_wanted {
                break;
            }
        }
        Ok((out, max_seen))
    }
}

struct Shared {
    state: Mutex<State>,
    stats: Arc<MqttStats>,
    client: AsyncClient,
    feed_topic: String,
    status_topic: String,
    ack_topic: String,
    /// `<topic>`, for `<topic>/labtest/<id>`.
    base_topic: String,
    rig: String,
    qos: QoS,
    window: usize,
    cap: usize,
    feed: Option<Mutex<FeedSource>>,
    load: tokio::sync::Notify,
}

/// The MQTT sink of a live run. Cheap to share (`Arc`); [`publish`](Self::publish) never blocks.
pub struct MqttPublisher {
    shared: Arc<Shared>,
    tasks: Mutex<Vec<tokio::task::JoinHandle<()>>>,
    done: Arc<AtomicBool>,
    test: String,
}

impl MqttPublisher {
    /// Starts the publisher on the current tokio runtime: the connection is made in the
    /// background (the run does not wait for the broker). `feed` is this run's feed file
    /// (`[output] feed`), already open for appending: lines beyond the memory buffer are
    /// read back from it. Fails only on a configuration the broker client rejects.
    pub fn start(cfg: &MqttConfig, config: &RigInfo, recording: Option<&Path>, feed: Option<&Path>) -> Result<MqttPublisher, String> {
        let test = cfg.test.clone().unwrap_or_else(new_test_id);
        let base = topic_for(&cfg.topic, &cfg.rig, &test);
        let client_id = cfg.client_id.clone().unwrap_or_else(|| format!("tagdeflect-{}", cfg.rig));
        let tls = if BrokerUrl::parse(&cfg.url)?.tls { Some(cfg.tls_config()?) } else { None };
        let mut opts = mqtt_options(&cfg.url, &client_id, cfg.username.as_deref(), cfg.password.as_deref(), tls)?;
        // The buffer retransmits itself: a clean session means the client never resends
        // anything of its own after a reconnect.
        opts.set_clean_session(true);
        opts.set_keep_alive(Duration::from_secs(cfg.keep_alive_s));
        let window: usize = 100;
        opts.set_inflight(window as u16);
        let started_ns = tagdeflect_core::clock::now_epoch_ns();
        let status = Status {
            state: "online",
            rig: cfg.rig.clone(),
            test: test.clone(),
            version: env!("CARGO_PKG_VERSION"),
            started_ns,
            cameras: config
                .cameras
                .iter()
                .map(|c| CameraStatus { name: c.name.clone(), source: c.source.to_string(), frame: None })
                .collect(),
            utm: config.utm.as_ref().map(|a| UtmStatus { address: a.to_string(), state: None }),
            recording: recording.map(|p| p.display().to_string()),
            last_seq: None,
            last_t_ns: None,
            mqtt_dropped: 0,
            archive_lag: None,
        };
        let status_topic = format!("{base}/status");
        let mut offline = status.clone();
        offline.state = "offline";
        opts.set_last_will(LastWill::new(&status_topic, serde_json::to_vec(&offline).expect("status serialises"), QoS::AtLeastOnce, true));
        let (client, eventloop) = AsyncClient::new(opts, window + 16);
        let feed = feed.map(|p| {
            let start = std::fs::metadata(p).map_or(0, |m| m.len());
            Mutex::new(FeedSource { path: p.to_path_buf(), start, pos: start, last_seq: None })
        });
        let shared = Arc::new(Shared {
            state: Mutex::new(State {
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
            }),
            stats: Arc::new(MqttStats::default()),
            client,
            feed_topic: format!("{base}/feed"),
            status_topic,
            ack_topic: format!("{base}/{ACK_SUFFIX}"),
            base_topic: base.clone(),
            rig: cfg.rig.clone(),
            qos: qos_of(cfg.qos),
            window,
            cap: cfg.buffer_lines,
            feed,
            load: tokio::sync::Notify::new(),
        });
        let done = Arc::new(AtomicBool::new(false));
        let poller = tokio::spawn(drive(shared.clone(), eventloop, done.clone()));
        let ticker = {
            let shared = shared.clone();
            let every = Duration::from_secs_f64(cfg.status_interval_s);
            tokio::spawn(async move {
                let mut tick = tokio::time::interval(every);
                tick.tick().await;
                loop {
                    tick.tick().await;
                    let mut st = shared.state.lock().expect("mqtt state");
                    if st.connected && !st.stopping {
                        shared.send_status(&mut st);
                    }
                }
            })
        };
        let mut tasks = vec![poller, ticker];
        if shared.feed.is_some() {
            tasks.push(tokio::spawn(load_loop(shared.clone())));
        }
        tracing::info!(rig = %cfg.rig, test = %test, topic = %base, "MQTT: publishing the feed to {} (test id {test})", cfg.url);
        eprintln!("tagdeflect: MQTT test id {test} (topic {base}/feed)");
        Ok(MqttPublisher { shared, tasks: Mutex::new(tasks), done, test })
    }

    /// The test id of this run.
    pub fn test(&self) -> &str {
        &self.test
    }

    /// The publisher's counters (for `/metrics`).
    pub fn stats(&self) -> Arc<MqttStats> {
        self.shared.stats.clone()
    }

    /// Makes room in the memory buffer for the next line and returns the lines the archive
    /// will never get so far: the `mqtt_dropped` of the line about to be
    /// [published](Self::publish). The oldest line held leaves memory; with a feed file it
    /// is read back from there when it has to be sent, without one it is lost if the broker
    /// never acknowledged it (counted). Called by the measurement's status step, so the line
    /// is complete before any sink sees it.
    pub fn reserve(&self) -> u64 {
        let s = &self.shared;
        let mut st = s.state.lock().expect("mqtt state");
        while st.mem.len() >= s.cap {
            let Some((seq, _)) = st.mem.pop_first() else { break };
            if s.feed.is_none() {
                s.forget(&mut st, seq);
            }
        }
        st.dropped
    }

    /// Hands a feed line over for publishing, never waiting on the network: keeps the line
    /// as serialised until the archive confirms it (its `mqtt_dropped` came from
    /// [`Self::reserve`]).
    pub fn publish(&self, line: &FeedLine) {
        let s = &self.shared;
        let mut st = s.state.lock().expect("mqtt state");
        let bytes = line.to_json().into_bytes();
        st.first_t_ns.get_or_insert(line.t_ns);
        st.mem.insert(line.seq, bytes);
        st.todo.insert(line.seq);
        st.made += 1;
        st.status.last_seq = Some(line.seq);
        st.status.last_t_ns = Some(line.t_ns);
        st.status.mqtt_dropped = st.dropped;
        if let Some(u) = st.status.utm.as_mut() {
            u.state = line.utm.clone();
        }
        for c in &line.cameras {
            if let Some(cs) = st.status.cameras.iter_mut().find(|x| x.name == c.name) {
                cs.frame = Some(c.frame);
            }
        }
        s.pump(&mut st);
    }

    /// Publishes a lab test's record, retained, on `<topic>/labtest/<id>` (now if connected,
    /// else on connecting; again on every connection); never blocks.
    pub fn publish_lab_test(&self, record: &crate::lab_test::TestRecord) {
        let msg = super::labtest::LabTestMessage::from_record(&self.shared.rig, &self.test, record);
        let payload = serde_json::to_vec(&msg).expect("a lab test record serialises");
        if payload.len() > super::labtest::MAX_LABTEST_BYTES {
            tracing::warn!(test = %record.id, bytes = payload.len(), "MQTT: the lab test record is larger than an archive takes; sent anyway");
        }
        let mut st = self.shared.state.lock().expect("mqtt state");
        let i = match st.lab.iter().position(|l| l.id == record.id) {
            Some(i) => i,
            None => {
                st.lab.push(LabOut { id: record.id.clone(), payload: Vec::new(), serial: 0, delivered: false });
                st.lab.len() - 1
            }
        };
        st.lab[i].payload = payload;
        st.lab[i].delivered = false;
        let id = record.id.clone();
        while st.lab.len() > LAB_RECORDS {
            match st.lab.iter().position(|l| l.delivered) {
                Some(j) => {
                    st.lab.remove(j);
                }
                None => break,
            }
        }
        if let Some(i) = st.lab.iter().position(|l| l.id == id) {
            self.shared.send_lab(&mut st, i);
        }
    }

    /// Ends the run: waits up to `timeout` until the archive has confirmed every line (when
    /// an archive has confirmed any line of this run; else until the broker has
    /// acknowledged them), sending again what it lacks; publishes the retained status
    /// `offline`, disconnects and logs what was published, confirmed, dropped and left.
    pub async fn finish(&self, timeout: Duration) {
        let s = &self.shared;
        let until = tokio::time::Instant::now() + timeout;
        loop {
            let left = {
                let mut st = s.state.lock().expect("mqtt state");
                if st.archive.is_some() {
                    // Lines past the archive's high water: a broker that lost them leaves no
                    // later line to show the gap.
                    let stalled = st.archive_progress.is_none_or(|t| t.elapsed() >= TAIL_RESEND_AFTER);
                    if stalled && st.connected && !st.delivered.is_empty() && st.in_flight() == 0 {
                        let again: Vec<(u64, u64)> = st.delivered.iter().collect();
                        for (a, b) in again {
                            st.todo.insert_range(a, b);
                        }
                        st.delivered = SeqRanges::new();
                        st.archive_progress = Some(Instant::now());
                        tracing::info!(lines = st.todo.len(), "MQTT: the archive has not confirmed the last lines; sending them again");
                        s.pump(&mut st);
                    }
                    st.unconfirmed()
                } else {
                    st.undelivered()
                }
            } + {
                let st = s.state.lock().expect("mqtt state");
                st.lab.iter().filter(|l| !l.delivered).count() as u64
            };
            if left == 0 || tokio::time::Instant::now() >= until {
                break;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        let (unconfirmed, undelivered, dropped, connected, confirmed) = {
            let mut st = s.state.lock().expect("mqtt state");
            st.stopping = true;
            st.status.state = "offline";
            if st.connected {
                s.send_status(&mut st);
            }
            let confirmed = st.archive.as_ref().map(|a| a.lines);
            (st.unconfirmed(), st.undelivered(), st.dropped, st.connected, confirmed)
        };
        if connected {
            // Let the status go out (acknowledged), then say goodbye.
            let until = tokio::time::Instant::now() + Duration::from_secs(1);
            while tokio::time::Instant::now() < until {
                let waiting = {
                    let st = s.state.lock().expect("mqtt state");
                    !st.order.is_empty() || st.pkids.values().any(|w| *w == Sent::Status)
                };
                if !waiting {
                    break;
                }
                tokio::time::sleep(Duration::from_millis(10)).await;
            }
            let _ = s.client.try_disconnect();
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        self.done.store(true, Ordering::SeqCst);
        for t in self.tasks.lock().expect("tasks").drain(..) {
            t.abort();
        }
        let published = s.stats.published.load(Ordering::Relaxed);
        match confirmed {
            Some(c) if unconfirmed == 0 => {
                tracing::info!(published, dropped, confirmed = c, "MQTT: the archive confirmed every feed line")
            }
            Some(c) => tracing::warn!(
                published,
                dropped,
                confirmed = c,
                unconfirmed,
                "MQTT: stopped with {unconfirmed} feed lines the archive has not confirmed (load them with `tagdeflect archive backfill`)"
            ),
            None if undelivered > 0 => {
                tracing::warn!(
                    published,
                    dropped,
                    undelivered,
                    "MQTT: stopped with {undelivered} feed lines not acknowledged by the broker"
                )
            }
            None => tracing::info!(published, dropped, "MQTT: all feed lines handed to the broker (no archive confirmed any)"),
        }
    }
}

impl Shared {
    /// Hands lines to the client while connected and the in-flight window allows, oldest
    /// first (lines the archive lacks come before new ones).
    fn pump(&self, st: &mut State) {
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

    fn update_stats(&self, st: &State) {
        self.stats.buffered.store(st.mem.len() as u64, Ordering::Relaxed);
        self.stats.unconfirmed.store(st.unconfirmed(), Ordering::Relaxed);
        if let Some(a) = &st.archive {
            self.stats.archive_high.store(a.high, Ordering::Relaxed);
            self.stats.archive_confirmed.store(a.lines, Ordering::Relaxed);
            self.stats.archive_lag.store(st.made.saturating_sub(a.lines), Ordering::Relaxed);
        }
    }

    /// A line that can no longer be sent: lost for the archive if the broker never had it.
    fn forget(&self, st: &mut State, seq: u64) {
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

    /// Hands the `i`-th lab record to the client when connected.
    fn send_lab(&self, st: &mut State, i: usize) {
        if !st.connected {
            return;
        }
        st.lab_serial += 1;
        let serial = st.lab_serial;
        let l = &mut st.lab[i];
        let topic = format!("{}/{}/{}", self.base_topic, super::labtest::LABTEST_SUFFIX, l.id);
        if self.client.try_publish(topic, QoS::AtLeastOnce, true, l.payload.clone()).is_ok() {
            l.serial = serial;
            st.order.push_back(Sent::Lab(serial));
        }
    }

    fn send_status(&self, st: &mut State) {
        st.status.mqtt_dropped = st.dropped;
        st.status.archive_lag = st.archive.as_ref().map(|a| st.made.saturating_sub(a.lines));
        let payload = serde_json::to_vec(&st.status).expect("status serialises");
        if self.client.try_publish(self.status_topic.clone(), QoS::AtLeastOnce, true, payload).is_ok() {
            st.order.push_back(Sent::Status);
        }
    }

    fn acked(&self, st: &mut State, who: Sent) {
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
    fn archive_acked(&self, st: &mut State, payload: &[u8]) {
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

/// Reads lines the memory no longer holds back from the feed file when [`Shared::pump`]
/// asks, a window at a time, off the lock.
async fn load_loop(shared: Arc<Shared>) {
    loop {
        shared.load.notified().await;
        loop {
            let wanted: Vec<u64> = {
                let mut st = shared.state.lock().expect("mqtt state");
                if !st.want_load {
                    break;
                }
                st.want_load = false;
                let mut w = Vec::new();
                for (a, b) in st.todo.iter() {
                    for seq in a..=b {
                        if !st.mem.contains_key(&seq) && !st.loaded.contains_key(&seq) {
                            w.push(seq);
                        }
                        if w.len() >= shared.window {
                            break;
                        }
                    }
                    if w.len() >= shared.window {
                        break;
                    }
                }
                w
            };
            if wanted.is_empty() {
                break;
            }
            let sh = shared.clone();
            let w = wanted.clone();
            let read =
                tokio::task::spawn_blocking(move || sh.feed.as_ref().expect("a feed file").lock().expect("feed source").read(&w)).await;
            // How long to wait before trying again (nothing found yet, or a read error).
            let retry_in = {
                let mut st = shared.state.lock().expect("mqtt state");
                let retry = match read {
                    Ok(Ok((lines, max_seen))) => {
                        let found: std::collections::HashSet<u64> = lines.iter().map(|l| l.0).collect();
                        for (seq, bytes) in lines {
                            if st.todo.contains(seq) {
                                st.loaded.insert(seq, bytes);
                            }
                        }
                        // Not in the file though the file went past it: the feed file lost it.
                        let mut lost = 0;
                        for seq in wanted.iter().filter(|s| !found.contains(s) && max_seen.is_some_and(|m| m > **s)) {
                            if st.todo.contains(*seq) {
                                shared.forget(&mut st, *seq);
                                lost += 1;
                            }
                        }
                        if lost > 0 {
                            tracing::warn!(lines = lost, "MQTT: feed lines the archive lacks are not in the feed file; counted as dropped");
                        }
                        // Nothing found: not written yet (the feed output is failing?).
                        (found.is_empty() && lost == 0).then_some(Duration::from_millis(500))
                    }
                    Ok(Err(e)) => {
                        tracing::warn!("MQTT: cannot read the feed file back ({e}); retrying");
                        Some(Duration::from_secs(1))
                    }
                    Err(_) => return,
                };
                if retry.is_none() {
                    shared.pump(&mut st);
                }
                retry
            };
            if let Some(d) = retry_in {
                tokio::time::sleep(d).await;
                let mut st = shared.state.lock().expect("mqtt state");
                st.want_load = true;
                shared.pump(&mut st);
            }
        }
    }
}

/// Drives the connection: never cancelled mid-poll, so no packet is half written.
async fn drive(shared: Arc<Shared>, mut eventloop: EventLoop, done: Arc<AtomicBool>) {
    let mut backoff = Backoff::new(Duration::from_millis(200), Duration::from_secs(2));
    let mut connections = 0u64;
    let mut last_error: Option<String> = None;
    while !done.load(Ordering::Relaxed) {
        match eventloop.poll().await {
            Ok(Event::Incoming(Packet::ConnAck(_))) => {
                let mut st = shared.state.lock().expect("mqtt state");
                st.connected = true;
                shared.stats.connected.store(1, Ordering::Relaxed);
                if connections > 0 {
                    shared.stats.reconnects.fetch_add(1, Ordering::Relaxed);
                }
                connections += 1;
                backoff.reset();
                last_error = None;
                tracing::info!(to_send = st.todo.len(), unconfirmed = st.unconfirmed(), "MQTT: connected to the broker");
                // The archive's acknowledgement (retained: the current one arrives at once).
                if let Err(e) = shared.client.try_subscribe(shared.ack_topic.clone(), QoS::AtLeastOnce) {
                    tracing::warn!("MQTT: cannot subscribe to {}: {e}", shared.ack_topic);
                }
                shared.send_status(&mut st);
                // The lab tests' records again: a broker restarted without persistence forgot them.
                for i in 0..st.lab.len() {
                    shared.send_lab(&mut st, i);
                }
                shared.pump(&mut st);
            }
            Ok(Event::Incoming(Packet::Publish(p))) => {
                if p.topic == shared.ack_topic {
                    let mut st = shared.state.lock().expect("mqtt state");
                    shared.archive_acked(&mut st, &p.payload);
                }
            }
            Ok(Event::Outgoing(Outgoing::Publish(pkid))) => {
                let mut st = shared.state.lock().expect("mqtt state");
                let who = match st.collided {
                    Some((p, w)) if p == pkid => {
                        st.collided = None;
                        Some(w)
                    }
                    _ => st.order.pop_front(),
                };
                if let Some(who) = who {
                    let qos0 = match who {
                        Sent::Line(_) => shared.qos == QoS::AtMostOnce,
                        Sent::Status | Sent::Lab(_) => false,
                    };
                    if qos0 || pkid == 0 {
                        shared.acked(&mut st, who);
                        shared.pump(&mut st);
                    } else {
                        st.pkids.insert(pkid, who);
                    }
                }
            }
            Ok(Event::Outgoing(Outgoing::AwaitAck(pkid))) => {
                let mut st = shared.state.lock().expect("mqtt state");
                if let Some(w) = st.order.pop_front() {
                    st.collided = Some((pkid, w));
                }
            }
            // QoS 1 (and the status) end with PUBACK, QoS 2 with PUBCOMP.
            Ok(Event::Incoming(Packet::PubAck(rumqttc::PubAck { pkid, .. })))
            | Ok(Event::Incoming(Packet::PubComp(rumqttc::PubComp { pkid, .. }))) => {
                let mut st = shared.state.lock().expect("mqtt state");
                if let Some(w) = st.pkids.remove(&pkid) {
                    shared.acked(&mut st, w);
                }
                shared.pump(&mut st);
            }
            Ok(_) => {}
            Err(e) => {
                {
                    let mut guard = shared.state.lock().expect("mqtt state");
                    let st = &mut *guard;
                    // Everything the client still holds is forgotten (clean session); the
                    // lines in flight go back to be sent.
                    eventloop.clean();
                    eventloop.pending.clear();
                    eventloop.state.events.clear();
                    st.connected = false;
                    shared.stats.connected.store(0, Ordering::Relaxed);
                    let flying: Vec<Sent> =
                        st.order.drain(..).chain(st.pkids.drain().map(|(_, w)| w)).chain(st.collided.take().map(|c| c.1)).collect();
                    for w in flying {
                        if let Sent::Line(seq) = w {
                            st.todo.insert(seq);
                        }
                    }
                    shared.update_stats(st);
                }
                let msg = e.to_string();
                if last_error.as_deref() != Some(msg.as_str()) {
                    tracing::warn!("MQTT: broker unreachable ({msg}); keeping up to {} feed lines in memory, retrying", shared.cap);
                    last_error = Some(msg);
                }
                tokio::time::sleep(backoff.next_delay()).await;
            }
        }
    }
}

/// The publisher as a sink of finished lines (the room for each was made by
/// [`MqttPublisher::reserve`] when its line was completed).
pub struct MqttSink(pub Arc<MqttPublisher>);

impl crate::LineSink for MqttSink {
    fn name(&self) -> String {
        "mqtt".into()
    }
    fn accept(&mut self, f: &crate::Finished) {
        self.0.publish(&f.line);
    }
}
