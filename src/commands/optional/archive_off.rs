//! A build without the `archive` feature: `archive` and `archive-bench` say which feature
//! they need (`archive.rs` stands here with the feature).

use anyhow::Result;
use clap::Subcommand;

/// The feature's commands, hidden: each names the feature it needs.
#[derive(Subcommand)]
pub enum ArchiveCommand {
    /// `tagdeflect archive`: not in this build.
    #[command(hide = true, disable_help_flag = true)]
    Archive {
        /// Whatever was given after the command.
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
    /// `tagdeflect archive-bench`: not in this build.
    #[command(hide = true, disable_help_flag = true)]
    ArchiveBench {
        /// Whatever was given after the command.
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
}

impl ArchiveCommand {
    /// The error: the command needs the `archive` feature (exit 2).
    pub fn run(self) -> Result<()> {
        let name = match self {
            ArchiveCommand::Archive { .. } => "archive",
            ArchiveCommand::ArchiveBench { .. } => "archive-bench",
        };
        Err(super::not_in_this_build(name, "archive"))
    }
}
