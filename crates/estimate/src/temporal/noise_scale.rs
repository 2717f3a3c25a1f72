//! The set-to-set scale of a tag's measurement noise, learned from its centres (see the
//! module docs of [`super`], "The noise the filter is told").
//!
//! The solve states each set's pixel-noise covariance from its corner residuals; on a coarse
//! render most of that residual is the same from set to set (a bias, which cancels from
//! displacements), so the stated covariance can be many times the noise a set really adds.
//! What a set adds is seen in the centres' second differences: over three full sets at
//! times `t₀ < t₁ < t₂` with `ρ = (t₂ − t₁)/(t₁ − t₀)`, `e = z₂ − (1 + ρ) z₁ + ρ z₀` is zero
//! for a tag at rest or moving at a constant rate, and its covariance is
//! `V = R₂ + (1 + ρ)² R₁ + ρ² R₀` (the sets' stated covariances `R` scaled by the ratio);
//! `eᵀ V⁻¹ e / 3` is then that ratio times a χ²₃ / 3 draw. The ratio is the exponential
//! mean of its logarithm over the last [`MEMORY_S`] seconds (a log mean: robust to the one
//! large difference where the rate changes, which is also clipped), corrected for the
//! log-χ² bias, taken at [`MARGIN`] times its value and never above 1 (a stated noise is
//! never taken as understated).

use nalgebra::{Matrix3, Vector3};

/// Memory of the learned scale, s (a beam's lighting and focus change over minutes).
const MEMORY_S: f64 = 10.0;
/// Second differences before the scale is used (until then the stated noise is taken).
const WARM_UP: u32 = 10;
/// The learned variance ratio is taken at this multiple of its estimate: the estimate's
/// own spread (a log mean of some 50 correlated draws at 5 sets/s) and non-white wander
/// would otherwise let noise at rest pass the surprise and jump tests too often (at 1.5×, a
/// set at rest passes the jump gate with a chance of 2·10⁻⁵, the surprise threshold
/// 4·10⁻⁴; at 1×, 10⁻³ and 7·10⁻³, and the smoothing at rest was lost; at 2× a ramp from
/// rest at 30 sets/s went unseen for three sets).
pub const MARGIN: f64 = 1.5;
/// `E[ln(χ²₃ / 3)]`: ψ(3/2) + ln 2 − ln 3.
const LOG_CHI2_3_BIAS: f64 = -0.3690;
/// A second difference's log ratio above the running mean by more than this is clipped (a
/// change of rate, not noise).
const CLIP_LOG: f64 = 3.0;

/// One full set's centre as remembered for the next second differences.
#[derive(Debug, Clone, Copy)]
struct Seen {
    t_ns: i64,
    centre: Vector3<f64>,
    cov: Matrix3<f64>,
}

/// The learned ratio of a tag's set-to-set noise to its stated noise (a variance ratio).
#[derive(Debug, Clone, Copy, Default)]
pub struct NoiseScale {
    /// The last two full sets, newest last.
    seen: [Option<Seen>; 2],
    /// Running mean of the second differences' log ratio.
    log_mean: f64,
    /// Second differences counted so far.
    count: u32,
}

impl NoiseScale {
    /// Forgets everything (the filter started afresh).
    pub fn reset(&mut self) {
        *self = NoiseScale::default();
    }

    /// The ratio to scale the stated covariance by for the tests of a change (in (0, 1]; 1
    /// until [`WARM_UP`] second differences were seen).
    pub fn scale(&self) -> f64 {
        if self.count < WARM_UP {
            return 1.0;
        }
        ((self.log_mean - LOG_CHI2_3_BIAS).exp() * MARGIN).clamp(1e-6, 1.0)
    }

    /// Learns from one full set's centre and its stated covariance.
    pub fn observe(&mut self, t_ns: i64, centre: Vector3<f64>, cov: &Matrix3<f64>) {
        let now = Seen { t_ns, centre, cov: *cov };
        if let [Some(a), Some(b)] = self.seen {
            if let Some(log_ratio) = second_difference_log_ratio(&a, &b, &now) {
                self.learn(log_ratio, (now.t_ns - b.t_ns) as f64 * 1e-9);
            }
        }
        self.seen = [self.seen[1], Some(now)];
    }

    fn learn(&mut self, log_ratio: f64, dt_s: f64) {
        self.count = self.count.saturating_add(1);
        let x = if self.count > 1 { log_ratio.min(self.log_mean + CLIP_LOG) } else { log_ratio };
        let weight = (1.0 - (-dt_s / MEMORY_S).exp()).max(1.0 / self.count as f64);
        self.log_mean += weight * (x - self.log_mean);
    }
}

/// `ln(eᵀ V⁻¹ e / 3)` of three full sets (see the module docs); `None` when their times are
/// not increasing or `V` is singular.
fn second_difference_log_ratio(a: &Seen, b: &Seen, c: &Seen) -> Option<f64> {
    let (h1, h2) = (b.t_ns - a.t_ns, c.t_ns - b.t_ns);
    if h1 <= 0 || h2 <= 0 {
        return None;
    }
    let rho = h2 as f64 / h1 as f64;
    let e = c.centre - b.centre * (1.0 + rho) + a.centre * rho;
    let v = c.cov + b.cov * (1.0 + rho).powi(2) + a.cov * rho.powi(2);
    let ratio = e.dot(&(v.try_inverse()? * e)) / 3.0;
    Some(ratio.max(1e-12).ln())
}
