//! `tagdeflect archive` and `archive-bench` (the `archive` feature).

use anyhow::Result;
use clap::Subcommand;

/// The archive's commands.
#[derive(Subcommand)]
pub enum ArchiveCommand {
    /// Subscribe to the feeds rigs publish over MQTT and keep them in PostgreSQL.
    Archive(tagdeflect_archive::ArchiveOptions),
    /// Measure how many feed lines per second one archive ingests (simulated rigs).
    ArchiveBench(tagdeflect_archive::bench::ArchiveBenchOptions),
}

impl ArchiveCommand {
    /// Runs the command.
    pub fn run(self) -> Result<()> {
        match self {
            ArchiveCommand::Archive(opts) => tagdeflect_archive::run(opts).map_err(archive_error),
            ArchiveCommand::ArchiveBench(opts) => tagdeflect_archive::bench::run(&opts).map_err(archive_error),
        }
    }
}

/// An archive error with its exit code (bad options exit 2, a failure of the machine 1).
fn archive_error(e: tagdeflect_archive::ArchiveError) -> anyhow::Error {
    if e.is_bad_input() {
        anyhow::Error::new(tagdeflect_core::BadInput::new(e.to_string()))
    } else {
        anyhow::Error::new(tagdeflect_core::RuntimeFailure::new(e.to_string()))
    }
}
