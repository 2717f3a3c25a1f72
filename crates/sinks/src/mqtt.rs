//! The MQTT publisher (`[output.mqtt]`, SPEC "Configuration"): every feed line goes to
//! `<topic>/feed`, a retained status message to `<topic>/status`, with a last will that
//! says the rig went offline.
//!
//! The measurement never waits on the broker. [`MqttPublisher::publish`] only takes a lock
//! for a few microseconds and hands the serialised line to a bounded buffer; a task on the
//! pipeline's runtime drives the connection ([`rumqttc`]), sends what the buffer holds and
//! reconnects with a backoff (0.2 s doubling to 2 s) while the broker is unreachable.
//!
//! **Delivery accounting.** The buffer owns every line until the broker has acknowledged it
//! (PUBACK at QoS 1, PUBCOMP at QoS 2): lines sent but unacknowledged when the connection
//! breaks go back to the front of the buffer and are sent again on the next connection
//! (an archive deduplicates them on `(rig, test, seq)`). At most `buffer_lines` lines are
//! held, sent or not; beyond that the oldest is dropped and counted. The count so far is
//! written into every feed line as `mqtt_dropped` (the local feed and the published line
//! carry the same value: the count includes a drop caused by this very line). It bounds
//! what the broker never got from above: a dropped line that was sent but not yet
//! acknowledged when the connection broke may have reached the broker after all.
//!
//! **Metrics.** [`MqttPublisher::stats`] returns an `Arc<`[`MqttStats`]`>` of atomics an HTTP
//! `/metrics` endpoint can read at any time: `dropped` (lines dropped from the buffer),
//! `published` (lines acknowledged by the broker), `buffered` (lines held now),
//! `connected` (0/1) and `reconnects`.

use std::collections::{BTreeMap, HashMap, VecDeque};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use rumqttc::{AsyncClient, Event, EventLoop, LastWill, MqttOptions, Outgoing, Packet, QoS, TlsConfiguration, Transport};
use serde::{Deserialize, Serialize};

use crate::RigInfo;
use tagdeflect_core::feed::FeedLine;

/// `[output.mqtt]`: publish the feed to an MQTT broker.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MqttConfig {
    /// `mqtt://host[:port]` (1883) or `mqtts://host[:port]` (TLS, 8883).
    pub url: String,
    /// Topic prefix; `{rig}` and `{test}` must each be a whole topic level.
    #[serde(default = "default_topic")]
    pub topic: String,
    /// This rig's name (default: the host name).
    #[serde(default = "default_rig")]
    pub rig: String,
    /// The test id; generated per run (`YYYYMMDDTHHMMSSZ-xxxx`, printed) when absent. A
    /// configured id must be new for every run: an archive keeps the first line it got for
    /// each (rig, test, seq).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub test: Option<String>,
    /// QoS of the feed lines (0, 1 or 2; 1 = at least once).
    #[serde(default = "default_qos")]
    pub qos: u8,
    /// MQTT client id (default `tagdeflect-<rig>`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub client_id: Option<String>,
    /// User name for the broker.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub username: Option<String>,
    /// Password for the broker (never written into recordings).
    #[serde(default, skip_serializing)]
    pub password: Option<String>,
    /// TLS: PEM file of the CA certificates that sign the broker's certificate (default:
    /// the system bundle `/etc/ssl/certs/ca-certificates.crt`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ca_file: Option<PathBuf>,
    /// TLS client authentication: PEM certificate chain (with `client_key`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub client_cert: Option<PathBuf>,
    /// TLS client authentication: PEM private key (with `client_cert`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub client_key: Option<PathBuf>,
    /// Feed lines held while the broker is unreachable or slow (sent or not yet
    /// acknowledged); the oldest is dropped beyond this.
    #[serde(default = "default_buffer")]
    pub buffer_lines: usize,
    /// MQTT keep-alive, seconds.
    #[serde(default = "default_keep_alive")]
    pub keep_alive_s: u64,
    /// Seconds between refreshes of the retained status.
    #[serde(default = "default_status_interval")]
    pub status_interval_s: f64,
}

