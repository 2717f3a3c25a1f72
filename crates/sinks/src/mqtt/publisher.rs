//! The publisher: the buffer of feed lines, the task that drives the connection and pumps
//! the buffer into it, and the publisher as a sink (see the module doc of [`super`]).

use std::collections::{BTreeMap, HashMap, VecDeque};
use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use rumqttc::{AsyncClient, Event, EventLoop, LastWill, Outgoing, Packet, QoS};
use serde::Serialize;

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
    /// Feed lines dropped from the buffer (oldest first) since the start.
    pub dropped: AtomicU64,
    /// Feed lines acknowledged by the broker (at QoS 0: written to the connection).
    pub published: AtomicU64,
    /// Feed lines held in the buffer now (sent or not, unacknowledged).
    pub buffered: AtomicU64,
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
}

struct State {
    connected: bool,
    stopping: bool,
    next_id: u64,
    /// Lines not handed to the client yet, oldest first.
    unsent: VecDeque<(u64, Vec<u8>)>,
    /// Lines handed to the client, not acknowledged.
    sent: BTreeMap<u64, Vec<u8>>,
    /// Publishes handed to the client, in order, awaiting their packet id.
    order: VecDeque<Sent>,
    /// Packet id → publish awaiting its acknowledgement.
    pkids: HashMap<u16, Sent>,
    /// A publish parked by the client on a packet-id collision.
    collided: Option<(u16, Sent)>,
    status: Status,
    dropped: u64,
}

