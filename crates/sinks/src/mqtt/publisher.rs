//! The publisher: starts the connection's tasks, takes feed lines without waiting on the
//! network, and ends the run (see the module doc of [`super`]); the publisher as a sink.

use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use rumqttc::{AsyncClient, LastWill, QoS};

use super::connection::drive;
use super::feed_source::{load_loop, FeedSource};
use super::state::{Sent, Shared, State, TAIL_RESEND_AFTER};
use super::{MqttConfig, MqttStats};
use crate::status::{RigStatus, RunStatus};
use crate::RigInfo;
use tagdeflect_core::feed::FeedLine;
use tagdeflect_wire::{mqtt_options, topic_for, BrokerUrl, SeqRanges, WireError, ACK_SUFFIX, FEED_SUFFIX, STATUS_SUFFIX};

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

/// The client's options of `[output.mqtt]`: TLS, credentials, a clean session (the buffer
/// retransmits itself), the keep-alive and the in-flight window.
fn connection_options(cfg: &MqttConfig, window: usize) -> Result<rumqttc::MqttOptions, WireError> {
    let client_id = cfg.client_id.clone().unwrap_or_else(|| format!("tagdeflect-{}", cfg.rig));
    let tls = if BrokerUrl::parse(&cfg.url)?.tls { Some(cfg.tls_config()?) } else { None };
    let mut opts = mqtt_options(&cfg.url, &client_id, cfg.username.as_deref(), cfg.password.as_deref(), tls)?;
    // The buffer retransmits itself: a clean session means the client never resends
    // anything of its own after a reconnect.
    opts.set_clean_session(true);
    opts.set_keep_alive(Duration::from_secs(cfg.keep_alive_s));
    opts.set_inflight(window as u16);
    Ok(opts)
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
    pub fn start(cfg: &MqttConfig, config: &RigInfo, recording: Option<&Path>, feed: Option<&Path>) -> Result<MqttPublisher, WireError> {
        let test = cfg.test.clone().unwrap_or_else(new_test_id);
        let base = topic_for(&cfg.topic, &cfg.rig, &test);
        let window: usize = 100;
        let mut opts = connection_options(cfg, window)?;
        let run = RunStatus::new(config, recording.map(|p| p.display().to_string()), tagdeflect_core::clock::now_epoch_ns());
        let status = RigStatus { state: "online", rig: cfg.rig.clone(), test: test.clone(), run, mqtt_dropped: 0, archive_lag: None };
        let status_topic = format!("{base}/{STATUS_SUFFIX}");
        let mut offline = status.clone();
        offline.state = "offline";
        opts.set_last_will(LastWill::new(&status_topic, serde_json::to_vec(&offline).expect("status serialises"), QoS::AtLeastOnce, true));
        let (client, eventloop) = AsyncClient::new(opts, window + 16);
        let feed = feed.map(|p| Mutex::new(FeedSource::new(p)));
        let shared = Arc::new(Shared {
            state: Mutex::new(State::new(status)),
            stats: Arc::new(MqttStats::default()),
            client,
            feed_topic: format!("{base}/{FEED_SUFFIX}"),
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

    /// What the publisher's tasks share.
    pub(super) fn shared(&self) -> &Shared {
        &self.shared
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
        st.status.run.observe(line);
        st.status.mqtt_dropped = st.dropped;
        s.pump(&mut st);
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
