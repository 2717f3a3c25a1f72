//! A test's zero: the mean of its first [`ZERO_SETS`] frame sets, per quantity, and the
//! line's values counted from it.
//!
//! The zero's σ (added to every later line's) is the scatter of those sets *about a straight
//! line fitted through them*, over √n: a zero taken while the beam moves (a mid-test `zero`,
//! or a start during loading) counts the motion in its mean, which is the fitted line's value
//! at the zero's middle set, and not in its σ — the plain scatter about the mean took the
//! motion for noise and raised σ ~14×. From fewer than three sets no trend can
//! be told from noise: the plain scatter is kept.

use std::collections::BTreeMap;

use tagdeflect_core::feed::FeedLine;

/// Frame sets whose mean is a test's zero.
pub const ZERO_SETS: usize = 5;

/// The least spread of the zero's sets' loads that is warned of, kN, whatever the preload:
/// 1–4 % of the first peak of the standards' beams (ASTM C1609's 150 mm beams 30–45 kN, EN
/// 14651's F_L 12–20 kN), below the 5 % at the first point from which the report calls a test
/// not recorded from its start (docs/report.md "A zero taken while the load climbs").
pub const ZERO_SPREAD_FLOOR_KN: f64 = 0.5;

/// A test's zero: the mean of its first [`ZERO_SETS`] sets, per quantity.
#[derive(Default)]
pub(super) struct Zero {
    pub(super) n: usize,
    pub(super) tags: BTreeMap<u32, Mean<3>>,
    pub(super) net: Mean<1>,
    pub(super) gauges: BTreeMap<String, Mean<1>>,
    /// The lowest and highest load of its sets that carried one, kN.
    pub(super) loads_kn: Option<[f64; 2]>,
}

impl Zero {
    /// Takes `line` into the zero while it forms; true while it does.
    pub(super) fn take(&mut self, line: &FeedLine) -> bool {
        if self.n >= ZERO_SETS {
            return false;
        }
        self.n += 1;
        for t in &line.tags {
            self.tags.entry(t.id).or_default().add(t.pos_mm);
        }
        if let Some(v) = line.net_deflection_mm {
            self.net.add([v]);
        }
        for (k, g) in &line.gauges {
            self.gauges.entry(k.clone()).or_default().add([g.value]);
        }
        if let Some(l) = line.load_kn {
            self.widen_loads(l);
        }
        true
    }

    /// Takes `load_kn` into the range of the zero's loads.
    pub(super) fn widen_loads(&mut self, load_kn: f64) {
        let [lo, hi] = self.loads_kn.get_or_insert([load_kn, load_kn]);
        *lo = lo.min(load_kn);
        *hi = hi.max(load_kn);
    }

    /// Counts the line's values from the zero; a tag first seen after the zero formed counts
    /// from where it was first seen.
    pub(super) fn apply(&mut self, line: &mut FeedLine) {
        for t in &mut line.tags {
            let m = self.tags.entry(t.id).or_insert_with(|| {
                let mut m = Mean::default();
                m.add(t.pos_mm);
                m
            });
            let (mean, sd_of_mean) = m.get();
            for ((d, p), m) in t.disp_mm.iter_mut().zip(t.pos_mm).zip(mean) {
                *d = round_um(p - m);
            }
            if let Some(s) = t.sigma_mm.as_mut() {
                for k in 0..3 {
                    s[k] = (s[k].powi(2) + sd_of_mean[k].powi(2)).sqrt();
                }
            }
        }
        if let Some(v) = line.net_deflection_mm.as_mut() {
            if self.net.n > 0 {
                let (mean, sd) = self.net.get();
                *v = round_um(*v - mean[0]);
                if let Some(s) = line.net_deflection_sigma_mm.as_mut() {
                    *s = (s.powi(2) + sd[0].powi(2)).sqrt();
                }
            }
        }
        for (k, g) in line.gauges.iter_mut() {
            if let Some(m) = self.gauges.get(k) {
                let (mean, sd) = m.get();
                g.value -= mean[0];
                if g.sigma.is_finite() {
                    g.sigma = (g.sigma.powi(2) + sd[0].powi(2)).sqrt();
                }
            }
        }
    }
}

