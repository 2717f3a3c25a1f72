//! `bench --dynamics`: the control signal's dynamics (docs/control.md "Dynamics"): the
//! temporal estimate's gain and phase lag on a sinusoidal net deflection, its step response,
//! and — with `--analog ADDR`, a DAQ (or `tests/fixtures/analog_device.py labjack PORT`) —
//! what the analog output's valid line does on a lost camera, a stalled pipeline and a
//! device fault (`dynamics_valid.rs`).
//!
//! The sinusoid and the step are simulated as the closed-loop test does: the specimen's true
//! net deflection with 2 µm of white noise (the measured noise of a rendered scene) through
//! the temporal estimator ([`TagFilter`]) at 30 frame sets/s, its output against the truth.
//! The rendered-camera pipeline's own latency is `bench --realtime`'s figure (exposure →
//! register or DAC write); at frequency f it adds 360° × f × latency of phase lag.

use nalgebra::{Matrix3, Vector3};
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use serde::Serialize;
use tagdeflect_estimate::temporal::{TagFilter, TemporalConfig};

/// Frame sets per second of the simulated signal.
pub const DYNAMICS_FPS: f64 = 30.0;
/// White noise of the simulated measurement, mm (a rendered scene's, docs/control.md).
pub const NOISE_MM: f64 = 0.002;
/// Amplitude of the sinusoids, mm.
pub const SINE_AMPLITUDE_MM: f64 = 0.05;
/// Height of the step, mm.
pub const STEP_MM: f64 = 0.05;
/// Settling time before a sinusoid is fitted, s.
const SETTLE_S: f64 = 2.0;

/// The estimate's response to a sinusoidal net deflection at one frequency.
#[derive(Debug, Clone, Serialize)]
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
#[derive(Debug, Clone, Serialize)]
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

/// Runs `truth(t_s)` through the temporal estimator at [`DYNAMICS_FPS`] for `duration_s`
/// with [`NOISE_MM`] of noise: (t s, truth mm, output mm) per frame set.
fn through_estimate(truth: impl Fn(f64) -> f64, duration_s: f64, seed: u64) -> Vec<(f64, f64, f64)> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let noise = Normal::new(0.0, NOISE_MM).expect("a positive σ");
    let cov = Matrix3::identity() * NOISE_MM.powi(2);
    let mut filter: Option<TagFilter> = None;
    let sets = (duration_s * DYNAMICS_FPS).round() as usize;
    let mut out = Vec::with_capacity(sets);
    for k in 0..sets {
        let t_s = k as f64 / DYNAMICS_FPS;
        let t_ns = (t_s * 1e9).round() as i64;
        let x = truth(t_s);
        let z = Vector3::new(noise.sample(&mut rng), noise.sample(&mut rng), x + noise.sample(&mut rng));
        let y = match filter.as_mut() {
            Some(f) => f.update(t_ns, z, &cov, &cov, false).centre.z,
            None => {
                let f = TagFilter::new(TemporalConfig::default(), t_ns, z, &cov);
                let y = f.centre().z;
                filter = Some(f);
                y
            }
        };
        out.push((t_s, x, y));
    }
    out
}

/// Gain and phase lag of the estimate on `SINE_AMPLITUDE_MM · sin(2π f t)`: the output
/// fitted (least squares) with a sin + b cos + c over whole periods after [`SETTLE_S`].
pub fn sine_response(freq_hz: f64, seed: u64) -> SineResponse {
    let periods = (2.0 * freq_hz).ceil().max(2.0) / freq_hz; // ≥ 2 whole periods, ≥ 1 s
    let w = 2.0 * std::f64::consts::PI * freq_hz;
    let samples = through_estimate(|t| SINE_AMPLITUDE_MM * (w * t).sin(), SETTLE_S + periods, seed);
    let fitted: Vec<_> = samples.iter().filter(|s| s.0 >= SETTLE_S).collect();
    let (mut ata, mut aty) = (Matrix3::<f64>::zeros(), Vector3::<f64>::zeros());
    for (t, _, y) in &fitted {
        let row = Vector3::new((w * t).sin(), (w * t).cos(), 1.0);
        ata += row * row.transpose();
        aty += row * *y;
    }
    let abc = ata.lu().solve(&aty).unwrap_or_else(Vector3::zeros);
    let gain = abc.x.hypot(abc.y) / SINE_AMPLITUDE_MM;
    let phase_lag_deg = -abc.y.atan2(abc.x).to_degrees();
    let residual = fitted.iter().map(|(t, _, y)| (y - (abc.x * (w * t).sin() + abc.y * (w * t).cos() + abc.z)).powi(2)).sum::<f64>();
    SineResponse {
        freq_hz,
        gain,
        phase_lag_deg,
        delay_ms: phase_lag_deg / 360.0 / freq_hz * 1e3,
        residual_rms_mm: (residual / fitted.len().max(1) as f64).sqrt(),
    }
}

/// The estimate's response to a [`STEP_MM`] step 2 s into the run (2 s after it).
pub fn step_figures(seed: u64) -> StepFigures {
    let at_s = 2.0;
    let samples = through_estimate(|t| if t >= at_s { STEP_MM } else { 0.0 }, at_s + 2.0, seed);
    let after: Vec<_> = samples.iter().filter(|s| s.0 >= at_s - 1e-9).collect();
    let first_beyond = |frac: f64| after.iter().find(|s| s.2 >= frac * STEP_MM).map_or(f64::NAN, |s| (s.0 - at_s) * 1e3);
    let (t10, t90) = (first_beyond(0.1), first_beyond(0.9));
    let peak = after.iter().filter(|s| s.0 < at_s + 1.0).map(|s| s.2).fold(f64::MIN, f64::max);
    StepFigures {
        step_mm: STEP_MM,
        to_10_percent_ms: t10,
        to_90_percent_ms: t90,
        rise_10_90_ms: t90 - t10,
        overshoot_percent: ((peak - STEP_MM) / STEP_MM * 100.0).max(0.0),
    }
}

