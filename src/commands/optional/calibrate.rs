//! `tagdeflect calibrate` (the `calibrate` feature); the command's work is
//! [`crate::commands::calibrate`].

use anyhow::Result;
use clap::Subcommand;

/// The calibration's command.
#[derive(Subcommand)]
pub enum CalibrateCommand {
    /// Camera intrinsics from views of a target (images or a live camera); writes an OpenCV
    /// FileStorage YAML and reports uncertainties, coverage and outliers.
    Calibrate(tagdeflect_calibrate::CalibrateOptions),
}

impl CalibrateCommand {
    /// Runs the command.
    pub fn run(self) -> Result<()> {
        match self {
            CalibrateCommand::Calibrate(opts) => crate::commands::calibrate::run(&opts),
        }
    }
}