/// A [`Mean`] as stored: count, sums (then the sums of each value times its index, for the
/// trend; absent in records of earlier versions), sums of squares.
pub(super) type MeanParts = (usize, Vec<f64>, Vec<f64>);

/// A running mean of `N` values with the standard deviation of the mean.
#[derive(Clone, Copy)]
pub(super) struct Mean<const N: usize> {
    n: usize,
    sum: [f64; N],
    sum_sq: [f64; N],
    /// Σ k·x, k the value's index (0, 1, ...): the trend.
    sum_kx: [f64; N],
}

impl<const N: usize> Default for Mean<N> {
    fn default() -> Self {
        Mean { n: 0, sum: [0.0; N], sum_sq: [0.0; N], sum_kx: [0.0; N] }
    }
}

impl<const N: usize> Mean<N> {
    pub(super) fn to_parts(self) -> MeanParts {
        (self.n, self.sum.iter().chain(&self.sum_kx).copied().collect(), self.sum_sq.to_vec())
    }
    pub(super) fn from_parts(p: &MeanParts) -> Self {
        let mut m = Mean { n: p.0, ..Mean::default() };
        for (k, (sum, sq)) in m.sum.iter_mut().zip(m.sum_sq.iter_mut()).enumerate() {
            *sum = p.1.get(k).copied().unwrap_or(0.0);
            *sq = p.2.get(k).copied().unwrap_or(0.0);
        }
        // A record without the trend's sums: no trend (Σ k·x = k̄·Σx).
        let mid = m.n.saturating_sub(1) as f64 / 2.0;
        for k in 0..N {
            m.sum_kx[k] = p.1.get(N + k).copied().unwrap_or(mid * m.sum[k]);
        }
        m
    }
    fn add(&mut self, v: [f64; N]) {
        let index = self.n as f64;
        self.n += 1;
        for k in 0..N {
            self.sum[k] += v[k];
            self.sum_sq[k] += v[k] * v[k];
            self.sum_kx[k] += index * v[k];
        }
    }
    /// Mean, and its standard deviation: the scatter about the values' straight-line trend
    /// over √n from three values on (the plain scatter from two, 0 from one).
    fn get(&self) -> ([f64; N], [f64; N]) {
        let n = self.n.max(1) as f64;
        let k_mean = (n - 1.0) / 2.0;
        // Σ (k − k̄)² for k = 0..n−1.
        let s_kk = n * (n * n - 1.0) / 12.0;
        let mut mean = [0.0; N];
        let mut sd = [0.0; N];
        for k in 0..N {
            mean[k] = self.sum[k] / n;
            let s_xx = (self.sum_sq[k] - n * mean[k] * mean[k]).max(0.0);
            let var = match self.n {
                0 | 1 => 0.0,
                2 => s_xx,
                _ => {
                    let s_kx = self.sum_kx[k] - n * k_mean * mean[k];
                    (s_xx - s_kx * s_kx / s_kk).max(0.0) / (n - 2.0)
                }
            };
            sd[k] = (var / n).sqrt();
        }
        (mean, sd)
    }
}

/// The warning of a zero whose sets' loads spanned `[lo, hi]` kN, when the span exceeds the
/// method's preload or [`ZERO_SPREAD_FLOOR_KN`], whichever is larger: the load more than
/// doubled from the preload, or rose by more than a few % of a first peak, while the zero was
/// taken — a machine loading fast with no seating, whose zero stands for no one load.
pub(super) fn spread_warning([lo, hi]: [f64; 2], preload_kn: Option<f64>) -> Option<String> {
    let limit_kn = preload_kn.unwrap_or(0.0).max(ZERO_SPREAD_FLOOR_KN);
    (hi - lo > limit_kn).then(|| {
        format!(
            "the zero's {ZERO_SETS} frame sets spanned {:.3} kN of load ({lo:.3} to {hi:.3} kN, more than {limit_kn:.3} kN): \
             the machine was loading fast while the zero was taken (no seating?); the zero stands for no one load",
            hi - lo
        )
    })
}