fn default_topic() -> String {
    "tagdeflect/{rig}/{test}".into()
}
fn default_rig() -> String {
    hostname()
}
fn default_qos() -> u8 {
    1
}
fn default_buffer() -> usize {
    10_000
}
fn default_keep_alive() -> u64 {
    15
}
fn default_status_interval() -> f64 {
    5.0
}

/// This machine's host name (`localhost` when unknown).
pub fn hostname() -> String {
    std::fs::read_to_string("/proc/sys/kernel/hostname")
        .or_else(|_| std::fs::read_to_string("/etc/hostname"))
        .map(|s| s.trim().to_string())
        .ok()
        .filter(|s| !s.is_empty())
        .unwrap_or_else(|| "localhost".into())
}

/// A broker address parsed from `mqtt://` / `mqtts://` URLs.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BrokerUrl {
    /// True for `mqtts://` (also `ssl://`).
    pub tls: bool,
    /// Host name or address.
    pub host: String,
    /// TCP port.
    pub port: u16,
    /// User name given in the URL.
    pub username: Option<String>,
    /// Password given in the URL.
    pub password: Option<String>,
}

impl BrokerUrl {
    /// Parses `mqtt://[user[:password]@]host[:port]` (also `tcp://`; `mqtts://` / `ssl://` for TLS).
    pub fn parse(url: &str) -> Result<BrokerUrl, String> {
        let (scheme, rest) = url.split_once("://").ok_or_else(|| format!("\"{url}\" is not a URL like mqtt://host:1883"))?;
        let tls = match scheme {
            "mqtt" | "tcp" => false,
            "mqtts" | "ssl" => true,
            _ => return Err(format!("unknown scheme \"{scheme}\": expected mqtt:// or mqtts://")),
        };
        let rest = rest.trim_end_matches('/');
        if rest.contains('/') || rest.contains('?') {
            return Err(format!("\"{url}\": expected mqtt://host[:port] with no path"));
        }
        let (auth, hostport) = match rest.rsplit_once('@') {
            Some((a, h)) => (Some(a), h),
            None => (None, rest),
        };
        let (username, password) = match auth {
            None => (None, None),
            Some(a) => match a.split_once(':') {
                Some((u, p)) => (Some(u.to_string()), Some(p.to_string())),
                None => (Some(a.to_string()), None),
            },
        };
        let (host, port) = if let Some(h) = hostport.strip_prefix('[') {
            // [v6]:port
            let (h, p) = h.split_once(']').ok_or_else(|| format!("\"{url}\": unclosed [ in the host"))?;
            (h.to_string(), p.strip_prefix(':'))
        } else {
            match hostport.rsplit_once(':') {
                Some((h, p)) => (h.to_string(), Some(p)),
                None => (hostport.to_string(), None),
            }
        };
        if host.is_empty() {
            return Err(format!("\"{url}\": no host"));
        }
        let port = match port {
            Some(p) => p.parse::<u16>().map_err(|_| format!("\"{url}\": port \"{p}\" is not a number 1..65535"))?,
            None if tls => 8883,
            None => 1883,
        };
        Ok(BrokerUrl { tls, host, port, username, password })
    }
}

/// Replaces `{rig}` and `{test}` in a topic template.
pub fn topic_for(template: &str, rig: &str, test: &str) -> String {
    template.replace("{rig}", rig).replace("{test}", test)
}

/// Checks a topic template: no wildcards, `{rig}` and `{test}` each one whole level.
pub fn check_topic_template(t: &str) -> Result<(), String> {
    if t.is_empty() || t.contains(['+', '#', '\0']) {
        return Err(format!("\"{t}\" must be a non-empty topic without the wildcards + and #"));
    }
    let levels: Vec<&str> = t.split('/').collect();
    for ph in ["{rig}", "{test}"] {
        let whole = levels.iter().filter(|l| **l == ph).count();
        if whole != 1 || t.matches(ph).count() != 1 {
            return Err(format!("\"{t}\" must contain {ph} exactly once, as a whole topic level (e.g. \"tagdeflect/{{rig}}/{{test}}\"), so an archive can tell rigs and tests apart"));
        }
    }
    Ok(())
}

