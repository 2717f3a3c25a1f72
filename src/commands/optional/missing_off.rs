//! A full build: every command is in it, so none is missing (`missing.rs` stands here in a
//! build without some feature).

use anyhow::Result;
use clap::Subcommand;

/// No missing command.
#[derive(Subcommand)]
pub enum MissingCommand {}

impl MissingCommand {
    /// Nothing to run: the enum has no value.
    pub fn run(self) -> Result<()> {
        match self {}
    }
}
