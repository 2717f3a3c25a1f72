//! One module per command around the graph ([`crate::graph`]): assets, bench, calibrate,
//! cameras, check, the lab tests' `test` client, report and export, and the simulator's
//! recordings. `run`, `record`, `demo` and `replay` are the graph itself
//! ([`crate::graph::entry`]).

pub mod assets;
pub mod bench;
#[cfg(feature = "calibrate")]
pub mod calibrate;
pub mod cameras;
pub mod check;
pub mod lab_test;
pub mod report;
#[cfg(feature = "sim")]
pub mod simulate;
