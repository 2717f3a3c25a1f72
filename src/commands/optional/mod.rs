//! The commands a cargo feature brings (`simulate` and `demo`: `sim`; `archive` and
//! `archive-bench`: `archive`; `calibrate`: `calibrate`), each feature's commands one clap
//! [`Subcommand`](clap::Subcommand) enum flattened into the command line.
//!
//! A feature that is off leaves an `_off` twin in its module's place: an enum without
//! variants (the command line has no such command) and the same hooks, so `main.rs` carries
//! no feature gate. [`missing`] names the feature of a command this build lacks.

#[cfg(feature = "archive")]
pub mod archive;
#[cfg(not(feature = "archive"))]
#[path = "archive_off.rs"]
pub mod archive;
#[cfg(feature = "calibrate")]
pub mod calibrate;
#[cfg(not(feature = "calibrate"))]
#[path = "calibrate_off.rs"]
pub mod calibrate;
#[cfg(not(all(feature = "sim", feature = "archive", feature = "calibrate")))]
pub mod missing;
#[cfg(all(feature = "sim", feature = "archive", feature = "calibrate"))]
#[path = "missing_off.rs"]
pub mod missing;
#[cfg(feature = "sim")]
pub mod sim;
#[cfg(not(feature = "sim"))]
#[path = "sim_off.rs"]
pub mod sim;
