//! The MQTT publisher (`[output.mqtt]`, SPEC "Configuration"): every feed line goes to
//! `<topic>/feed`, a retained status message to `<topic>/status`, with a last will that
//! says the rig went offline; each lab test's record, retained, to `<topic>/labtest/<id>`
//! ([`lab_test`]). What crosses the broker (topics, the archive's acknowledgement, the lab
//! test's record, broker URLs) is the wire contract, `tagdeflect_wire`, which the archive
//! reads too.
//!
//! The measurement never waits on the broker. [`MqttPublisher::publish`] only takes a lock
//! for a few microseconds and hands the serialised line to a bounded buffer; a task on the
//! pipeline's runtime drives the connection ([`rumqttc`]), sends what the buffer holds and
//! reconnects with a backoff (0.2 s doubling to 2 s) while the broker is unreachable.
//!
//! **Delivery, end to end.** QoS 1 is a promise between the rig and the broker, not between
//! the rig and the archive: a broker restarted without persistence acknowledges lines and
//! delivers them to nobody until the archive has subscribed again. So the rig keeps every
//! line until the *archive* has confirmed it. After each commit, an archive publishes,
//! retained, on `<topic>/archive` what it holds of the test ([`tagdeflect_wire::ArchiveAck`]: per run, the
//! high-water seq and the gaps below it). The rig subscribes to it on every connection,
//! forgets what the archive holds, and sends again what the broker acknowledged but the
//! archive lacks below its high water (lines older than a second: the archive's view may
//! be a moment older than the broker's acknowledgement); at the end of a run, lines past
//! the archive's high water are sent again after 2 s without progress. An archive
//! deduplicates them on (rig, test, run, seq).
//!
//! **Memory and the feed file.** At most `buffer_lines` lines are kept in memory; beyond
//! that the oldest leaves memory. With a feed file (`[output] feed`) it stays owed: it is
//! read back from this run's part of the file when it has to be sent. Without one, a line
//! that leaves memory before the broker acknowledged it is lost and counted. The count so
//! far is written into every feed line as `mqtt_dropped` (the local feed and the published
//! line carry the same value): lines the archive will never get from this rig. Lines the
//! broker took but the archive never confirmed before they left memory (no feed file) are
//! counted apart (`evicted_unconfirmed`); the gap view of the archive shows them.
//!
//! **Metrics.** [`MqttPublisher::stats`] returns an `Arc<`[`MqttStats`]`>` of atomics an HTTP
//! `/metrics` endpoint can read at any time: `dropped`, `published` (lines acknowledged by
//! the broker), `buffered` (lines in memory), `unconfirmed`, `archive_lag` (lines of this
//! run the archive does not hold yet), `archive_high`, `archive_confirmed`,
//! `evicted_unconfirmed`, `connected` (0/1) and `reconnects`. The retained status carries
//! `archive_lag` too.

//!
//! The files: `config` (`[output.mqtt]` and its checks), `publisher` (start, take lines, end
//! the run), `state` (what is owed and in flight, the broker's and the archive's
//! acknowledgements), `connection` (the task that drives the connection), `feed_source`
//! (lines read back from the feed file), `lab_test` (lab tests' records), `stats`; the
//! status message is the run's status model ([`crate::status`]).

mod config;
mod connection;
mod feed_source;
mod lab_test;
mod publisher;
mod state;
mod stats;

pub use config::MqttConfig;
pub use publisher::{MqttPublisher, MqttSink};
pub use stats::MqttStats;
