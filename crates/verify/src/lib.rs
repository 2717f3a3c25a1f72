//! Verification of the instrument (docs/verification.md): from a recording's feed and the
//! known positions a rigid target was held at, the figures a lab puts on a certificate.
//!
//! * [`stability`]: at rest — the noise of every tag and of the net deflection, the drift
//!   per hour, the Allan deviation at 1, 10 and 100 s;
//! * [`steps`]: at known displacements — each step's error, the bias, linearity,
//!   repeatability and hysteresis;
//! * [`iso9513`]: the class by ISO 9513's table (bias and resolution against the limits);
//! * [`uncertainty`]: the expanded uncertainty (k = 2) of a deflection over the verified
//!   range (GUM, the components as typed);
//! * [`reference`]: SPEC's reference file (`{"t_ns", "displacement_mm"}` lines) grouped into
//!   holds, the step plan of a verification; [`stroke`]: holds read from the UTM's stroke;
//! * [`Quantity`]: the verified quantity (net deflection, a gauge, a tag);
//! * [`verify()`]: all of it, VDI/VDE 2626's ZS/ZD/D figures and a verdict with its reasons.
//!
//! The crate does arithmetic only: it reads no files and knows no command line.

pub mod iso9513;
mod plan;
mod quantity;
pub mod reference;
mod series;
pub mod stability;
pub mod steps;
pub mod stroke;
pub mod uncertainty;
mod verify;

pub use plan::{StepPlan, StepWindow, VERIFY_STEPS_FILE};
pub use quantity::Quantity;
pub use reference::{Hold, ReferencePoint, REFERENCE_FILE};
pub use series::Series;
pub use stroke::{holds_from_stroke, StrokeHolds};
pub use verify::{verify, VdiFigures, Verdict, Verification, VerifyOptions};

/// What keeps a verification from being computed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum VerifyError {
    /// The step plan is unusable (no steps, a window that ends before it starts, ...).
    #[error("steps: {0}")]
    Steps(String),
    /// The feed has too little in it (no lines, a step window without a solved line, ...).
    #[error("feed: {0}")]
    Feed(String),
}
