//! A build without the `sim` feature: `simulate` and `demo` say which feature they need
//! (`sim.rs` stands here with the feature).

use anyhow::Result;
use clap::Subcommand;

/// The feature's commands, hidden: each names the feature it needs.
#[derive(Subcommand)]
pub enum SimCommand {
    /// `tagdeflect simulate`: not in this build.
    #[command(hide = true, disable_help_flag = true)]
    Simulate {
        /// Whatever was given after the command.
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
    /// `tagdeflect demo`: not in this build.
    #[command(hide = true, disable_help_flag = true)]
    Demo {
        /// Whatever was given after the command.
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
}

impl SimCommand {
    /// The error: the command needs the `sim` feature (exit 2).
    pub fn run(self) -> Result<()> {
        let name = match self {
            SimCommand::Simulate { .. } => "simulate",
            SimCommand::Demo { .. } => "demo",
        };
        Err(super::not_in_this_build(name, "sim"))
    }
}

/// No simulator errors in this build.
pub fn is_bad_input(_c: &(dyn std::error::Error + 'static)) -> bool {
    false
}
