//! The errors of tag detection: bad detector or refinement options, and the AprilTag
//! library failing to create its objects.
//!
//! A module of its own below both [`crate::apriltag`] and [`crate::refine`], so that
//! refinement reports its option errors without importing the detector wrapper (the
//! wrapper calls refinement, never the reverse).

use thiserror::Error;

use tagdeflect_core::tags::TagFamily;

/// Errors of the detector wrapper and of the refinement options.
#[derive(Debug, Error)]
pub enum DetectError {
    /// The option set holds no tag family.
    #[error("detector options: no tag family given (expected at least one of tag36h11, tag25h9, tag16h5)")]
    NoFamily,
    /// A family was listed twice.
    #[error("detector options: tag family {0} listed twice")]
    DuplicateFamily(TagFamily),
    /// An option is out of range.
    #[error("detector option {name} = {value}: {expected}")]
    BadOption {
        /// Option name.
        name: &'static str,
        /// The value given.
        value: String,
        /// What is expected.
        expected: &'static str,
    },
    /// The C library returned a null pointer when creating an object.
    #[error("the AprilTag library failed to create {0} (out of memory?)")]
    Create(&'static str),
}
