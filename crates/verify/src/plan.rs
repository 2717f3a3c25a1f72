//! The known positions of a verification and when each was held (`verify_steps.json`).

use serde::{Deserialize, Serialize};

use crate::VerifyError;

/// Name of the step plan in a recording folder (written by `simulate --verify-steps`, or by
/// the lab next to its recording).
pub const VERIFY_STEPS_FILE: &str = "verify_steps.json";

/// One known position of the rigid target: where it was (downward, mm, in the sense of a
/// deflection) and, when known, the time window it was held in (ns since the Unix epoch).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StepWindow {
    /// The reference's reading (micrometer, height gauge, crosshead), downward positive, mm.
    pub position_mm: f64,
    /// Start of the hold, ns since the Unix epoch (absent: the holds share the record evenly).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub start_ns: Option<i64>,
    /// End of the hold (exclusive), ns since the Unix epoch.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub end_ns: Option<i64>,
}

/// The steps of a verification in the order they were held.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StepPlan {
    /// The steps, in order.
    pub steps: Vec<StepWindow>,
    /// Fraction of each hold's lines left out at its start while the target and the
    /// temporal estimate settle (default 0.3).
    #[serde(default = "default_settle")]
    pub settle_fraction: f64,
}

fn default_settle() -> f64 {
    0.3
}

impl StepPlan {
    /// A plan of positions held one after another for equal times (no windows).
    pub fn from_positions(positions_mm: &[f64]) -> StepPlan {
        let steps = positions_mm.iter().map(|&p| StepWindow { position_mm: p, start_ns: None, end_ns: None }).collect();
        StepPlan { steps, settle_fraction: default_settle() }
    }

    /// Parses a plan from JSON: `{"steps": [...]}` or a bare array of positions in mm.
    pub fn from_json(text: &str) -> Result<StepPlan, VerifyError> {
        if let Ok(positions) = serde_json::from_str::<Vec<f64>>(text) {
            return Ok(StepPlan::from_positions(&positions));
        }
        serde_json::from_str(text).map_err(|e| VerifyError::Steps(e.to_string()))
    }

    /// Each step's position and its window `[start, end)` in ns; the record spans
    /// `[t0_ns, t1_ns]` (used when the steps give no windows: equal shares).
    pub fn windows(&self, t0_ns: i64, t1_ns: i64) -> Result<Vec<(f64, i64, i64)>, VerifyError> {
        if self.steps.is_empty() {
            return Err(VerifyError::Steps("no steps".into()));
        }
        if !(0.0..1.0).contains(&self.settle_fraction) {
            return Err(VerifyError::Steps(format!("settle_fraction {} is not in [0, 1)", self.settle_fraction)));
        }
        let timed = self.steps.iter().filter(|s| s.start_ns.is_some() && s.end_ns.is_some()).count();
        if timed == 0 {
            let n = self.steps.len() as i64;
            let span = t1_ns - t0_ns + 1;
            return Ok(self
                .steps
                .iter()
                .enumerate()
                .map(|(i, s)| (s.position_mm, t0_ns + span * i as i64 / n, t0_ns + span * (i as i64 + 1) / n))
                .collect());
        }
        if timed != self.steps.len() {
            return Err(VerifyError::Steps("either every step gives start_ns and end_ns or none does".into()));
        }
        let mut out = Vec::new();
        for (i, s) in self.steps.iter().enumerate() {
            let (a, b) = (s.start_ns.unwrap_or(0), s.end_ns.unwrap_or(0));
            if b <= a || !s.position_mm.is_finite() {
                return Err(VerifyError::Steps(format!(
                    "step {}: its window ends before it starts or its position is not a number",
                    i + 1
                )));
            }
            out.push((s.position_mm, a, b));
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn positions_share_the_record_and_windows_are_checked() {
        let p = StepPlan::from_json("[0, 0.5, 1]").unwrap();
        let w = p.windows(0, 299).unwrap();
        assert_eq!(w, vec![(0.0, 0, 100), (0.5, 100, 200), (1.0, 200, 300)]);
        let bad = StepPlan::from_json(r#"{"steps":[{"position_mm":0,"start_ns":5,"end_ns":5}]}"#).unwrap();
        assert!(matches!(bad.windows(0, 10), Err(VerifyError::Steps(_))));
        assert!(StepPlan::from_json("{}").is_err());
    }
}
