//! The commands' drivers around the graph: replay, live (run / record / demo / replay
//! --realtime), check and bench, and the report a run writes at its end.

pub mod bench;
#[cfg(feature = "calibrate")]
pub mod calibrate_cmd;
pub mod check;
pub mod journal;
pub mod live;
pub mod replay;
pub mod report_cmd;
pub mod run_report;

pub use tagdeflect_estimate::measure;
