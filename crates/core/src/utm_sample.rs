//! Readings of the testing machine (UTM) and their interpolation at frame-set times.

use serde::{Deserialize, Serialize};
use std::collections::VecDeque;

/// One reading of the testing machine.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct UtmSample {
    /// Time of the reading, ns since the Unix epoch.
    pub t_ns: i64,
    /// Load, kN.
    #[serde(rename = "load_kN")]
    pub load_kn: f64,
    /// Stroke (crosshead travel), mm, when configured.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stroke_mm: Option<f64>,
}

/// A time-ordered window of UTM samples with linear interpolation (no extrapolation).
#[derive(Debug, Default, Clone)]
pub struct UtmHistory {
    samples: VecDeque<UtmSample>,
    /// Samples older than this many ns behind the newest are dropped (0 = keep all).
    keep_ns: i64,
    /// Two samples further apart than this are not interpolated between (an outage of the
    /// UTM link: nothing is invented across it); 0 = no limit.
    max_gap_ns: i64,
}

impl UtmHistory {
    /// Keeps every sample (replay).
    pub fn unbounded() -> Self {
        Self { samples: VecDeque::new(), keep_ns: 0, max_gap_ns: 0 }
    }

    /// Keeps samples within `keep_ns` of the newest (live).
    pub fn with_window(keep_ns: i64) -> Self {
        Self { samples: VecDeque::new(), keep_ns, max_gap_ns: 0 }
    }

    /// From now on keeps only samples within `keep_ns` of the newest (live runs: memory stays
    /// flat over hours; 0 = keep all). Interpolation at a time older than the window gives
    /// `None`, never a wrong value.
    pub fn set_window(&mut self, keep_ns: i64) {
        self.keep_ns = keep_ns.max(0);
        self.prune();
    }

    /// Refuses to interpolate between samples more than `max_gap_ns` apart.
    pub fn with_max_gap(mut self, max_gap_ns: i64) -> Self {
        self.max_gap_ns = max_gap_ns;
        self
    }

    /// Adds a sample; out-of-order samples are inserted in place, duplicates of a time replace.
    pub fn push(&mut self, s: UtmSample) {
        match self.samples.back() {
            Some(last) if last.t_ns > s.t_ns => {
                let i = self.samples.partition_point(|x| x.t_ns < s.t_ns);
                if self.samples.get(i).is_some_and(|x| x.t_ns == s.t_ns) {
                    self.samples[i] = s;
                } else {
                    self.samples.insert(i, s);
                }
            }
            Some(last) if last.t_ns == s.t_ns => *self.samples.back_mut().unwrap() = s,
            _ => self.samples.push_back(s),
        }
        self.prune();
    }

    fn prune(&mut self) {
        if self.keep_ns > 0 {
            let newest = self.samples.back().map(|x| x.t_ns).unwrap_or(0);
            // Keep the last sample before the window too: a time inside the window but
            // before its first sample still interpolates (within the gap limit).
            while self.samples.len() > 2 && self.samples[1].t_ns < newest.saturating_sub(self.keep_ns) {
                self.samples.pop_front();
            }
        }
    }

    /// Number of samples held.
    pub fn len(&self) -> usize {
        self.samples.len()
    }

    /// True when no sample is held.
    pub fn is_empty(&self) -> bool {
        self.samples.is_empty()
    }

    /// Newest sample time.
    pub fn newest_t_ns(&self) -> Option<i64> {
        self.samples.back().map(|s| s.t_ns)
    }

