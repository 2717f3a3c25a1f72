//! `bench --dynamics`: the control signal's dynamics (docs/control.md "Dynamics"): the
//! temporal estimate's gain and phase lag on a sinusoidal net deflection, its step response
//! (`tagdeflect_estimate::temporal_response`, at 30 frame sets/s with the default
//! `[measure]`), and — with `--analog ADDR`, a DAQ (or `tests/fixtures/analog_device.py
//! labjack PORT`) — what the analog output's valid line does on a lost camera, a stalled
//! pipeline and a device fault (`dynamics_valid.rs`).
//!
//! The rendered-camera pipeline's own latency is `bench --realtime`'s figure (exposure →
//! register or DAC write); at frequency f it adds 360° × f × latency of phase lag.

use serde::Serialize;
use tagdeflect_core::control_summary::{SineResponse, StepFigures};
use tagdeflect_estimate::temporal::TemporalConfig;
use tagdeflect_estimate::temporal_response::{self as response, NOISE_MM, SINE_AMPLITUDE_MM};

/// Frame sets per second of the simulated signal.
pub const DYNAMICS_FPS: f64 = 30.0;

/// The estimate's figures: the three sinusoids and the step (default `[measure]`, 30 sets/s).
pub fn estimate_figures() -> (Vec<SineResponse>, StepFigures) {
    let d = response::dynamics(&TemporalConfig::default(), DYNAMICS_FPS);
    (d.sines, d.step)
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