/// Checks a rig or test name used in a topic level.
pub fn check_level_name(what: &str, v: &str) -> Result<(), String> {
    if v.is_empty() || v.contains(['/', '+', '#', '\0']) || v.starts_with('$') {
        return Err(format!("{what} \"{v}\" must be non-empty, without '/', '+', '#' and not start with '$' (it is a topic level)"));
    }
    Ok(())
}

impl MqttConfig {
    /// Validates the section and resolves TLS file paths against `base` (the config's
    /// folder). On error: the key (below `output.mqtt`) and what is wrong.
    pub fn validate(&mut self, base: &Path) -> Result<(), (&'static str, String)> {
        let url = BrokerUrl::parse(&self.url).map_err(|m| ("url", m))?;
        check_topic_template(&self.topic).map_err(|m| ("topic", m))?;
        check_level_name("rig", &self.rig).map_err(|m| ("rig", m))?;
        if let Some(t) = &self.test {
            check_level_name("test", t).map_err(|m| ("test", m))?;
        }
        if self.qos > 2 {
            return Err(("qos", format!("must be 0, 1 or 2, got {}", self.qos)));
        }
        if let Some(id) = &self.client_id {
            if id.is_empty() || id.len() > 256 {
                return Err(("client_id", "must be 1 to 256 characters".into()));
            }
        }
        if self.password.is_some() && self.username.is_none() && url.username.is_none() {
            return Err(("password", "a password needs a `username`".into()));
        }
        if self.buffer_lines == 0 {
            return Err(("buffer_lines", "must be at least 1".into()));
        }
        if self.keep_alive_s < 5 || self.keep_alive_s > 3600 {
            return Err(("keep_alive_s", format!("must be 5..3600 s, got {}", self.keep_alive_s)));
        }
        if !(self.status_interval_s.is_finite() && self.status_interval_s >= 0.1) {
            return Err(("status_interval_s", "must be at least 0.1 s".into()));
        }
        let tls_keys = self.ca_file.is_some() || self.client_cert.is_some() || self.client_key.is_some();
        if tls_keys && !url.tls {
            return Err(("url", "TLS options are set but the URL is not mqtts://".into()));
        }
        if self.client_cert.is_some() != self.client_key.is_some() {
            return Err(("client_cert", "give both `client_cert` and `client_key`, or neither".into()));
        }
        for (key, p) in [("ca_file", &mut self.ca_file), ("client_cert", &mut self.client_cert), ("client_key", &mut self.client_key)] {
            if let Some(path) = p {
                if path.is_relative() {
                    *path = base.join(&*path);
                }
                if let Err(e) = std::fs::metadata(&*path) {
                    return Err((key, format!("cannot read {}: {e}", path.display())));
                }
            }
        }
        if url.tls {
            tls_config(self).map_err(|m| ("ca_file", m))?;
        }
        Ok(())
    }
}

