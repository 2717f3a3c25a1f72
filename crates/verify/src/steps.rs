//! At known displacements: each step's error, the bias, linearity, repeatability and
//! hysteresis.

use serde::{Deserialize, Serialize};

use crate::series::{line_fit, mean, sd};

/// How a step's position was approached.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Approach {
    /// The first step (the reference).
    First,
    /// From a smaller position (the target moved down).
    Increasing,
    /// From a larger position.
    Decreasing,
}

/// One held step as measured.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StepResult {
    /// Step number from 1.
    pub step: usize,
    /// The reference's position, mm.
    pub position_mm: f64,
    /// The known displacement from the first step, mm (ISO 9513's `l_t`).
    pub nominal_mm: f64,
    /// How it was approached.
    pub approach: Approach,
    /// Feed lines averaged (after the settling lines).
    pub lines: usize,
    /// Mean measured displacement from the first step, mm.
    pub measured_mm: f64,
    /// Standard deviation of one reading in the hold, mm.
    pub sd_mm: Option<f64>,
    /// `measured_mm − nominal_mm`, mm.
    pub error_mm: f64,
    /// Mean net deflection in the hold, mm (a rigid target: zero).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub net_deflection_mm: Option<f64>,
}

/// The known-displacement figures over all steps.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct KnownFigures {
    /// Smallest and largest known displacement, mm.
    pub range_mm: [f64; 2],
    /// Mean error over the steps, mm.
    pub bias_mm: f64,
    /// Largest |error|, mm.
    pub max_error_mm: f64,
    /// Slope of the best-fit line measured vs known (1 = no scale error).
    pub slope: Option<f64>,
    /// Largest deviation of a step from the best-fit line, mm.
    pub linearity_mm: Option<f64>,
    /// Largest standard deviation over the repeats of a position, mm (`None`: no repeats).
    pub repeatability_mm: Option<f64>,
    /// Largest |increasing − decreasing| mean error at one position, mm (`None`: no position
    /// approached both ways).
    pub hysteresis_mm: Option<f64>,
}

/// Builds a step's result from its hold's readings (downward displacement and net
/// deflection, mm); `None` when the hold has no reading.
pub fn step_result(
    step: usize,
    position_mm: f64,
    first_mm: f64,
    previous_mm: Option<f64>,
    displacement_mm: &[f64],
    net_mm: &[f64],
) -> Option<StepResult> {
    let measured_mm = mean(displacement_mm)?;
    let approach = match previous_mm {
        None => Approach::First,
        Some(p) if position_mm >= p => Approach::Increasing,
        Some(_) => Approach::Decreasing,
    };
    let nominal_mm = position_mm - first_mm;
    Some(StepResult {
        step,
        position_mm,
        nominal_mm,
        approach,
        lines: displacement_mm.len(),
        measured_mm,
        sd_mm: sd(displacement_mm),
        error_mm: measured_mm - nominal_mm,
        net_deflection_mm: mean(net_mm),
    })
}

/// The figures over the steps (at least one).
pub fn known_figures(steps: &[StepResult]) -> KnownFigures {
    let nominal: Vec<f64> = steps.iter().map(|s| s.nominal_mm).collect();
    let measured: Vec<f64> = steps.iter().map(|s| s.measured_mm).collect();
    let errors: Vec<f64> = steps.iter().map(|s| s.error_mm).collect();
    let fit = line_fit(&nominal, &measured);
    let linearity_mm = fit.map(|(a, b)| nominal.iter().zip(&measured).map(|(x, y)| (y - a - b * x).abs()).fold(0.0, f64::max));
    KnownFigures {
        range_mm: [nominal.iter().copied().fold(f64::INFINITY, f64::min), nominal.iter().copied().fold(f64::NEG_INFINITY, f64::max)],
        bias_mm: mean(&errors).unwrap_or(0.0),
        max_error_mm: errors.iter().map(|e| e.abs()).fold(0.0, f64::max),
        slope: fit.map(|(_, b)| b),
        linearity_mm,
        repeatability_mm: by_position(steps, |group| sd(&group.iter().map(|s| s.measured_mm).collect::<Vec<_>>())),
        hysteresis_mm: by_position(steps, hysteresis),
    }
}

/// The largest of `figure` over the groups of steps at one position (`None` if no group gives one).
fn by_position(steps: &[StepResult], figure: impl Fn(&[&StepResult]) -> Option<f64>) -> Option<f64> {
    let mut positions: Vec<f64> = steps.iter().map(|s| s.position_mm).collect();
    positions.sort_by(f64::total_cmp);
    positions.dedup_by(|a, b| (*a - *b).abs() < 1e-9);
    positions
        .iter()
        .filter_map(|p| {
            let group: Vec<&StepResult> = steps.iter().filter(|s| (s.position_mm - p).abs() < 1e-9).collect();
            figure(&group)
        })
        .reduce(f64::max)
}

/// |mean error reached increasing − mean error reached decreasing| at one position (the
/// first step counts on both sides: it is reached from nothing).
fn hysteresis(group: &[&StepResult]) -> Option<f64> {
    let side = |a: Approach| {
        mean(&group.iter().filter(|s| s.approach == a || s.approach == Approach::First).map(|s| s.error_mm).collect::<Vec<_>>())
    };
    let has = |a: Approach| group.iter().any(|s| s.approach == a);
    if !(has(Approach::Increasing) || has(Approach::First)) || !has(Approach::Decreasing) {
        return None;
    }
    Some((side(Approach::Increasing)? - side(Approach::Decreasing)?).abs())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bias_linearity_repeatability_and_hysteresis_by_hand() {
        // 0 → 1 → 2 → 1 → 0 with errors 0, +2 µm, +1 µm, −2 µm, 0.
        let plan = [(0.0, 0.0), (1.0, 0.002), (2.0, 0.001), (1.0, -0.002), (0.0, 0.0)];
        let mut prev = None;
        let steps: Vec<StepResult> = plan
            .iter()
            .enumerate()
            .map(|(i, &(p, e))| {
                let r = step_result(i + 1, p, 0.0, prev, &[p + e, p + e], &[]).unwrap();
                prev = Some(p);
                r
            })
            .collect();
        assert_eq!(steps[3].approach, Approach::Decreasing);
        let k = known_figures(&steps);
        assert!((k.bias_mm - 0.0002).abs() < 1e-12);
        assert!((k.max_error_mm - 0.002).abs() < 1e-12);
        assert!((k.hysteresis_mm.unwrap() - 0.004).abs() < 1e-12);
        assert!((k.repeatability_mm.unwrap() - 0.004 / 2f64.sqrt()).abs() < 1e-12);
        // The best line of the errors: slope 0.0012 / 2.8, at x = 1 it is 2/7000 mm; the
        // decreasing step at 1 mm lies 0.002 + 2/7000 mm below it.
        let lin = k.linearity_mm.unwrap();
        assert!((lin - (0.002 + 2.0 / 7000.0)).abs() < 1e-12, "{lin}");
    }
}
