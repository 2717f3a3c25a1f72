//! Why a solve failed.

/// Why a solve failed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SolveError {
    /// Not enough usable observations.
    #[error("{what}: too few corners ({got}, need at least {needed})")]
    TooFewCorners {
        /// Which solve.
        what: String,
        /// Corners needed.
        needed: usize,
        /// Corners given (finite ones).
        got: usize,
    },
    /// The geometry does not determine a pose.
    #[error("degenerate geometry: {what}")]
    Degenerate {
        /// What failed and where.
        what: String,
    },
    /// An argument is out of range.
    #[error("invalid input: {what}")]
    InvalidInput {
        /// What is wrong.
        what: String,
    },
}
