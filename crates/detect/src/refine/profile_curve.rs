//! A tabulated edge profile as a curve ([`super::profile`]): its value and slope between the
//! nodes, and the centroid of its line-spread function that defines where the edge is.

use super::profile::{CENTRE_HALF_WIDTH_PX, RANGE_PX};

/// `P(d)` and `dP/dd` of the tabulated `values` (nodes evenly over ±[`RANGE_PX`];
/// Catmull–Rom between nodes, constant beyond).
#[inline(always)]
pub(super) fn interpolate(v: &[f64], d: f64) -> (f64, f64) {
    let n = v.len();
    let step = 2.0 * RANGE_PX / (n - 1) as f64;
    let u = (d + RANGE_PX) / step;
    if !(u > 0.0) {
        return (v[0], 0.0);
    }
    if u >= (n - 1) as f64 {
        return (v[n - 1], 0.0);
    }
    // 0 < u < NODES − 1: truncation is the floor.
    let i = u as usize;
    let t = u - i as f64;
    let p1 = v[i];
    let p2 = v[i + 1];
    let p0 = if i > 0 { v[i - 1] } else { p1 };
    let p3 = if i + 2 < n { v[i + 2] } else { p2 };
    let (m1, m2) = (0.5 * (p2 - p0), 0.5 * (p3 - p1));
    let (t2, t3) = (t * t, t * t * t);
    let value = (2.0 * t3 - 3.0 * t2 + 1.0) * p1 + (t3 - 2.0 * t2 + t) * m1 + (-2.0 * t3 + 3.0 * t2) * p2 + (t3 - t2) * m2;
    let slope = (6.0 * t2 - 6.0 * t) * p1 + (3.0 * t2 - 4.0 * t + 1.0) * m1 + (-6.0 * t2 + 6.0 * t) * p2 + (3.0 * t2 - 2.0 * t) * m2;
    (value, slope / step)
}

/// The centroid of the tabulated profile's line-spread function (see
/// [`super::profile::EdgeProfile::centroid_px`]).
pub(super) fn centroid_px(values: &[f64]) -> f64 {
    let w = CENTRE_HALF_WIDTH_PX;
    let value = |d: f64| interpolate(values, d).0;
    // −∫(d − c)P′ = ∫P − w (P(c + w) + P(c − w)) over the window: decreasing in c for a
    // rising edge; bisection on ±0.75 px.
    let g = |c: f64| {
        let steps = 160;
        let h = 2.0 * w / steps as f64;
        let mut s = 0.5 * (value(c - w) + value(c + w));
        for k in 1..steps {
            s += value(c - w + k as f64 * h);
        }
        s * h - w * (value(c + w) + value(c - w))
    };
    let (mut lo, mut hi) = (-0.75, 0.75);
    // g rises through its root for a dark-to-bright profile.
    let falling = g(lo) > g(hi);
    for _ in 0..40 {
        let mid = 0.5 * (lo + hi);
        if (g(mid) > 0.0) == falling {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    0.5 * (lo + hi)
}
