//! Errors of the report.

use std::path::PathBuf;

/// Errors of the report.
#[derive(Debug, thiserror::Error)]
pub enum ReportError {
    /// A feed (or UTM) line that cannot be read.
    #[error("{}:{line}: {message}", path.display())]
    BadLine {
        /// The feed file.
        path: PathBuf,
        /// 1-based line.
        line: usize,
        /// What is wrong.
        message: String,
    },
    /// A file that cannot be read or written.
    #[error("{}: {message}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// What failed.
        message: String,
    },
    /// The feed lacks what the standard needs.
    #[error("{}: {message}", path.display())]
    Data {
        /// The feed file.
        path: PathBuf,
        /// What is missing.
        message: String,
    },
    /// The config lacks what the report needs.
    #[error("{}: {message}", path.display())]
    Config {
        /// The config file.
        path: PathBuf,
        /// What is missing.
        message: String,
    },
    /// Drawing a plot failed.
    #[error("plot {name}: {message}")]
    Plot {
        /// The plot.
        name: String,
        /// What failed.
        message: String,
    },
}
