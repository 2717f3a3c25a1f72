//! A build without the `sim` feature: no `simulate` or `demo` command (`sim.rs` stands here
//! with the feature).

use anyhow::Result;
use clap::Subcommand;

/// No simulator commands in this build.
#[derive(Subcommand)]
pub enum SimCommand {}

impl SimCommand {
    /// Nothing to run: the enum has no value.
    pub fn run(self) -> Result<()> {
        match self {}
    }
}

/// No simulator errors in this build.
pub fn is_bad_input(_c: &(dyn std::error::Error + 'static)) -> bool {
    false
}
