//! A build without the `calibrate` feature: `calibrate` says which feature it needs
//! (`calibrate.rs` stands here with the feature).

use anyhow::Result;
use clap::Subcommand;

/// The feature's commands, hidden: each names the feature it needs.
#[derive(Subcommand)]
pub enum CalibrateCommand {
    /// `tagdeflect calibrate`: not in this build.
    #[command(hide = true, disable_help_flag = true)]
    Calibrate {
        /// Whatever was given after the command.
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
}

impl CalibrateCommand {
    /// The error: the command needs the `calibrate` feature (exit 2).
    pub fn run(self) -> Result<()> {
        let name = match self {
            CalibrateCommand::Calibrate { .. } => "calibrate",
        };
        Err(super::not_in_this_build(name, "calibrate"))
    }
}