    /// Load and stroke linearly interpolated at `t_ns`; `None` outside the samples' span
    /// (no extrapolation) and inside a gap longer than the maximum. Stroke is `None` when
    /// either neighbour lacks it.
    pub fn interpolate(&self, t_ns: i64) -> Option<(f64, Option<f64>)> {
        let first = self.samples.front()?;
        let last = self.samples.back()?;
        if t_ns < first.t_ns || t_ns > last.t_ns {
            return None;
        }
        let i = self.samples.partition_point(|x| x.t_ns < t_ns);
        let b = self.samples[i];
        if b.t_ns == t_ns || i == 0 {
            return Some((b.load_kn, b.stroke_mm));
        }
        let a = self.samples[i - 1];
        // i128: arbitrary times (a corrupt recording) must not overflow.
        let span = b.t_ns as i128 - a.t_ns as i128;
        if self.max_gap_ns > 0 && span > self.max_gap_ns as i128 {
            return None;
        }
        let w = (t_ns as i128 - a.t_ns as i128) as f64 / span as f64;
        let lerp = |x: f64, y: f64| x + (y - x) * w;
        let stroke = match (a.stroke_mm, b.stroke_mm) {
            (Some(x), Some(y)) => Some(lerp(x, y)),
            _ => None,
        };
        Some((lerp(a.load_kn, b.load_kn), stroke))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn s(t: i64, l: f64) -> UtmSample {
        UtmSample { t_ns: t, load_kn: l, stroke_mm: Some(l / 10.0) }
    }

    #[test]
    fn interpolates_linearly_and_never_extrapolates() {
        let mut h = UtmHistory::unbounded();
        h.push(s(100, 1.0));
        h.push(s(300, 3.0));
        h.push(s(200, 2.5)); // out of order
        assert_eq!(h.interpolate(99), None);
        assert_eq!(h.interpolate(301), None);
        let (l, st) = h.interpolate(250).unwrap();
        assert!((l - 2.75).abs() < 1e-12 && (st.unwrap() - 0.275).abs() < 1e-12);
        assert_eq!(h.interpolate(100).unwrap().0, 1.0);
        assert_eq!(h.interpolate(300).unwrap().0, 3.0);
    }

    #[test]
    fn no_interpolation_across_an_outage() {
        let mut h = UtmHistory::unbounded().with_max_gap(100);
        h.push(s(0, 1.0));
        h.push(s(50, 2.0));
        h.push(s(500, 9.0));
        assert!(h.interpolate(25).is_some());
        assert_eq!(h.interpolate(300), None);
        assert_eq!(h.interpolate(500).unwrap().0, 9.0);
    }

    #[test]
    fn window_drops_old_samples() {
        let mut h = UtmHistory::with_window(100);
        for t in 0..10 {
            h.push(s(t * 50, t as f64));
        }
        // The window's samples and the one before it.
        assert_eq!(h.len(), 4);
        assert_eq!(h.newest_t_ns(), Some(450));
        assert!(h.interpolate(340).is_some(), "inside the window, before its first sample");
        assert_eq!(h.interpolate(250), None, "older than the window");
    }

    #[test]
    fn live_window_keeps_memory_flat_over_hours() {
        // 50 Hz for 3 simulated hours; a 60 s window holds ~3000 samples, whatever the length.
        let mut h = UtmHistory::unbounded().with_max_gap(500_000_000);
        h.set_window(60_000_000_000);
        let mut max_len = 0;
        for k in 0..(3 * 3600 * 50) {
            h.push(s(k * 20_000_000, k as f64));
            max_len = max_len.max(h.len());
        }
        assert!(max_len <= 3002, "{max_len}");
        let newest = h.newest_t_ns().unwrap();
        assert!(h.interpolate(newest - 30_000_000_000).is_some(), "30 s back still interpolates");
    }

    #[test]
    fn extreme_times_do_not_overflow() {
        let mut h = UtmHistory::unbounded().with_max_gap(100);
        h.push(s(i64::MIN, 1.0));
        h.push(s(i64::MAX, 2.0));
        assert_eq!(h.interpolate(0), None);
        let mut h = UtmHistory::with_window(i64::MAX);
        h.push(s(i64::MIN, 1.0));
        h.push(s(i64::MAX, 2.0));
        h.push(s(0, 2.0));
        assert!(h.interpolate(1).is_some());
    }
}
