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

mod client;
mod config;
mod publisher;

pub use client::{check_level_name, check_topic_template, hostname, mqtt_options, tls_config_for, topic_for, BrokerUrl};
pub use config::MqttConfig;
pub use publisher::{MqttPublisher, MqttSink, MqttStats};