struct Shared {
    state: Mutex<State>,
    stats: Arc<MqttStats>,
    client: AsyncClient,
    feed_topic: String,
    status_topic: String,
    qos: QoS,
    window: usize,
    cap: usize,
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
    /// background (the run does not wait for the broker). Fails only on a configuration
    /// the broker client rejects.
    pub fn start(cfg: &MqttConfig, config: &RigInfo, recording: Option<&Path>) -> Result<MqttPublisher, String> {
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
        };
        let status_topic = format!("{base}/status");
        let mut offline = status.clone();
        offline.state = "offline";
        opts.set_last_will(LastWill::new(&status_topic, serde_json::to_vec(&offline).expect("status serialises"), QoS::AtLeastOnce, true));
        let (client, eventloop) = AsyncClient::new(opts, window + 16);
        let shared = Arc::new(Shared {
            state: Mutex::new(State {
                connected: false,
                stopping: false,
                next_id: 0,
                unsent: VecDeque::new(),
                sent: BTreeMap::new(),
                order: VecDeque::new(),
                pkids: HashMap::new(),
                collided: None,
                status,
                dropped: 0,
            }),
            stats: Arc::new(MqttStats::default()),
            client,
            feed_topic: format!("{base}/feed"),
            status_topic,
            qos: qos_of(cfg.qos),
            window,
            cap: cfg.buffer_lines,
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
        tracing::info!(rig = %cfg.rig, test = %test, topic = %base, "MQTT: publishing the feed to {} (test id {test})", cfg.url);
        eprintln!("tagdeflect: MQTT test id {test} (topic {base}/feed)");
        Ok(MqttPublisher { shared, tasks: Mutex::new(vec![poller, ticker]), done, test })
    }

    /// The test id of this run.
    pub fn test(&self) -> &str {
        &self.test
    }

    /// The publisher's counters (for `/metrics`).
    pub fn stats(&self) -> Arc<MqttStats> {
        self.shared.stats.clone()
    }

    /// Makes room in the buffer for the next line (dropping the oldest when it is full) and
    /// returns the lines dropped so far, this one's drop included: the `mqtt_dropped` of the
    /// line about to be [published](Self::publish). Called by the measurement's status step,
    /// so the line is complete before any sink sees it.
    pub fn reserve(&self) -> u64 {
        let s = &self.shared;
        let mut st = s.state.lock().expect("mqtt state");
        if st.unsent.len() + st.sent.len() >= s.cap {
            let oldest_unsent = st.unsent.front().map(|(id, _)| *id);
            let oldest_sent = st.sent.keys().next().copied();
            match (oldest_unsent, oldest_sent) {
                (Some(u), Some(v)) if v < u => {
                    st.sent.remove(&v);
                }
                (Some(_), _) => {
                    st.unsent.pop_front();
                }
                (None, Some(v)) => {
                    st.sent.remove(&v);
                }
                (None, None) => {}
            }
            st.dropped += 1;
            s.stats.dropped.fetch_add(1, Ordering::Relaxed);
        }
        st.dropped
    }

    /// Hands a feed line over for publishing, never waiting on the network: buffers the
    /// line as serialised (its `mqtt_dropped` came from [`Self::reserve`]). Lines reserved
    /// but not yet handed over (those in the sinks' queue) may hold the buffer that many
    /// lines above its size for a moment.
    pub fn publish(&self, line: &FeedLine) {
        let s = &self.shared;
        let mut st = s.state.lock().expect("mqtt state");
        let bytes = line.to_json().into_bytes();
        let id = st.next_id;
        st.next_id += 1;
        st.unsent.push_back((id, bytes));
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

    /// Ends the run: waits up to `timeout` for the buffer to drain, publishes the retained
    /// status `offline`, disconnects and logs what was published, dropped and left unsent.
    pub async fn finish(&self, timeout: Duration) {
        let s = &self.shared;
        let until = tokio::time::Instant::now() + timeout;
        loop {
            let left = {
                let st = s.state.lock().expect("mqtt state");
                st.unsent.len() + st.sent.len()
            };
            if left == 0 || tokio::time::Instant::now() >= until {
                break;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        let (unsent, dropped, connected) = {
            let mut st = s.state.lock().expect("mqtt state");
            st.stopping = true;
            st.status.state = "offline";
            if st.connected {
                s.send_status(&mut st);
            }
            (st.unsent.len() + st.sent.len(), st.dropped, st.connected)
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
        if unsent > 0 {
            tracing::warn!(published, dropped, unsent, "MQTT: stopped with {unsent} feed lines not acknowledged by the broker");
        } else {
            tracing::info!(published, dropped, "MQTT: all feed lines handed to the broker");
        }
    }
}

impl Shared {
    /// Hands buffered lines to the client while connected and the in-flight window allows.
    fn pump(&self, st: &mut State) {
        while st.connected && st.order.len() + st.pkids.len() < self.window {
            let Some((id, bytes)) = st.unsent.pop_front() else { break };
            match self.client.try_publish(self.feed_topic.clone(), self.qos, false, bytes.clone()) {
                Ok(()) => {
                    st.sent.insert(id, bytes);
                    st.order.push_back(Sent::Line(id));
                }
                Err(_) => {
                    st.unsent.push_front((id, bytes));
                    break;
                }
            }
        }
        self.stats.buffered.store((st.unsent.len() + st.sent.len()) as u64, Ordering::Relaxed);
    }

    fn send_status(&self, st: &mut State) {
        let payload = serde_json::to_vec(&st.status).expect("status serialises");
        if self.client.try_publish(self.status_topic.clone(), QoS::AtLeastOnce, true, payload).is_ok() {
            st.order.push_back(Sent::Status);
        }
    }

    fn acked(&self, st: &mut State, who: Sent) {
        if let Sent::Line(id) = who {
            if st.sent.remove(&id).is_some() {
                self.stats.published.fetch_add(1, Ordering::Relaxed);
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
                let n = st.unsent.len();
                tracing::info!(buffered = n, "MQTT: connected to the broker");
                shared.send_status(&mut st);
                shared.pump(&mut st);
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
                        Sent::Status => false,
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
                    let mut st = shared.state.lock().expect("mqtt state");
                    // Everything the client still holds is forgotten (clean session); the
                    // buffer takes the unacknowledged lines back, in order.
                    eventloop.clean();
                    eventloop.pending.clear();
                    eventloop.state.events.clear();
                    st.connected = false;
                    shared.stats.connected.store(0, Ordering::Relaxed);
                    let sent = std::mem::take(&mut st.sent);
                    for (id, bytes) in sent.into_iter().rev() {
                        st.unsent.push_front((id, bytes));
                    }
                    st.order.clear();
                    st.pkids.clear();
                    st.collided = None;
                }
                let msg = e.to_string();
                if last_error.as_deref() != Some(msg.as_str()) {
                    tracing::warn!("MQTT: broker unreachable ({msg}); buffering up to {} feed lines, retrying", shared.cap);
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
