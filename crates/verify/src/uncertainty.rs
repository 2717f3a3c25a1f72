//! The expanded uncertainty (k = 2) of a deflection over the verified range, by the GUM:
//! the standard uncertainties of the components combined in quadrature.
//!
//! | component | standard uncertainty | from |
//! | --- | --- | --- |
//! | bias | `max |error| / √3` | the steps (left uncorrected: a rectangular distribution of half-width the largest error) |
//! | repeatability | the largest SD over repeats of a position | the steps |
//! | noise of one reading | SD at rest | the static hold |
//! | digit | `0.01 µm / (2√3)` | the feed's rounding |
//! | reference | `U_ref / k_ref` | as typed (the equipment's certificate) |

use serde::{Deserialize, Serialize};

use crate::iso9513::FEED_DIGIT_MM;

/// One component of the budget.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Component {
    /// What it is.
    pub name: String,
    /// Its standard uncertainty, mm.
    pub u_mm: f64,
}

/// The budget and its result.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Uncertainty {
    /// The components.
    pub components: Vec<Component>,
    /// Combined standard uncertainty, mm.
    pub combined_mm: f64,
    /// Coverage factor.
    pub k: f64,
    /// Expanded uncertainty `k × combined`, mm.
    pub expanded_mm: f64,
    /// The range of deflections it holds for, mm.
    pub range_mm: [f64; 2],
}

/// What the budget is built from (all mm).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Inputs {
    /// Largest |error| of a step.
    pub max_error_mm: f64,
    /// Largest SD over repeats of a position (0 when no position was repeated).
    pub repeatability_mm: f64,
    /// SD of one reading at rest.
    pub noise_mm: f64,
    /// The reference's expanded uncertainty as typed.
    pub reference_u_mm: f64,
    /// Its coverage factor.
    pub reference_k: f64,
    /// The verified range.
    pub range_mm: [f64; 2],
}

/// The budget of `inputs`, expanded with k = 2.
pub fn budget(inputs: &Inputs) -> Uncertainty {
    let components = vec![
        Component { name: "bias (largest step error, rectangular)".into(), u_mm: inputs.max_error_mm / 3f64.sqrt() },
        Component { name: "repeatability (SD over repeats of a position)".into(), u_mm: inputs.repeatability_mm },
        Component { name: "noise of one reading (SD at rest)".into(), u_mm: inputs.noise_mm },
        Component { name: "digit of the feed (0.01 µm, rectangular)".into(), u_mm: FEED_DIGIT_MM / (2.0 * 3f64.sqrt()) },
        Component { name: "reference (as typed)".into(), u_mm: inputs.reference_u_mm / inputs.reference_k.max(1.0) },
    ];
    let combined_mm = components.iter().map(|c| c.u_mm * c.u_mm).sum::<f64>().sqrt();
    Uncertainty { components, combined_mm, k: 2.0, expanded_mm: 2.0 * combined_mm, range_mm: inputs.range_mm }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn components_add_in_quadrature() {
        let u = budget(&Inputs {
            max_error_mm: 3f64.sqrt() * 0.003,
            repeatability_mm: 0.004,
            noise_mm: 0.0,
            reference_u_mm: 0.0,
            reference_k: 2.0,
            range_mm: [0.0, 1.0],
        });
        let digit = FEED_DIGIT_MM / (2.0 * 3f64.sqrt());
        assert!((u.combined_mm - (0.005f64.powi(2) + digit * digit).sqrt()).abs() < 1e-12);
        assert!((u.expanded_mm - 2.0 * u.combined_mm).abs() < 1e-15);
    }
}
