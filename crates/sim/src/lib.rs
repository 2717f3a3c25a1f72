//! The synthetic rig: scene, beam mechanics, renderer and ground truth.
//!
//! [`SimParams`] (from `config::sim`) holds every option of the simulated rig (the `[sim]`
//! config section and the options of `tagdeflect simulate`); [`SimRig`] builds the scene
//! from them and renders camera images at any time; [`simulate`] writes a SPEC recording
//! with ground truth.
//!
//! **World frame** of the simulated rig (mm): origin at midspan on the bottom edge of the
//! beam's front face; `x` along the beam (to the right as the cameras see it), `y`
//! horizontal away from the cameras (into the scene), `z` up (`world.up = [0, 0, 1]`).
//! The beam occupies `|x| ≤ length/2`, `0 ≤ y ≤ width`, `0 ≤ z ≤ height` at rest; the
//! supports are under its bottom edge at `x = ±span/2`; deflection is positive downward.

mod beam;
mod drift;
pub mod edge_patch;
mod error;
mod law;
pub mod live_rig;
mod loading;
pub mod machine;
mod params;
mod record;
mod render_rig;
mod rig;
mod scene;
mod sensor;
mod timing;
mod trace;
mod truth;

pub use beam::FourPointBeam;
pub use error::SimError;
pub use law::{load_at, tada_v1, NotchCompliance};
pub use record::{render_frame_set, simulate, simulate_as, SimSummary, SIM_TRUTH_FILE};
pub use rig::{SimCamera, SimRig, SimRigSections};
/// The renderer and the lens model the scene is traced through (shared with the
/// calibration's test images).
pub use tagdeflect_render::{self as render, lens};
pub use truth::{SimTruthCamera, SimTruthLine, SimTruthTag};

// The parameters of the rig are config (`[sim]`, checked when the config is read); the
// simulator uses them from there and the config never imports the simulator.
pub use crate::params::{camera_names, LoadLaw, SimParams, SimTest};
