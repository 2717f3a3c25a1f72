//! A test's zero: the mean of its first [`ZERO_SETS`] frame sets, per quantity, and the
//! line's values counted from it.

use std::collections::BTreeMap;

use tagdeflect_core::feed::FeedLine;

/// Frame sets whose mean is a test's zero.
pub const ZERO_SETS: usize = 5;

/// A test's zero: the mean of its first [`ZERO_SETS`] sets, per quantity.
#[derive(Default)]
pub(super) struct Zero {
    pub(super) n: usize,
    pub(super) tags: BTreeMap<u32, Mean<3>>,
    pub(super) net: Mean<1>,
    pub(super) gauges: BTreeMap<String, Mean<1>>,
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
        true
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

/// A [`Mean`] as stored: count, sums, sums of squares.
pub(super) type MeanParts = (usize, Vec<f64>, Vec<f64>);

/// A running mean of `N` values with the standard deviation of the mean.
#[derive(Clone, Copy)]
pub(super) struct Mean<const N: usize> {
    n: usize,
    sum: [f64; N],
    sum_sq: [f64; N],
}

impl<const N: usize> Default for Mean<N> {
    fn default() -> Self {
        Mean { n: 0, sum: [0.0; N], sum_sq: [0.0; N] }
    }
}

impl<const N: usize> Mean<N> {
    pub(super) fn to_parts(self) -> MeanParts {
        (self.n, self.sum.to_vec(), self.sum_sq.to_vec())
    }
    pub(super) fn from_parts(p: &MeanParts) -> Self {
        let mut m = Mean { n: p.0, ..Mean::default() };
        for (k, (sum, sq)) in m.sum.iter_mut().zip(m.sum_sq.iter_mut()).enumerate() {
            *sum = p.1.get(k).copied().unwrap_or(0.0);
            *sq = p.2.get(k).copied().unwrap_or(0.0);
        }
        m
    }
    fn add(&mut self, v: [f64; N]) {
        self.n += 1;
        for ((sum, sq), x) in self.sum.iter_mut().zip(self.sum_sq.iter_mut()).zip(v) {
            *sum += x;
            *sq += x * x;
        }
    }
    /// Mean, and the standard deviation of the mean (0 from one value).
    fn get(&self) -> ([f64; N], [f64; N]) {
        let n = self.n.max(1) as f64;
        let mut mean = [0.0; N];
        let mut sd = [0.0; N];
        for k in 0..N {
            mean[k] = self.sum[k] / n;
            if self.n > 1 {
                let var = ((self.sum_sq[k] - n * mean[k] * mean[k]) / (n - 1.0)).max(0.0);
                sd[k] = (var / n).sqrt();
            }
        }
        (mean, sd)
    }
}

fn round_um(v: f64) -> f64 {
    (v * 1e6).round() / 1e6
}
