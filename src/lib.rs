//! tagdeflect: non-contact deflection measurement of beams in bending with AprilTags.
//!
//! Data flows one way: sources → frames → [`sync`] → frame sets → [`detect`] →
//! observations → [`solve`] → solutions → sinks. Live capture and replay are the same
//! graph with different sources (see [`pipeline`]).

pub mod accuracy;
pub mod archive;
pub mod backoff;
pub mod calibrate;
pub mod camera;
pub mod clock;
pub mod config;
pub mod detect;
pub mod feed;
pub mod frame;
pub mod fuzzing;
pub mod pipeline;
pub mod recording;
pub mod report;
pub mod sim;
pub mod sinks;
pub mod solve;
pub mod sources;
pub mod sync;
pub mod tags;
pub mod utm;

/// Bad input — a config value a component cannot take, a recording that cannot be read:
/// the command line exits 2 with this message (as for config and recording errors), and
/// systemd does not restart the daemon (`RestartPreventExitStatus=2`).
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct BadInput(String);

impl BadInput {
    /// A bad-input error with its message (say what and where).
    pub fn new(message: impl Into<String>) -> Self {
        Self(message.into())
    }
}

/// A failure of a running daemon that a restart may cure (a thread that died): the command
/// line exits 1, and systemd restarts the daemon (`Restart=on-failure`).
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct RuntimeFailure(String);

impl RuntimeFailure {
    /// A runtime failure with its message.
    pub fn new(message: impl Into<String>) -> Self {
        Self(message.into())
    }
}
