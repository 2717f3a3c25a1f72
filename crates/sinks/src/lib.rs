//! Sinks: where feed lines go. Each sink fails on its own: an output that cannot be
//! written is reported, retried with backoff and never holds the measurement back.

pub mod analog_output;
pub mod control_output;
mod fanout;
#[cfg(feature = "http")]
pub mod http;
pub mod lab_test;
#[cfg(feature = "mqtt")]
pub mod mqtt;
pub mod output;
pub mod recorder;
mod rig_info;
pub mod signal;
pub mod signal_log;
pub mod status;

pub use fanout::{Fanout, FeedFileSink, Finished, LineSink, Overflow};
pub use rig_info::RigInfo;
