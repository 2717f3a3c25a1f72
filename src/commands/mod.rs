//! One module per command around the graph ([`crate::graph`]): assets, bench, calibrate,
//! cameras, check, the lab tests' `test` client, the control API's users, report and export, and the simulator's
//! recordings. `run`, `record`, `demo` and `replay` are the graph itself
//! ([`crate::graph::entry`]); [`optional`] holds the command-line faces of the commands a
//! feature brings, [`args`] the parsers the command line shares.

pub mod args;
pub mod assets;
pub mod bench;
#[cfg(feature = "calibrate")]
pub mod calibrate;
pub mod cameras;
pub mod check;
pub mod lab_test;
pub mod optional;
pub mod report;
#[cfg(feature = "sim")]
pub mod simulate;
pub mod user;
pub mod verify;

pub use args::parse_duration_s;
