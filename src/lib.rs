//! tagdeflect: non-contact deflection measurement of beams in bending with AprilTags.
//!
//! This crate is the program. It assembles the config from the sections the components own
//! ([`config`]), builds the graph — sources → frame sets → measurement → sinks — from it
//! ([`graph`]), and holds one module per command around the graph ([`commands`]). The
//! components are the workspace's library crates, named by their own names everywhere (the
//! program's code and its tests alike):
//!
//! | crate | holds |
//! | --- | --- |
//! | `tagdeflect-core` | the ground floor: frames, cameras, tags, clock, feed line, config problems, the payloads that cross crates |
//! | `tagdeflect-detect` | AprilTag detection, refinement, tracking |
//! | `tagdeflect-estimate` | poses, LM, drift, temporal estimate, gauges, the measurement of a frame set |
//! | `tagdeflect-io` | what comes in: sources, frame-set assembly, UTM, recordings |
//! | `tagdeflect-sinks` | what goes out: recorder, live page, MQTT, control registers, lab tests |
//! | `tagdeflect-report` | the test report |
//! | `tagdeflect-sim`, `-calibrate`, `-archive` | behind the features of the same names |
//!
//! [`accuracy`] and [`fuzzing`] are the tools the tests and `bench` share.

pub mod accuracy;
pub mod commands;
pub mod config;
pub mod fuzzing;
pub mod graph;
