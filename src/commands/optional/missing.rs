//! A build without some feature: a command it lacks is named with the feature it needs,
//! and exits 2 (`missing_off.rs` stands here in a full build, which keeps clap's own error,
//! with its suggestion, for a typo).

use anyhow::Result;
use clap::Subcommand;

/// The commands that need a cargo feature, and the feature.
const FEATURE_COMMANDS: &[(&str, &str)] =
    &[("simulate", "sim"), ("demo", "sim"), ("archive", "archive"), ("archive-bench", "archive"), ("calibrate", "calibrate")];

/// Any command clap does not know.
#[derive(Subcommand)]
pub enum MissingCommand {
    /// A command this build was made without (its feature is named in the error).
    #[command(external_subcommand)]
    Missing(Vec<String>),
}

impl MissingCommand {
    /// The error for a command this build does not have.
    pub fn run(self) -> Result<()> {
        let MissingCommand::Missing(args) = self;
        let name = args.first().map(String::as_str).unwrap_or("");
        Err(match FEATURE_COMMANDS.iter().find(|(c, _)| *c == name) {
            Some((c, f)) => anyhow::Error::new(tagdeflect_core::BadInput::new(format!(
                "`tagdeflect {c}` is not in this build: it needs the `{f}` feature (cargo build --release --features {f})"
            ))),
            None => anyhow::Error::new(tagdeflect_core::BadInput::new(format!("unknown command \"{name}\" (see `tagdeflect --help`)"))),
        })
    }
}
