//! The kinds of failure the command line tells apart by exit code.

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

/// A result not fit to measure with, though the command did its work: a calibration whose
/// verdict is POOR, a `check` whose camera poses fit worse than stated. The command line exits
/// 3, so a script stops on it; what was written stays written.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct NotFit(String);

impl NotFit {
    /// A not-fit verdict with its message (what, by how much, against which limit).
    pub fn new(message: impl Into<String>) -> Self {
        Self(message.into())
    }
}
