//! tagdeflect: non-contact deflection measurement of beams in bending with AprilTags.
//!
//! This crate is the program: it assembles the config from the sections the components own
//! ([`config`]), builds the graph — sources → frame sets → measurement → sinks — in one place
//! ([`graph`]), and holds one module per command ([`pipeline`]). The components are the
//! workspace's library crates, re-exported here under the names the program and its tests
//! use:
//!
//! | module | crate | holds |
//! | --- | --- | --- |
//! | `frame`, `camera`, `tags`, `clock`, `backoff`, `feed` | `tagdeflect-core` | the shared building blocks |
//! | [`detect`] | `tagdeflect-detect` | AprilTag detection, refinement, tracking |
//! | [`solve`] | `tagdeflect-estimate` | poses, LM, drift, gauges, the measurement of a frame set |
//! | [`sources`], [`sync`], [`utm`], [`recording`] | `tagdeflect-io` | what comes in |
//! | [`sinks`] | `tagdeflect-sinks` | recorder, live page, MQTT |
//! | [`report`] | `tagdeflect-report` | the test report |
//! | `sim`, `calibrate`, `archive` | `tagdeflect-sim`, `-calibrate`, `-archive` | behind the features of the same names |

pub mod accuracy;
pub mod config;
pub mod fuzzing;
pub mod graph;
pub mod pipeline;

pub use tagdeflect_core::{backoff, camera, clock, feed, frame, tags};
pub use tagdeflect_core::{BadInput, RuntimeFailure};
pub use tagdeflect_detect as detect;
pub use tagdeflect_estimate as solve;
pub use tagdeflect_io::{sync, utm};
pub use tagdeflect_report as report;

#[cfg(feature = "archive")]
pub use tagdeflect_archive as archive;
#[cfg(feature = "calibrate")]
pub use tagdeflect_calibrate as calibrate;

/// The simulated rig (`tagdeflect-sim`), with the recording writers that need the whole config.
#[cfg(feature = "sim")]
pub mod sim {
    pub use tagdeflect_sim::*;

    use crate::config::Config;
    use std::path::Path;

    /// Writes a simulated recording of `params` into `out` (frames as PNG).
    pub fn simulate(params: &SimParams, out: &Path) -> Result<SimSummary, SimError> {
        simulate_as(params, out, tagdeflect_core::frame::FrameFormat::Png)
    }

    /// [`simulate`] with the frames written in `format`.
    pub fn simulate_as(params: &SimParams, out: &Path, format: tagdeflect_core::frame::FrameFormat) -> Result<SimSummary, SimError> {
        let rig = SimRig::new(params)?;
        tagdeflect_sim::simulate_as(params, out, format, &Config::from_sim(&rig))
    }
}

/// Frame sources (`tagdeflect-io`), and the simulated cameras (`tagdeflect-sim`).
pub mod sources {
    pub use tagdeflect_core::clock;
    pub use tagdeflect_io::sources::*;
    #[cfg(feature = "sim")]
    pub use tagdeflect_sim::live_rig as sim;
}

/// Sinks (`tagdeflect-sinks`), and the feed file writer and line files (`tagdeflect-core`).
pub mod sinks {
    pub use tagdeflect_core::feed_file as feed;
    pub use tagdeflect_core::linefile;
    pub use tagdeflect_sinks::*;
}

/// Recordings (`tagdeflect-io`), opened with the program's config.
pub mod recording {
    pub use tagdeflect_io::recording::*;

    /// A recording with the program's whole config.
    pub type Recording = tagdeflect_io::recording::Recording<crate::config::Config>;
}
