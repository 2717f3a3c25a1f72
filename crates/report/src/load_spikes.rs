//! Glitched load readings: one reading that jumps away from its neighbours and back within a
//! sample (999 kN between two readings of 45 kN: a corrupted register, a bit flip, a
//! transmission error) is no load a testing machine can apply. Such a reading is left out of
//! the curve, so it is never the peak (P1, Pp, F_L), and the report's QC names it.
//!
//! **The rule.** Reading `i` is a glitch when it lies further than `J` from the line through
//! its two neighbours, on the same side of both (up then down, or down then up), while the
//! neighbours differ from each other by less than half that deviation; `J` is the larger of
//! 10 σ of the load's robust noise, the larger neighbour's magnitude and 1 % of the
//! 90th percentile of |load| (so exact, noiseless data has a floor). A drop that stays (a
//! crack) is one step, not a glitch. The first and last readings, having one neighbour, are
//! glitches only when they jump away from a steady neighbour towards a larger magnitude.
//!
//! Also here: the robust noise estimate the curve's σ use.

use crate::curve::median;

/// Glitch threshold in units of the load's robust noise.
const NOISE_FACTOR: f64 = 10.0;
/// Glitch threshold as a fraction of the larger neighbour's |load|: a glitch is more than
/// twice its neighbours' load (a sharp peak sampled coarsely, 40 kN between 32 and 29.8, is not).
const NEIGHBOUR_FRACTION: f64 = 1.0;
/// Glitch floor as a fraction of the 90th percentile of |load|.
const SCALE_FRACTION: f64 = 0.01;

/// The indices of the glitched readings of a load series (module docs).
#[derive(Debug, Clone, Default, PartialEq)]
pub(crate) struct LoadSpikes(Vec<usize>);

impl LoadSpikes {
    /// Finds the glitches of `load` (readings in time order; times are not needed, as a glitch
    /// is one reading whatever the sampling).
    pub(crate) fn find(load: &[f64]) -> LoadSpikes {
        let n = load.len();
        if n < 3 {
            return LoadSpikes::default();
        }
        let idx: Vec<f64> = (0..n).map(|i| i as f64).collect();
        let noise = robust_noise(&idx, load);
        let mut mags: Vec<f64> = load.iter().map(|v| v.abs()).collect();
        mags.sort_by(f64::total_cmp);
        let floor = SCALE_FRACTION * mags[(0.9 * (n - 1) as f64) as usize];
        let limit = |nb: f64| (NOISE_FACTOR * noise).max(NEIGHBOUR_FRACTION * nb.abs()).max(floor).max(f64::MIN_POSITIVE);
        let mut out = Vec::new();
        for i in 0..n {
            let glitch = if i == 0 || i == n - 1 {
                let (a, b) = if i == 0 { (load[1], load[2]) } else { (load[n - 2], load[n - 3]) };
                let step = load[i] - a;
                load[i].abs() > a.abs() && step.abs() > limit(a) && (a - b).abs() < step.abs() / 4.0
            } else {
                let (a, b) = (load[i - 1], load[i + 1]);
                let (da, db) = (load[i] - a, load[i] - b);
                let dev = load[i] - 0.5 * (a + b);
                da.signum() == db.signum() && dev.abs() > limit(a.abs().max(b.abs())) && (a - b).abs() < dev.abs() / 2.0
            };
            if glitch {
                out.push(i);
            }
        }
        LoadSpikes(out)
    }

    /// `(t_ns, load)` of each glitch.
    pub(crate) fn readings(&self, t_ns: &[i64], load: &[f64]) -> Vec<(i64, f64)> {
        self.0.iter().map(|&i| (t_ns[i], load[i])).collect()
    }

    /// `v` without the glitches' entries.
    pub(crate) fn without<T>(&self, v: Vec<T>) -> Vec<T> {
        if self.0.is_empty() {
            return v;
        }
        v.into_iter().enumerate().filter(|(i, _)| self.0.binary_search(i).is_err()).map(|(_, x)| x).collect()
    }
}

/// Robust noise of `y(t)`: 1.4826 · MAD of each interior point's deviation from the line
/// through its neighbours, normalised to the σ of white noise. 0 with fewer than 5 points.
pub(crate) fn robust_noise(t: &[f64], y: &[f64]) -> f64 {
    if y.len() < 5 {
        return 0.0;
    }
    let mut r: Vec<f64> = (1..y.len() - 1)
        .filter_map(|i| {
            let span = t[i + 1] - t[i - 1];
            if span <= 0.0 {
                return None;
            }
            let a = (t[i + 1] - t[i]) / span;
            let b = (t[i] - t[i - 1]) / span;
            Some((y[i] - (a * y[i - 1] + b * y[i + 1])) / (1.0 + a * a + b * b).sqrt())
        })
        .collect();
    if r.len() < 3 {
        return 0.0;
    }
    let med = median(&mut r);
    let mut dev: Vec<f64> = r.iter().map(|v| (v - med).abs()).collect();
    1.4826 * median(&mut dev)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_glitched_reading_is_found_and_a_crack_is_not() {
        let mut load: Vec<f64> = (0..50).map(|i| 0.9 * i as f64 + 0.01 * ((i * 7919) % 13) as f64).collect();
        load[20] = 999.0;
        assert_eq!(LoadSpikes::find(&load).0, vec![20]);
        // A drop that stays (a crack) and a final failure are no glitches.
        let crack: Vec<f64> = (0..40).map(|i| if i < 25 { 1.8 * i as f64 } else { 20.0 - 0.1 * i as f64 }).chain([0.0]).collect();
        assert!(LoadSpikes::find(&crack).0.is_empty(), "{:?}", LoadSpikes::find(&crack));
        // A sharp first peak sampled coarsely (0.01 mm per reading of the C1609 law) is the peak.
        let peak: Vec<f64> = (0..40).map(|k| if k <= 5 { 8.0 * k as f64 } else { 30.0 - (k - 5) as f64 / 45.0 }).collect();
        assert!(LoadSpikes::find(&peak).0.is_empty(), "{:?}", LoadSpikes::find(&peak));
        // A glitch at either end, upward.
        let mut ends: Vec<f64> = (0..30).map(|i| 40.0 + 0.05 * i as f64).collect();
        ends[0] = 500.0;
        ends[29] = -700.0;
        assert_eq!(LoadSpikes::find(&ends).0, vec![0, 29]);
        assert_eq!(LoadSpikes::find(&ends).without((0..30).collect::<Vec<_>>()).len(), 28);
    }
}
