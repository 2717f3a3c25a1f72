//! What a test is started with ([`TestMeta`], checked as an operator typed it; the type is
//! core's, as `test.json` is read by the archive too) and why a command is refused
//! ([`TestError`]).

pub use tagdeflect_core::lab_test::{TestMeta, STANDARDS};
use tagdeflect_core::Problem;

/// Why a command was refused.
#[derive(Debug, thiserror::Error)]
pub enum TestError {
    /// The command does not fit the state (start while running, stop while idle): HTTP 409.
    #[error("{0}")]
    Conflict(String),
    /// The previous test is still being stopped (its last line, folder and report) after a
    /// start waited [`START_WAIT`](super::START_WAIT) for it: HTTP 409 with `Retry-After`
    /// ([`START_RETRY_AFTER_S`](super::START_RETRY_AFTER_S)).
    #[error("{0}")]
    Stopping(String),
    /// The request is malformed: HTTP 400.
    #[error("{0}")]
    Bad(String),
    /// The folder could not be written: HTTP 500.
    #[error("{0}")]
    Io(String),
}

impl From<Problem> for TestError {
    /// A request that does not pass [`TestMeta::validate`]: malformed (its message as is).
    fn from(p: Problem) -> Self {
        TestError::Bad(p.message)
    }
}
