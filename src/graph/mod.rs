//! The graph: sources → frame sets → measurement → sinks, built in one place from the config.

pub mod sources;
pub mod page;
