//! What a test run under control carries into its folder (`control.json`, docs/control.md
//! "A test under control"): the signal served to the testing machine's controller, how often
//! it was valid, its longest invalid stretch and why, the exposure → write latency measured
//! live during the test, and the signal's dynamics through the temporal estimate. Written by
//! the binary at the test's stop (before its report), read by the report's "Control output"
//! section.

use serde::{Deserialize, Serialize};

/// The file in a test folder.
pub const CONTROL_FILE: &str = "control.json";

/// A test's control outputs (`control.json`).
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct ControlSummary {
    /// The test's id.
    pub test: String,
    /// One entry per control output that served the test (`analog`, `registers`).
    pub outputs: Vec<OutputSummary>,
    /// The signal's dynamics through the temporal estimate, computed at the stop.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dynamics: Option<Dynamics>,
}

/// One control output during a test.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct OutputSummary {
    /// `"analog"` (`[output.analog]`) or `"registers"` (`[output.control]`).
    pub kind: String,
    /// Where it goes, in words (the device's address, map and channel; the server's address).
    pub target: String,
    /// The signal: `net_deflection` or a `[[gauge]]`'s name.
    pub gauge: String,
    /// Largest σ of a valid value, mm.
    pub max_sigma_mm: f64,
    /// Frame sets without the value before it is stale.
    pub stale_sets: u32,
    /// The analog scaling (absent for the registers).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scaling: Option<AnalogScaling>,
    /// Frame sets of the test that reached the output.
    pub frame_sets: u64,
    /// Of those, frame sets after which the valid line was high (the value valid and, for a
    /// device, the device answering).
    pub valid_sets: u64,
    /// Stretches of invalid frame sets (or of time without frame sets).
    pub invalid_stretches: u64,
    /// The longest of them.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub longest_invalid: Option<InvalidStretch>,
    /// Exposure → write acknowledged by the device (the registers: → register updated),
    /// measured live on the test's frame sets.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub latency: Option<Latency>,
    /// Values written to the device during the test (acknowledged).
    #[serde(default)]
    pub values_written: u64,
    /// Values replaced by a newer one before their write.
    #[serde(default)]
    pub superseded: u64,
    /// Device outages that began during the test.
    #[serde(default)]
    pub outages: u64,
}

impl OutputSummary {
    /// Share of the test's frame sets with the valid line high, 0–1 (`None` without sets).
    pub fn valid_share(&self) -> Option<f64> {
        (self.frame_sets > 0).then(|| self.valid_sets as f64 / self.frame_sets as f64)
    }
}

/// `[output.analog]`'s scaling as configured.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct AnalogScaling {
    /// Volts per mm of the value.
    pub volts_per_mm: f64,
    /// Volts at a value of 0.
    pub offset_v: f64,
    /// The output's range (the clamp), V.
    pub range_v: [f64; 2],
    /// The safe voltage written while invalid and at stop; `None`: the last value is held.
    #[serde(default)]
    pub safe_v: Option<f64>,
}

/// A stretch of frame sets during which the valid line was low.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct InvalidStretch {
    /// Its first frame set's time (or the last set's before a stall), ns since the epoch.
    pub from_t_ns: i64,
    /// How long, ms (to the next valid frame set, or the test's end).
    pub duration_ms: f64,
    /// Frame sets in it.
    pub frame_sets: u64,
    /// Why, in words (the first cause seen in it).
    pub cause: String,
}

/// Latency figures, ms.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct Latency {
    /// Values timed.
    pub values: u64,
    /// Median, ms.
    pub p50_ms: f64,
    /// 99th percentile, ms.
    pub p99_ms: f64,
    /// Worst, ms.
    pub max_ms: f64,
}

impl Latency {
    /// The figures of `ms` (any order); `None` when empty.
    pub fn of(mut ms: Vec<f64>) -> Option<Latency> {
        ms.retain(|v| v.is_finite());
        if ms.is_empty() {
            return None;
        }
        ms.sort_by(f64::total_cmp);
        let q = |p: f64| ms[((ms.len() - 1) as f64 * p).round() as usize];
        Some(Latency { values: ms.len() as u64, p50_ms: q(0.5), p99_ms: q(0.99), max_ms: q(1.0) })
    }
}

/// The temporal estimate's response (`bench --dynamics`'s figures).
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct Dynamics {
    /// How they were found, in words.
    pub how: String,
    /// Frame sets per second they were computed at.
    pub sets_per_s: f64,
    /// Sinusoids.
    pub sines: Vec<SineResponse>,
    /// The step.
    pub step: StepFigures,
}

/// The estimate's response to a sinusoidal net deflection at one frequency.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct SineResponse {
    /// Frequency, Hz.
    pub freq_hz: f64,
    /// Amplitude out / amplitude in.
    pub gain: f64,
    /// Phase lag of the output behind the truth, degrees (positive: late).
    pub phase_lag_deg: f64,
    /// The same as a delay, ms.
    pub delay_ms: f64,
    /// RMS of the output against the fitted sinusoid, mm (what is not the sinusoid).
    pub residual_rms_mm: f64,
}

/// The estimate's response to a step of the net deflection.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct StepFigures {
    /// The step, mm.
    pub step_mm: f64,
    /// From the step to the first output beyond 10 % of it, ms.
    pub to_10_percent_ms: f64,
    /// From the step to the first output beyond 90 % of it, ms.
    pub to_90_percent_ms: f64,
    /// 10–90 % rise time, ms (at the frame rate's resolution).
    pub rise_10_90_ms: f64,
    /// Largest output beyond the step in the second after it, % of the step.
    pub overshoot_percent: f64,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn latency_figures_are_the_order_statistics() {
        let l = Latency::of((1..=100).rev().map(f64::from).collect()).expect("figures");
        assert_eq!((l.values, l.p50_ms, l.p99_ms, l.max_ms), (100, 51.0, 99.0, 100.0));
        assert!(Latency::of(vec![f64::NAN]).is_none());
    }
}