/// The sinusoids' frequencies, Hz.
pub const SINE_FREQS_HZ: [f64; 3] = [0.1, 0.5, 2.0];

/// The estimate's figures: the three sinusoids and the step.
pub fn estimate_figures() -> (Vec<SineResponse>, StepFigures) {
    (SINE_FREQS_HZ.iter().map(|&f| sine_response(f, 46)).collect(), step_figures(46))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_fit_recovers_a_known_sinusoid_and_the_step_is_taken() {
        // The fit's own check: the estimate at 0.1 Hz passes the sinusoid (gain ≈ 1, small
        // lag) and what it leaves is about the filtered noise, not a misfit.
        let r = sine_response(0.1, 1);
        assert!((r.gain - 1.0).abs() < 0.05 && r.phase_lag_deg.abs() < 10.0, "{r:?}");
        assert!(r.residual_rms_mm < NOISE_MM, "{r:?}");
        let s = step_figures(1);
        assert!(s.to_90_percent_ms.is_finite() && s.to_90_percent_ms <= 1000.0, "{s:?}");
        assert!(s.rise_10_90_ms >= 0.0, "{s:?}");
    }
}

/// Everything `bench --dynamics` measures (also its `--json`, the `control_dynamics.json`
/// the report reads: docs/control.md "Dynamics").
#[derive(Debug, Clone, Serialize)]
pub struct ControlDynamics {
    /// The recording played.
    pub recording: std::path::PathBuf,
    /// `/proc/loadavg`'s 1, 5 and 15 minute load at the end, and the cores.
    pub load: String,
    /// The recording at its pace: exposure → register (and → DAC acknowledged).
    pub realtime: super::RealtimeFigures,
    /// The temporal estimate on sinusoids.
    pub sines: Vec<SineResponse>,
    /// The temporal estimate on a step.
    pub step: StepFigures,
    /// The valid line's timings (with `--analog`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub valid_line: Option<super::dynamics_valid::ValidLineFigures>,
}

/// `bench DIR --dynamics [--analog ADDR] [--json]`.
pub(super) fn bench_dynamics(rec: &crate::config::Recording, opts: &super::BenchOptions) -> anyhow::Result<()> {
    let analog = opts.analog.as_deref().map(|a| tagdeflect_sinks::analog_output::AnalogConfig {
        offset_v: 1.0,
        ..tagdeflect_sinks::analog_output::AnalogConfig::labjack(a, 1.0)
    });
    let realtime = super::realtime::run_realtime(rec, opts.full_frame, analog)?;
    let (sines, step) = estimate_figures();
    let valid_line = opts.analog.as_deref().map(super::dynamics_valid::valid_line_figures).transpose()?;
    let cores = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1);
    let loadavg = std::fs::read_to_string("/proc/loadavg").unwrap_or_default();
    let load = format!("{} on {cores} cores", loadavg.split_whitespace().take(3).collect::<Vec<_>>().join(" "));
    let d = ControlDynamics { recording: opts.dir.clone(), load, realtime, sines, step, valid_line };
    if opts.json {
        println!("{}", serde_json::to_string_pretty(&d)?);
    } else {
        print_dynamics(&d);
    }
    Ok(())
}

fn print_dynamics(d: &ControlDynamics) {
    super::realtime::print_realtime(&d.recording, &d.realtime);
    println!("temporal estimate, {DYNAMICS_FPS} sets/s, {:.0} µm noise, sinusoids of {:.0} µm:", NOISE_MM * 1e3, SINE_AMPLITUDE_MM * 1e3);
    for s in &d.sines {
        println!(
            "  {:>4} Hz: gain {:.3}, phase lag {:.1}° ({:.1} ms), residual {:.2} µm RMS",
            s.freq_hz,
            s.gain,
            s.phase_lag_deg,
            s.delay_ms,
            s.residual_rms_mm * 1e3
        );
    }
    let st = &d.step;
    println!(
        "  step {:.0} µm: 10 % after {:.1} ms, 90 % after {:.1} ms (10–90 % rise {:.1} ms), overshoot {:.1} %",
        st.step_mm * 1e3,
        st.to_10_percent_ms,
        st.to_90_percent_ms,
        st.rise_10_90_ms,
        st.overshoot_percent
    );
    if let Some(v) = &d.valid_line {
        println!("valid line (median / worst of 5, ms to the device's acknowledgement):");
        println!("  lost camera, first set without the value → low: {:.1} / {:.1}", v.lost_camera_ms[0], v.lost_camera_ms[1]);
        println!("  stalled pipeline, next set due → low: {:.1} / {:.1}", v.stall_from_due_ms[0], v.stall_from_due_ms[1]);
        println!("  stalled pipeline, last set → low: {:.1} / {:.1}", v.stall_from_last_ms[0], v.stall_from_last_ms[1]);
        println!("  device fault (connection cut 1 s): seen after {:.1} ms; the line {}", v.fault_detected_ms, v.fault_line);
        println!("  device back → low {:.1} ms, → high {:.1} ms", v.back_low_ms, v.back_high_ms);
    }
    println!("load {}", d.load);
}
