//! Known displacements read from the UTM's stroke (`verify --reference-from-stroke`): the
//! crosshead carries the rigid target, and each position it holds is a hold of the reference.
//!
//! A hold is a maximal run of consecutive stroke samples whose range (largest − smallest)
//! stays within `tolerance_mm` and that lasts at least `min_hold_ns`; its displacement is the
//! mean stroke of the run times `scale` (−1 when the machine's stroke grows as the crosshead
//! rises: the reference is downward positive, the sense of a deflection). Samples of a move
//! belong to no hold. A move slower than `tolerance_mm / min_hold_ns` cannot be told from a
//! hold: such moves must be made faster (docs/verification.md gives the defaults' figure).

use crate::reference::Hold;

/// How stroke samples become holds.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StrokeHolds {
    /// The largest range of the stroke within one hold, mm.
    pub tolerance_mm: f64,
    /// The shortest hold, ns.
    pub min_hold_ns: i64,
    /// Multiplies the stroke into the reference's displacement (1 or −1).
    pub scale: f64,
}

impl Default for StrokeHolds {
    fn default() -> Self {
        Self { tolerance_mm: 0.002, min_hold_ns: 1_000_000_000, scale: 1.0 }
    }
}

/// The holds of `samples` (`(t_ns, stroke_mm)`, sorted by time; non-finite strokes end a run).
pub fn holds_from_stroke(samples: &[(i64, f64)], rule: &StrokeHolds) -> Vec<Hold> {
    let mut out = Vec::new();
    let mut start = 0;
    while start < samples.len() {
        let end = run_end(samples, start, rule.tolerance_mm);
        let run = &samples[start..end];
        if let (Some(first), Some(last)) = (run.first(), run.last()) {
            if last.0 - first.0 >= rule.min_hold_ns {
                let mean = run.iter().map(|s| s.1).sum::<f64>() / run.len() as f64;
                out.push(Hold { displacement_mm: mean * rule.scale, first_ns: first.0, last_ns: last.0, lines: run.len() });
            }
        }
        start = end.max(start + 1);
    }
    out
}

/// The end (exclusive) of the run from `start` whose range stays within `tolerance_mm`.
fn run_end(samples: &[(i64, f64)], start: usize, tolerance_mm: f64) -> usize {
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for (i, &(_, s)) in samples.iter().enumerate().skip(start) {
        if !s.is_finite() {
            return i;
        }
        lo = lo.min(s);
        hi = hi.max(s);
        if hi - lo > tolerance_mm {
            return i;
        }
    }
    samples.len()
}

#[cfg(test)]
mod tests {
    use super::*;

    const S: i64 = 1_000_000_000;

    #[test]
    fn held_positions_become_holds_and_moves_belong_to_none() {
        // 10 Hz: 0 held 2 s, a 0.5 s move, 0.5 held 2 s, a short stop of 0.3 s, 1.0 held 1.5 s.
        let mut s = Vec::new();
        let mut t = 0;
        let mut push = |v: f64, n: usize, s: &mut Vec<(i64, f64)>| {
            for _ in 0..n {
                s.push((t, v));
                t += S / 10;
            }
        };
        push(0.0, 21, &mut s);
        for k in 1..5 {
            push(0.1 * k as f64, 1, &mut s);
        }
        push(0.5, 21, &mut s);
        push(0.7, 4, &mut s);
        push(1.0, 16, &mut s);
        let h = holds_from_stroke(&s, &StrokeHolds { scale: -1.0, ..StrokeHolds::default() });
        let got: Vec<(f64, usize)> = h.iter().map(|h| (h.displacement_mm, h.lines)).collect();
        assert_eq!(got, vec![(-0.0, 21), (-0.5, 21), (-1.0, 16)]);
        assert_eq!(h[1].first_ns, 25 * S / 10);
        assert_eq!(h[1].last_ns, 45 * S / 10);
    }

    #[test]
    fn noise_within_the_tolerance_is_one_hold_and_a_gap_ends_it() {
        let s: Vec<(i64, f64)> = (0..30).map(|i| (i * S / 10, if i % 2 == 0 { 0.2 } else { 0.2015 })).collect();
        let h = holds_from_stroke(&s, &StrokeHolds::default());
        assert_eq!(h.len(), 1);
        assert!((h[0].displacement_mm - 0.20075).abs() < 1e-12);
        let mut g = s.clone();
        g[15].1 = f64::NAN;
        assert_eq!(holds_from_stroke(&g, &StrokeHolds::default()).len(), 2);
    }
}
