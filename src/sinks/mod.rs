//! Sinks: where feed lines go. Each sink fails on its own: an unwritable output is
//! reported once and disabled while the others go on.

pub mod feed;
pub mod http;
pub mod mqtt;
