//! Sinks: where feed lines go. Each sink fails on its own: an output that cannot be
//! written is reported, retried with backoff and never holds the measurement back.

pub mod feed;
pub mod http;
pub mod linefile;
pub mod mqtt;
pub mod recorder;
