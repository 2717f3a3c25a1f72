//! The temporal estimate's response (docs/control.md "Dynamics"): its gain and phase lag on a
//! sinusoidal net deflection and its step response, for a controller closing its loop on the
//! signal. `bench --dynamics` prints them; a test run under control carries them in its
//! `control.json` (computed at the stop with the run's `[measure]` and frame rate).
//!
//! Simulated as the closed-loop test does: the specimen's true net deflection with
//! [`NOISE_MM`] of white noise (the measured noise of a rendered scene) through the estimator
//! ([`TagFilter`]), its output against the truth. The pipeline's own latency (exposure →
//! register or DAC write) adds 360° × f × latency of phase lag on top.

use nalgebra::{Matrix3, Vector3};
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use tagdeflect_core::control_summary::{Dynamics, SineResponse, StepFigures};

use crate::temporal::{TagFilter, TemporalConfig};

/// White noise of the simulated measurement, mm (a rendered scene's, docs/control.md).
pub const NOISE_MM: f64 = 0.002;
/// Amplitude of the sinusoids, mm.
pub const SINE_AMPLITUDE_MM: f64 = 0.05;
/// Height of the step, mm.
pub const STEP_MM: f64 = 0.05;
/// The sinusoids' frequencies, Hz.
pub const SINE_FREQS_HZ: [f64; 3] = [0.1, 0.5, 2.0];
/// Settling time before a sinusoid is fitted, s.
const SETTLE_S: f64 = 2.0;
/// The noise's seed (the figures are reproducible).
const SEED: u64 = 46;

/// Runs `truth(t_s)` through the temporal estimator at `fps` for `duration_s` with
/// [`NOISE_MM`] of noise: (t s, truth mm, output mm) per frame set.
fn through_estimate(cfg: &TemporalConfig, fps: f64, truth: impl Fn(f64) -> f64, duration_s: f64, seed: u64) -> Vec<(f64, f64, f64)> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let noise = Normal::new(0.0, NOISE_MM).expect("a positive σ");
    let cov = Matrix3::identity() * NOISE_MM.powi(2);
    let mut filter: Option<TagFilter> = None;
    let sets = (duration_s * fps).round() as usize;
    let mut out = Vec::with_capacity(sets);
    for k in 0..sets {
        let t_s = k as f64 / fps;
        let t_ns = (t_s * 1e9).round() as i64;
        let x = truth(t_s);
        let z = Vector3::new(noise.sample(&mut rng), noise.sample(&mut rng), x + noise.sample(&mut rng));
        let y = match filter.as_mut() {
            Some(f) => f.update(t_ns, z, &cov, &cov, false).centre.z,
            None => {
                let f = TagFilter::new(cfg.clone(), t_ns, z, &cov);
                let y = f.centre().z;
                filter = Some(f);
                y
            }
        };
        out.push((t_s, x, y));
    }
    out
}

/// Gain and phase lag of the estimate on `SINE_AMPLITUDE_MM · sin(2π f t)` at `fps` frame
/// sets/s: the output fitted (least squares) with a sin + b cos + c over whole periods after
/// 2 s of settling.
pub fn sine_response(cfg: &TemporalConfig, fps: f64, freq_hz: f64, seed: u64) -> SineResponse {
    let periods = (2.0 * freq_hz).ceil().max(2.0) / freq_hz; // ≥ 2 whole periods, ≥ 1 s
    let w = 2.0 * std::f64::consts::PI * freq_hz;
    let samples = through_estimate(cfg, fps, |t| SINE_AMPLITUDE_MM * (w * t).sin(), SETTLE_S + periods, seed);
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

/// The estimate's response to a [`STEP_MM`] step 2 s into the run (2 s after it); a level
/// never reached is given as the 2 s looked at.
pub fn step_figures(cfg: &TemporalConfig, fps: f64, seed: u64) -> StepFigures {
    let at_s = 2.0;
    let after_s = 2.0;
    let samples = through_estimate(cfg, fps, |t| if t >= at_s { STEP_MM } else { 0.0 }, at_s + after_s, seed);
    let after: Vec<_> = samples.iter().filter(|s| s.0 >= at_s - 1e-9).collect();
    let first_beyond = |frac: f64| after.iter().find(|s| s.2 >= frac * STEP_MM).map_or(after_s * 1e3, |s| (s.0 - at_s) * 1e3);
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

/// The three sinusoids and the step at `fps` frame sets/s with `cfg`.
pub fn dynamics(cfg: &TemporalConfig, fps: f64) -> Dynamics {
    Dynamics {
        how: format!(
            "the temporal estimate ([measure] temporal_accel_mm_s2 = {}) at {fps:.1} frame sets/s on a simulated net deflection with {:.0} µm of white noise: sinusoids of {:.0} µm fitted over whole periods after {SETTLE_S:.0} s, a {:.0} µm step (`bench --dynamics`, docs/control.md)",
            cfg.accel_mm_s2,
            NOISE_MM * 1e3,
            SINE_AMPLITUDE_MM * 1e3,
            STEP_MM * 1e3
        ),
        sets_per_s: fps,
        sines: SINE_FREQS_HZ.iter().map(|&f| sine_response(cfg, fps, f, SEED)).collect(),
        step: step_figures(cfg, fps, SEED),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_fit_recovers_a_known_sinusoid_and_the_step_is_taken() {
        // The fit's own check: the estimate at 0.1 Hz passes the sinusoid (gain ≈ 1, small
        // lag) and what it leaves is about the filtered noise, not a misfit.
        let cfg = TemporalConfig::default();
        let r = sine_response(&cfg, 30.0, 0.1, 1);
        assert!((r.gain - 1.0).abs() < 0.05 && r.phase_lag_deg.abs() < 10.0, "{r:?}");
        assert!(r.residual_rms_mm < NOISE_MM, "{r:?}");
        let s = step_figures(&cfg, 30.0, 1);
        assert!(s.to_90_percent_ms <= 1000.0, "{s:?}");
        assert!(s.rise_10_90_ms >= 0.0, "{s:?}");
    }
}
