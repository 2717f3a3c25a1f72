//! The commands a cargo feature brings (`simulate` and `demo`: `sim`; `archive` and
//! `archive-bench`: `archive`; `calibrate`: `calibrate`), each feature's commands one clap
//! [`Subcommand`](clap::Subcommand) enum flattened into the command line.
//!
//! A feature that is off leaves an `_off` twin in its module's place: the same commands,
//! hidden from the help, each failing with the feature it needs (exit 2), and the same
//! hooks, so `main.rs` carries no feature gate and a typo still gets clap's own error.

#[cfg(feature = "archive")]
pub mod archive;
#[cfg(not(feature = "archive"))]
#[path = "archive_off.rs"]
pub mod archive;
#[cfg(feature = "calibrate")]
pub mod calibrate;
#[cfg(not(feature = "calibrate"))]
#[path = "calibrate_off.rs"]
pub mod calibrate;
#[cfg(feature = "sim")]
pub mod sim;
#[cfg(not(feature = "sim"))]
#[path = "sim_off.rs"]
pub mod sim;

/// The error of a command this build was made without (an `_off` twin's).
#[cfg_attr(all(feature = "sim", feature = "archive", feature = "calibrate"), allow(dead_code))]
fn not_in_this_build(command: &str, feature: &str) -> anyhow::Error {
    anyhow::Error::new(tagdeflect_core::BadInput::new(format!(
        "`tagdeflect {command}` is not in this build: it needs the `{feature}` feature (cargo build --release --features {feature})"
    )))
}
