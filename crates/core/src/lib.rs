//! The building blocks every stage of tagdeflect shares: frames, the camera model, tags and
//! their roles, the rig as the config describes it (cameras, background, specimen, beam), the
//! one process clock, reconnect backoff, UTM samples, the feed line (one type, written by the
//! measurement and read tolerantly by the report), what the measurement observed for the page
//! and the line files it goes into, the virtual gauges' definitions, a lab test's record
//! (`test.json`), test methods, the specimens entered before their tests, and the hash-chained
//! audit log of a tests folder (`audit.jsonl`).
//!
//! Nothing here does I/O beyond reading and writing files, and nothing knows the command line.

pub mod audit;
pub mod backoff;
pub mod beam;
pub mod calibration_file;
pub mod camera;
pub mod camera_config;
pub mod clock;
pub mod control_summary;
pub mod disk;
pub mod error;
pub mod feed;
pub mod feed_file;
pub mod feed_rotation;
pub mod frame;
pub mod gauge;
pub mod lab_test;
pub mod limits;
pub mod linefile;
pub mod listen;
pub mod method;
pub mod observed;
pub mod problem;
pub mod rig;
pub mod specimen;
pub mod stats;
pub mod tags;
pub mod text_file;
pub mod users;
pub mod utm_sample;
pub mod verification;

pub use error::{BadInput, NotFit, RuntimeFailure};
pub use problem::Problem;
