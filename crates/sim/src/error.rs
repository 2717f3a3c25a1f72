//! The simulator's error.

/// An invalid simulation option or a failure while writing the simulated recording.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    /// An option is out of range.
    #[error("simulation option `{option}`: {message}")]
    Param {
        /// The option (as in `[sim]` and `--<option>`).
        option: String,
        /// What is wrong and what is expected.
        message: String,
    },
    /// Writing the recording failed.
    #[error("writing the simulated recording: {0}")]
    Recording(#[from] tagdeflect_io::recording::RecordingError),
    /// Writing an extra truth file failed.
    #[error("writing {path}: {source}")]
    Io {
        /// The file.
        path: std::path::PathBuf,
        /// The cause.
        source: std::io::Error,
    },
}

impl From<tagdeflect_core::Problem> for SimError {
    fn from(p: tagdeflect_core::Problem) -> Self {
        SimError::Param { option: p.key, message: p.message }
    }
}