fn round_um(v: f64) -> f64 {
    (v * 1e6).round() / 1e6
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A zero taken while the beam moves 0.1 mm a set with 2 µm of noise: its mean is the
    /// middle set's value and its σ the noise's over √n, not the motion's (which the plain
    /// scatter about the mean gave: ~70 µm, ~45× the noise's 1.5 µm).
    #[test]
    fn a_zero_taken_while_the_beam_moves_has_the_noise_sigma_not_the_motion() {
        let noise = [0.002, -0.001, -0.002, 0.003, -0.002];
        let mut m = Mean::<1>::default();
        for (k, e) in noise.iter().enumerate() {
            m.add([0.1 * k as f64 + e]);
        }
        let (mean, sd) = m.get();
        assert!((mean[0] - 0.2).abs() < 0.001, "{mean:?}");
        assert!(sd[0] > 0.0005 && sd[0] < 0.003, "σ of the zero {} mm", sd[0]);
        // Stored and read back (a resumed test), and a record of an earlier version (no
        // trend's sums): the plain scatter then.
        let back = Mean::<1>::from_parts(&m.to_parts());
        assert_eq!(back.get(), m.get());
        let (n, sums, sq) = m.to_parts();
        let old = Mean::<1>::from_parts(&(n, sums[..1].to_vec(), sq));
        assert!(old.get().1[0] > 0.05, "no trend known: the plain scatter {}", old.get().1[0]);
        // At rest the two agree to the degrees of freedom.
        let mut rest = Mean::<1>::default();
        for e in noise {
            rest.add([e]);
        }
        assert!(rest.get().1[0] < 0.003);
    }

    /// The zero's spread warned of above the preload or 0.5 kN, whichever is larger: a seated
    /// machine (0.05 kN a set from the 0.5 kN preload) is not warned of; one loading 4 kN a set
    /// is, naming the loads; with no preload (no method) the floor alone decides.
    #[test]
    fn a_zero_whose_sets_span_more_than_the_preload_or_half_a_kilonewton_is_warned_of() {
        let mut seated = Zero::default();
        let mut unseated = Zero::default();
        for k in 0..ZERO_SETS {
            seated.take(&FeedLine { load_kn: Some(0.5 + 0.05 * k as f64), ..FeedLine::default() });
            unseated.take(&FeedLine { load_kn: Some(0.5 + 4.0 * k as f64), ..FeedLine::default() });
        }
        seated.take(&FeedLine { load_kn: Some(9.0), ..FeedLine::default() });
        assert_eq!(seated.loads_kn, Some([0.5, 0.7]), "a sixth line is no set of the zero");
        assert_eq!(spread_warning(seated.loads_kn.unwrap(), Some(0.5)), None);
        let w = spread_warning(unseated.loads_kn.unwrap(), Some(0.5)).expect("16 kN across the zero's sets");
        assert!(w.contains("spanned 16.000 kN of load (0.500 to 16.500 kN, more than 0.500 kN)"), "{w}");
        // The larger of the preload and the floor.
        assert!(spread_warning([1.0, 2.9], Some(2.0)).is_none());
        assert!(spread_warning([1.0, 3.1], Some(2.0)).is_some());
        assert!(spread_warning([0.0, 0.45], None).is_none());
        assert!(spread_warning([0.0, 0.55], None).is_some());
        // A zero without loads has no range.
        let mut none = Zero::default();
        none.take(&FeedLine::default());
        assert_eq!(none.loads_kn, None);
    }
}