/// Builds the rustls client configuration of a `mqtts://` connection: the CA bundle
/// (default: the system's), and optionally a client certificate and key (PEM files).
pub fn tls_config_for(
    ca_file: Option<&Path>,
    client_cert: Option<&Path>,
    client_key: Option<&Path>,
) -> Result<Arc<rustls::ClientConfig>, String> {
    use rustls::pki_types::pem::PemObject;
    use rustls::pki_types::{CertificateDer, PrivateKeyDer};
    let ca = ca_file.map(Path::to_path_buf).unwrap_or_else(|| PathBuf::from("/etc/ssl/certs/ca-certificates.crt"));
    let mut roots = rustls::RootCertStore::empty();
    let certs = CertificateDer::pem_file_iter(&ca).map_err(|e| format!("{}: {e}", ca.display()))?;
    for c in certs {
        let c = c.map_err(|e| format!("{}: {e}", ca.display()))?;
        roots.add(c).map_err(|e| format!("{}: {e}", ca.display()))?;
    }
    if roots.is_empty() {
        return Err(format!("{}: no CA certificate in it", ca.display()));
    }
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let builder = rustls::ClientConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .map_err(|e| e.to_string())?
        .with_root_certificates(roots);
    let config = match (client_cert, client_key) {
        (Some(cert), Some(key)) => {
            let chain: Vec<CertificateDer<'static>> = CertificateDer::pem_file_iter(cert)
                .and_then(|it| it.collect::<Result<Vec<_>, _>>())
                .map_err(|e| format!("{}: {e}", cert.display()))?;
            let key = PrivateKeyDer::from_pem_file(key).map_err(|e| format!("{}: {e}", key.display()))?;
            builder.with_client_auth_cert(chain, key).map_err(|e| format!("client certificate: {e}"))?
        }
        _ => builder.with_no_client_auth(),
    };
    Ok(Arc::new(config))
}

fn tls_config(cfg: &MqttConfig) -> Result<Arc<rustls::ClientConfig>, String> {
    tls_config_for(cfg.ca_file.as_deref(), cfg.client_cert.as_deref(), cfg.client_key.as_deref())
}

/// Connection options for a broker URL (TLS, credentials from the URL or given).
pub fn mqtt_options(
    url: &str,
    client_id: &str,
    username: Option<&str>,
    password: Option<&str>,
    tls: Option<Arc<rustls::ClientConfig>>,
) -> Result<MqttOptions, String> {
    let u = BrokerUrl::parse(url)?;
    let mut o = MqttOptions::new(client_id, u.host.clone(), u.port);
    if u.tls {
        let cfg = match tls {
            Some(c) => c,
            None => tls_config_for(None, None, None)?,
        };
        o.set_transport(Transport::tls_with_config(TlsConfiguration::Rustls(cfg)));
    }
    let user = username.map(str::to_string).or(u.username);
    let pass = password.map(str::to_string).or(u.password);
    if let Some(user) = user {
        o.set_credentials(user, pass.unwrap_or_default());
    }
    // Feed lines of a big rig are a few kB; leave ample room.
    o.set_max_packet_size(1 << 20, 1 << 20);
    Ok(o)
}

fn qos_of(q: u8) -> QoS {
    match q {
        0 => QoS::AtMostOnce,
        1 => QoS::AtLeastOnce,
        _ => QoS::ExactlyOnce,
    }
}

/// A new test id: the UTC start time and four random hex digits.
pub fn new_test_id() -> String {
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
        let tls = if BrokerUrl::parse(&cfg.url)?.tls { Some(tls_config(cfg)?) } else { None };
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
    let mut backoff = Duration::from_millis(200);
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
                backoff = Duration::from_millis(200);
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
                tokio::time::sleep(backoff).await;
                backoff = (backoff * 2).min(Duration::from_secs(2));
            }
        }
    }
}

/// Byte offset of `key = ...` in the `[output.mqtt]` section of a config text (or of the
/// section header when the key is not written there), for located config errors.
pub fn key_offset(text: &str, key: &str) -> Option<usize> {
    let mut offset = 0;
    let mut header = None;
    for line in text.split_inclusive('\n') {
        let t = line.trim();
        if t.starts_with('[') {
            if header.is_some() {
                break;
            }
            if t.trim_start_matches('[').trim_end_matches(']').trim() == "output.mqtt" {
                header = Some(offset);
            }
        } else if header.is_some() {
            if let Some((k, _)) = t.split_once('=') {
                if k.trim().trim_matches('"') == key {
                    return Some(offset);
                }
            }
        }
        offset += line.len();
    }
    header
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
