//! One module per command around the graph ([`crate::graph`]): replay, check, bench, report
//! and export, calibrate, the daemon's journal summaries, and the report a run writes at its
//! end.

pub mod bench;
#[cfg(feature = "calibrate")]
pub mod calibrate_cmd;
pub mod cameras;
pub mod check;
pub mod journal;
pub mod replay;
pub mod report_cmd;
pub mod run_report;
pub mod test_cmd;

pub use tagdeflect_estimate::measure;
