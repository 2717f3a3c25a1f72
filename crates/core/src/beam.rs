//! `[specimen.beam]`: the specimen's geometry, for the report's stresses.

use serde::{Deserialize, Serialize};

/// `[specimen.beam]` (SPEC): width, depth and span of the beam, and the notch of a
/// notched beam (three-point tests). Millimetres.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BeamConfig {
    /// Width `b`, mm.
    pub width_mm: f64,
    /// Depth `d` (or `h`), mm; for a notched beam the height above the notch is
    /// `depth_mm - notch_mm`.
    pub depth_mm: f64,
    /// Span `L` between the supports, mm.
    pub span_mm: f64,
    /// Notch depth of a notched beam, mm.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub notch_mm: Option<f64>,
    /// Tolerance of the measured width (± mm; the report takes it as the half-width of a
    /// uniform distribution, σ = tol/√3). Absent: the width is taken as exact.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub width_tol_mm: Option<f64>,
    /// Tolerance of the measured depth, ± mm.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub depth_tol_mm: Option<f64>,
    /// Tolerance of the span, ± mm.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub span_tol_mm: Option<f64>,
    /// Tolerance of the measured notch depth, ± mm.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub notch_tol_mm: Option<f64>,
}

impl BeamConfig {
    /// Checks the values (positive lengths, a notch above zero and below the depth, a span
    /// longer than the depth); keys are relative to `[specimen.beam]`.
    pub fn validate(&self) -> Result<(), crate::Problem> {
        use crate::Problem;
        for (k, v) in [("width_mm", self.width_mm), ("depth_mm", self.depth_mm), ("span_mm", self.span_mm)] {
            if !(v.is_finite() && v > 0.0) {
                return Err(Problem::new(k, format!("must be a positive length in mm, got {v}")));
            }
        }
        if let Some(n) = self.notch_mm {
            if !(n.is_finite() && n > 0.0 && n < self.depth_mm) {
                return Err(Problem::new("notch_mm", format!("must be a positive depth below depth_mm = {}, got {n}", self.depth_mm)));
            }
        }
        for (k, v) in [
            ("width_tol_mm", self.width_tol_mm),
            ("depth_tol_mm", self.depth_tol_mm),
            ("span_tol_mm", self.span_tol_mm),
            ("notch_tol_mm", self.notch_tol_mm),
        ] {
            if let Some(v) = v {
                if !(v.is_finite() && v >= 0.0 && v < 0.5 * self.depth_mm.min(self.width_mm)) {
                    return Err(Problem::new(k, format!("must be a tolerance in mm, ≥ 0 and well below the dimension, got {v}")));
                }
            }
        }
        if self.span_mm < self.depth_mm {
            return Err(Problem::new(
                "span_mm",
                format!("span {} mm is shorter than the depth {} mm: not a beam in bending", self.span_mm, self.depth_mm),
            ));
        }
        Ok(())
    }

    /// Standard uncertainties `(width, depth, span, notch)` from the tolerances, mm
    /// (uniform within ± tolerance: σ = tol/√3; 0 without a tolerance).
    pub fn sigmas_mm(&self) -> (f64, f64, f64, f64) {
        let u = |t: Option<f64>| t.unwrap_or(0.0) / 3f64.sqrt();
        (u(self.width_tol_mm), u(self.depth_tol_mm), u(self.span_tol_mm), u(self.notch_tol_mm))
    }

    /// Height of the ligament above the notch (`depth - notch`), mm.
    pub fn ligament_mm(&self) -> f64 {
        self.depth_mm - self.notch_mm.unwrap_or(0.0)
    }
}
