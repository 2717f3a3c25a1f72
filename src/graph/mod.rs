//! The graph: sources → frame sets → measurement → sinks, built from the config.
//!
//! * [`entry`]: one entry point per way to run it (`run`/`record`/`demo`, `replay` as fast as
//!   it goes or at its pace, `check`'s first frame set);
//! * [`run`]: the story of a run (`run_async`): outputs, measurement, sources, UTM, the
//!   solver thread, the assembler, the shutdown — each a part of its own below;
//! * [`outputs`]: every output built by its own config section; [`page`] (the live page),
//!   `broker` (MQTT), [`lab_test`] (the tests), [`run_report`] (the report at the end),
//!   [`utm_file`] (the UTM's own rate), [`control_file`] (a test's `control.json`) are those
//!   outputs' graph-side parts;
//! * [`sources`] (the cameras), [`playback`] (a recording as the source), [`utm`] (the UTM's
//!   events and their forwarder), [`queue`] (the solver's queue), [`solver`] (its thread),
//!   [`smoothing`] (`replay --smooth`), [`journal`] (the run's summaries in the log),
//!   [`signals`] (what stops a run);
//! * [`in_process`]: the same measurement over a recording driven on the caller's thread
//!   (`bench`, tests).
//!
//! A feature that is off leaves an `_off` twin in its module's place with the same hooks
//! (`page`: `http`; `broker`: `mqtt`; `sim`: `sim`), so no function carries a feature gate.

#[cfg(feature = "mqtt")]
mod broker;
#[cfg(not(feature = "mqtt"))]
#[path = "broker_off.rs"]
mod broker;
pub mod control_file;
pub mod entry;
pub mod in_process;
pub mod journal;
pub mod lab_test;
mod outputs;
#[cfg(feature = "http")]
pub mod page;
#[cfg(not(feature = "http"))]
#[path = "page_off.rs"]
pub mod page;
pub mod playback;
mod queue;
pub mod run;
pub mod run_report;
mod signals;
#[cfg(feature = "sim")]
pub mod sim;
#[cfg(not(feature = "sim"))]
#[path = "sim_off.rs"]
pub mod sim;
mod smoothing;
mod solver;
pub mod sources;
mod utm;
pub mod utm_file;
