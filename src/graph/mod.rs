//! The graph: sources → frame sets → measurement → sinks, built in one place from the config.
//!
//! * [`sources`]: every camera of the config started (V4L2, Aravis, a recording played at its
//!   pace, the simulated rig's cameras);
//! * [`run`]: the live graph behind `run`, `record`, `demo` and `replay --realtime` — the
//!   assembler, the solver thread, the sinks built from `[output]` in one place
//!   (`Outputs::build`) and fed on their own thread;
//! * [`page`]: the live page's hooks (absent without the `http` feature).

pub mod lab_tests;
pub mod page;
pub mod run;
pub mod sources;
