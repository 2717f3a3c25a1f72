//! The MQTT wire contract between a rig's publisher (`tagdeflect_sinks::mqtt`) and the
//! archive (`tagdeflect_archive`): what crosses the broker, so that neither side stands on
//! the other (SPEC "Configuration" `[output.mqtt]`, "Archive").
//!
//! * [`broker`]: broker URLs (`mqtt://`, `mqtts://`), TLS and the client's connection options.
//! * [`topic`]: the topic template (`{rig}`, `{test}` as whole levels), its levels' names and
//!   the layout below it: `<topic>/feed`, `<topic>/status`, `<topic>/archive`,
//!   `<topic>/labtest/<id>`.
//! * [`ack`]: the archive's retained acknowledgement of what it holds ([`ArchiveAck`]).
//! * [`lab_test`]: a lab test's record on the broker ([`LabTestMessage`]) and its checks.

pub mod ack;
pub mod broker;
mod error;
pub mod lab_test;
pub mod topic;

pub use ack::{ArchiveAck, RunHeld, SeqRanges};
pub use broker::{hostname, mqtt_options, tls_config_for, BrokerUrl};
pub use error::WireError;
pub use lab_test::{LabTestMessage, MAX_LAB_TEST_BYTES};
pub use topic::{
    check_level_name, check_topic_template, topic_for, Kind, TopicLayout, ACK_SUFFIX, FEED_SUFFIX, LAB_TEST_SUFFIX, STATUS_SUFFIX,
};
