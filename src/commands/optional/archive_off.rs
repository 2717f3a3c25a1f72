//! A build without the `archive` feature: no `archive` or `archive-bench` command
//! (`archive.rs` stands here with the feature).

use anyhow::Result;
use clap::Subcommand;

/// No archive commands in this build.
#[derive(Subcommand)]
pub enum ArchiveCommand {}

impl ArchiveCommand {
    /// Nothing to run: the enum has no value.
    pub fn run(self) -> Result<()> {
        match self {}
    }
}
