//! At rest: noise, drift per hour and Allan deviation of a series.

use serde::{Deserialize, Serialize};

use crate::series::{line_fit, sd, Series};

/// The averaging times of the Allan deviation reported, s.
pub const ALLAN_TAUS_S: [f64; 3] = [1.0, 10.0, 100.0];

/// The shortest record at rest whose least-squares slope is given as a drift per hour, s.
pub const DRIFT_MIN_S: f64 = 60.0;

/// Clusters of τ a record must hold for the Allan deviation at τ to be given.
pub const ALLAN_MIN_CLUSTERS: usize = 3;

/// The Allan deviation at one averaging time, or why it is not given.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AllanPoint {
    /// Averaging time, s.
    pub tau_s: f64,
    /// Overlapping Allan deviation, mm (`None`: not enough data).
    pub adev_mm: Option<f64>,
    /// "not enough data: ..." when `adev_mm` is absent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub note: Option<String>,
}

/// Stability of one quantity at rest.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Stability {
    /// Samples.
    pub samples: usize,
    /// Duration covered, s.
    pub duration_s: f64,
    /// Standard deviation of one reading (the noise), mm.
    pub sd_mm: Option<f64>,
    /// Slope of the least-squares line through the readings, mm per hour (`None` for a
    /// record shorter than [`DRIFT_MIN_S`]: not enough data).
    pub drift_mm_per_h: Option<f64>,
    /// Allan deviation at [`ALLAN_TAUS_S`].
    pub allan: Vec<AllanPoint>,
}

/// The stability figures of a series.
pub fn stability(s: &Series) -> Stability {
    let duration_s = match (s.t_s.first(), s.t_s.last()) {
        (Some(a), Some(b)) => b - a,
        _ => 0.0,
    };
    let drift = line_fit(&s.t_s, &s.value_mm).map(|(_, b)| b * 3600.0).filter(|_| duration_s >= DRIFT_MIN_S);
    let allan = ALLAN_TAUS_S
        .iter()
        .map(|&tau| {
            let adev = s.interval_s().and_then(|dt| allan_deviation(&s.value_mm, dt, tau));
            let note =
                adev.is_none().then(|| format!("not enough data: {duration_s:.1} s at rest, {} × {tau} s needed", ALLAN_MIN_CLUSTERS));
            AllanPoint { tau_s: tau, adev_mm: adev, note }
        })
        .collect();
    Stability { samples: s.len(), duration_s, sd_mm: sd(&s.value_mm), drift_mm_per_h: drift, allan }
}

/// Overlapping Allan deviation of evenly spaced readings `y` (interval `dt_s`) at averaging
/// time `tau_s`: `σ²(τ) = ½ ⟨(ȳ_{k+m} − ȳ_k)²⟩` over every start `k`, `ȳ_k` the mean of
/// `m = round(τ/dt)` readings from `k`. `None` when `m < 1` or the record holds fewer than
/// [`ALLAN_MIN_CLUSTERS`] clusters of `m`.
pub fn allan_deviation(y: &[f64], dt_s: f64, tau_s: f64) -> Option<f64> {
    if dt_s <= 0.0 || !dt_s.is_finite() {
        return None;
    }
    let m = (tau_s / dt_s).round() as usize;
    if m < 1 || y.len() < ALLAN_MIN_CLUSTERS * m {
        return None;
    }
    let mut prefix = Vec::with_capacity(y.len() + 1);
    prefix.push(0.0);
    for v in y {
        prefix.push(prefix.last().unwrap_or(&0.0) + v);
    }
    let avg = |k: usize| (prefix[k + m] - prefix[k]) / m as f64;
    let count = y.len() + 1 - 2 * m;
    let sum: f64 = (0..count).map(|k| (avg(k + m) - avg(k)).powi(2)).sum();
    Some((0.5 * sum / count as f64).sqrt())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A deterministic Gaussian white noise (Box–Muller over a 64-bit LCG).
    fn white(n: usize, sigma: f64) -> Vec<f64> {
        let mut x: u64 = 0x2545_F491_4F6C_DD1D;
        let mut uniform = move || {
            x = x.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((x >> 11) as f64 + 0.5) / (1u64 << 53) as f64
        };
        (0..n).map(|_| sigma * (-2.0 * uniform().ln()).sqrt() * (std::f64::consts::TAU * uniform()).cos()).collect()
    }

    #[test]
    fn allan_deviation_of_white_noise_falls_as_one_over_root_tau() {
        let (dt, sigma) = (0.1, 1e-3);
        let y = white(200_000, sigma);
        for tau in [0.1, 1.0, 10.0, 100.0] {
            let adev = allan_deviation(&y, dt, tau).unwrap();
            let expected = sigma / (tau / dt).sqrt();
            // The estimate scatters by ≈ 1/√(2N/m): 5 % at τ = 100 s (the noise is seeded).
            assert!((adev / expected - 1.0).abs() < 0.1, "τ {tau}: {adev} vs {expected}");
        }
        assert_eq!(allan_deviation(&y[..2000], dt, 100.0), None, "200 s of data: fewer than 3 clusters of 100 s");
    }

    #[test]
    fn drift_per_hour_and_notes() {
        let t: Vec<f64> = (0..100).map(|k| k as f64).collect();
        let short = Series { t_s: t[..30].to_vec(), value_mm: vec![0.0; 30] };
        assert_eq!(stability(&short).drift_mm_per_h, None, "29 s: not enough data for a drift per hour");
        let s = Series { value_mm: t.iter().map(|t| 1e-4 * t).collect(), t_s: t };
        let st = stability(&s);
        assert!((st.drift_mm_per_h.unwrap() - 0.36).abs() < 1e-9);
        assert!(st.allan[0].adev_mm.is_some() && st.allan[2].adev_mm.is_none());
        assert!(st.allan[2].note.as_deref().unwrap().starts_with("not enough data"));
    }
}
