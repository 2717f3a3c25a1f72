//! A build without the `calibrate` feature: no `calibrate` command (`calibrate.rs` stands
//! here with the feature).

use anyhow::Result;
use clap::Subcommand;

/// No calibration command in this build.
#[derive(Subcommand)]
pub enum CalibrateCommand {}

impl CalibrateCommand {
    /// Nothing to run: the enum has no value.
    pub fn run(self) -> Result<()> {
        match self {}
    }
}
