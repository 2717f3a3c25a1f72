//! `tagdeflect simulate`: a recording of the simulated rig (`tagdeflect-sim`), written with
//! the program's whole config (the simulator knows its rig, not the config file's sections).

use std::path::Path;

use tagdeflect_core::frame::FrameFormat;
use tagdeflect_sim::{SimError, SimParams, SimRig, SimSummary};

use crate::config::Config;

/// Writes a simulated recording of `params` into `out` (frames as PNG).
pub fn simulate(params: &SimParams, out: &Path) -> Result<SimSummary, SimError> {
    simulate_as(params, out, FrameFormat::Png)
}

/// [`simulate`] with the frames written in `format`.
pub fn simulate_as(params: &SimParams, out: &Path, format: FrameFormat) -> Result<SimSummary, SimError> {
    let rig = SimRig::new(params)?;
    tagdeflect_sim::simulate_as(params, out, format, &Config::from_sim(&rig))
}
