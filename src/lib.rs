//! tagdeflect: non-contact deflection measurement of beams in bending with AprilTags.
//!
//! Data flows one way: sources → frames → [`sync`] → frame sets → [`detect`] →
//! observations → [`solve`] → solutions → sinks. Live capture and replay are the same
//! graph with different sources (see [`pipeline`]).

pub mod accuracy;
pub mod camera;
pub mod config;
pub mod detect;
pub mod feed;
pub mod frame;
pub mod pipeline;
pub mod recording;
pub mod report;
pub mod sim;
pub mod sinks;
pub mod solve;
pub mod sources;
pub mod sync;
pub mod tags;
pub mod utm;
