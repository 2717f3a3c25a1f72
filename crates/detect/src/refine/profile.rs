//! The edge profile learned from the images: a camera's edge-spread function (ESF), tabulated
//! from the tag edges it has fitted, and its running accumulation.
//!
//! For a straight edge, whatever a camera does before the pixel (a lens's blur of any shape,
//! the pixel's fill factor) and after it with a shift-invariant kernel (sharpening, a
//! demosaic's interpolation, a blur), the value at a pixel centre is a fixed function of
//! the signed distance `d` of that centre from the edge line, scaled by the two grey levels:
//! `I = B + C · P(d)`. A wrong model of `P` biases each edge by an amount that depends on the
//! edge's sub-pixel phase; a `P` learned from many edges at many phases (the effective PSF of
//! Anderson & King, PASP 112, 2000) has no such bias. Here each well-fitted edge's band gives
//! samples `(d, (I − B) / C)` (`d` from its fitted line, `B`, `C` its fitted levels), which
//! are accumulated with tent weights on nodes every [`NODE_PX`] over ±[`RANGE_PX`]; a
//! profile is built from their means (module [`ProfileLearner::build`]): its black side
//! pinned to 0, its white end to 1 (the scale is the fit's contrast, so this changes no
//! position), and **re-centred on the centroid of its line-spread function** within ±
//! [`CENTRE_HALF_WIDTH_PX`] of the edge — the true edge for any symmetric point-spread
//! function and pixel, and a property of the accumulated profile alone, so it cannot move with
//! an edge's phase (the 50 % crossing would need the white plateau, which the band's 1.5 px
//! outside the tag does not always reach). Between nodes the profile is a Catmull–Rom cubic
//! (continuous slope, the LM's Jacobian); beyond them it is constant.

use super::band::EdgeBand;
use super::fit::Line;
use tagdeflect_core::frame::GrayImage;

/// Spacing of the profile's nodes, pixels.
pub const NODE_PX: f64 = 0.125;
/// The profile covers ±this distance from the edge, pixels.
pub const RANGE_PX: f64 = 3.0;
/// Half width of the window (pixels) whose line-spread centroid defines the edge.
pub const CENTRE_HALF_WIDTH_PX: f64 = 1.25;
const NODES: usize = (2.0 * RANGE_PX / NODE_PX) as usize + 1;
/// A node is known once its samples' tent weights reach this.
const MIN_NODE_WEIGHT: f64 = 20.0;
/// Edges needed before a profile is built.
const MIN_EDGES: u64 = 24;
/// A sample further than this (in units of the contrast) from its node's mean is not taken
/// (an occluded pixel, a mislabelled bit); applied once the node has [`MIN_NODE_WEIGHT`].
const MAX_DEVIATION: f64 = 0.3;
/// An edge whose fit's RMS residual exceeds this fraction of its contrast gives no samples.
const MAX_EDGE_RMS: f64 = 0.15;
/// Sums are halved when a node's weight exceeds this: the profile follows a slow change of
/// the optics (focus, temperature) over a few hundred frames, and never jumps.
const MAX_NODE_WEIGHT: f64 = 2.0e6;
/// Depth (pixels) beyond the data bits' inner edge from which a pixel beside a white bit no
/// longer sees that edge (the profile's black side is reached within it).
const WHITE_EDGE_CLEARANCE_PX: f64 = 2.0;

/// A camera's learned edge-spread function (see the module docs): `P(d)` with `d` the signed
/// distance (pixels, towards the white side) of a pixel centre from the edge line.
#[derive(Debug, Clone, PartialEq)]
pub struct EdgeProfile {
    /// `P` at `d = −RANGE_PX + k · NODE_PX`.
    values: Vec<f64>,
    /// Edges whose samples built it.
    edges: u64,
}

impl EdgeProfile {
    /// A profile tabulated from `f` (e.g. a model ESF; tests and comparisons).
    pub fn from_fn(f: impl Fn(f64) -> f64) -> Self {
        Self { values: (0..NODES).map(|k| f(node_d(k))).collect(), edges: 0 }
    }

    /// Edges whose samples built this profile.
    pub fn edges(&self) -> u64 {
        self.edges
    }

    /// `P(d)` and `dP/dd` (Catmull–Rom between nodes, constant beyond them).
    #[inline(always)]
    pub fn value_slope(&self, d: f64) -> (f64, f64) {
        let u = (d + RANGE_PX) / NODE_PX;
        if !(u > 0.0) {
            return (self.values[0], 0.0);
        }
        if u >= (NODES - 1) as f64 {
            return (self.values[NODES - 1], 0.0);
        }
        // 0 < u < NODES − 1: truncation is the floor.
        let i = u as usize;
        let t = u - i as f64;
        let v = &self.values;
        let p1 = v[i];
        let p2 = v[i + 1];
        let p0 = if i > 0 { v[i - 1] } else { p1 };
        let p3 = if i + 2 < NODES { v[i + 2] } else { p2 };
        let (m1, m2) = (0.5 * (p2 - p0), 0.5 * (p3 - p1));
        let (t2, t3) = (t * t, t * t * t);
        let value = (2.0 * t3 - 3.0 * t2 + 1.0) * p1 + (t3 - 2.0 * t2 + t) * m1 + (-2.0 * t3 + 3.0 * t2) * p2 + (t3 - t2) * m2;
        let slope = (6.0 * t2 - 6.0 * t) * p1 + (3.0 * t2 - 4.0 * t + 1.0) * m1 + (-6.0 * t2 + 6.0 * t) * p2 + (3.0 * t2 - 2.0 * t) * m2;
        (value, slope / NODE_PX)
    }

    /// `P(d)`.
    pub fn value(&self, d: f64) -> f64 {
        self.value_slope(d).0
    }

    /// The centroid (pixels) of the line-spread function `P′` within ±[`CENTRE_HALF_WIDTH_PX`]
    /// of it: the `c` where `∫ (d − c) P′(d) dd` over `[c − w, c + w]` vanishes.
    pub fn centroid_px(&self) -> f64 {
        let w = CENTRE_HALF_WIDTH_PX;
        // −∫(d − c)P′ = ∫P − w (P(c + w) + P(c − w)) over the window: decreasing in c for a
        // rising edge; bisection on ±0.75 px.
        let g = |c: f64| {
            let steps = 160;
            let h = 2.0 * w / steps as f64;
            let mut s = 0.5 * (self.value(c - w) + self.value(c + w));
            for k in 1..steps {
                s += self.value(c - w + k as f64 * h);
            }
            s * h - w * (self.value(c + w) + self.value(c - w))
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
}

/// The distance of node `k` from the edge, pixels.
fn node_d(k: usize) -> f64 {
    -RANGE_PX + k as f64 * NODE_PX
}

/// A camera's accumulation of edge samples (see the module docs).
#[derive(Debug, Clone)]
pub struct ProfileLearner {
    weight: Vec<f64>,
    sum: Vec<f64>,
    edges: u64,
}

impl Default for ProfileLearner {
    fn default() -> Self {
        Self { weight: vec![0.0; NODES], sum: vec![0.0; NODES], edges: 0 }
    }
}

impl ProfileLearner {
    /// Edges accumulated.
    pub fn edges(&self) -> u64 {
        self.edges
    }

    /// Forgets every sample.
    pub fn clear(&mut self) {
        *self = Self::default();
    }

    /// Adds the samples of a tag's last fit (`memory`: its bands and fitted lines) in `image`.
    /// Tags whose four edges were not all fitted give none.
    pub fn add_tag(&mut self, image: &GrayImage, memory: &super::EdgeMemory) {
        let Some(bands) = memory.bands.as_ref() else { return };
        if memory.lines.iter().any(|l| l.is_none()) {
            return;
        }
        for (band, line) in bands.edges.iter().zip(&memory.lines) {
            if let Some(line) = line {
                self.add_edge(image, band, line);
            }
        }
    }

    /// Adds one edge's samples: its pixels that cannot see the data bits' inner edge.
    fn add_edge(&mut self, image: &GrayImage, band: &EdgeBand, line: &Line) {
        let [black, contrast, _] = line.levels;
        if contrast.abs() < 4.0 || !(line.rms < MAX_EDGE_RMS * contrast.abs()) {
            return;
        }
        self.edges += 1;
        for p in &band.pixels {
            let u = band.a + band.dir * p.t + band.normal * p.n;
            let d = line.distance(&u);
            if p.white && d + p.gap < WHITE_EDGE_CLEARANCE_PX {
                continue;
            }
            let x = (d + RANGE_PX) / NODE_PX;
            if !(x >= 0.0 && x < (NODES - 1) as f64) {
                continue;
            }
            let v = (image.data[p.index] as f64 - black) / contrast;
            let k = x as usize;
            let f = x - k as f64;
            let near = if f < 0.5 { k } else { k + 1 };
            if self.weight[near] >= MIN_NODE_WEIGHT && (v - self.sum[near] / self.weight[near]).abs() > MAX_DEVIATION {
                continue;
            }
            // Unweighted: the band's tapers keep the fit continuous; every pixel's value is
            // as good a sample of the profile.
            for (node, w) in [(k, 1.0 - f), (k + 1, f)] {
                self.weight[node] += w;
                self.sum[node] += w * v;
            }
        }
        if self.weight.iter().any(|&w| w > MAX_NODE_WEIGHT) {
            self.weight.iter_mut().for_each(|w| *w *= 0.5);
            self.sum.iter_mut().for_each(|s| *s *= 0.5);
        }
    }

    /// The profile of the samples so far (see the module docs), or `None` while too few
    /// edges or nodes are known: the nodes from 2.5 px inside the edge to
    /// [`CENTRE_HALF_WIDTH_PX`] outside it must all be.
    pub fn build(&self) -> Option<EdgeProfile> {
        if self.edges < MIN_EDGES {
            return None;
        }
        let known = |k: usize| self.weight[k] >= MIN_NODE_WEIGHT;
        let centre = (RANGE_PX / NODE_PX) as usize;
        let first = centre - (2.5 / NODE_PX) as usize;
        let need_last = centre + (CENTRE_HALF_WIDTH_PX / NODE_PX).ceil() as usize;
        if !(first..=need_last).all(known) {
            return None;
        }
        let lo = (0..=first).rev().take_while(|&k| known(k)).last().unwrap_or(first);
        let hi = (need_last..NODES).take_while(|&k| known(k)).last().unwrap_or(need_last);
        let mean = |k: usize| self.sum[k] / self.weight[k];
        let values: Vec<f64> = (0..NODES).map(|k| mean(k.clamp(lo, hi))).collect();
        // Black side: the nodes 2.25 px and more inside the edge.
        let black_nodes = lo..=centre - (2.25 / NODE_PX) as usize;
        let black = black_nodes.clone().map(|k| values[k]).sum::<f64>() / black_nodes.count() as f64;
        let white = values[hi];
        if !(white - black > 0.5) {
            return None;
        }
        let raw = EdgeProfile { values: values.iter().map(|v| (v - black) / (white - black)).collect(), edges: self.edges };
        let c = raw.centroid_px();
        // Re-centred: the table's node k takes the raw profile at node k's distance + c.
        Some(EdgeProfile { values: (0..NODES).map(|k| raw.value(node_d(k) + c)).collect(), edges: self.edges })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn gaussian_esf(sigma: f64, shift: f64) -> impl Fn(f64) -> f64 {
        move |d: f64| 0.5 * (1.0 + libm_erf((d - shift) / (sigma * std::f64::consts::SQRT_2)))
    }

    /// erf by Abramowitz & Stegun 7.1.26 (1.5e-7), enough for these tests.
    fn libm_erf(x: f64) -> f64 {
        let t = 1.0 / (1.0 + 0.327_591_1 * x.abs());
        let y = 1.0
            - (((((1.061_405_429 * t - 1.453_152_027) * t) + 1.421_413_741) * t - 0.284_496_736) * t + 0.254_829_592) * t * (-x * x).exp();
        if x >= 0.0 {
            y
        } else {
            -y
        }
    }

    #[test]
    fn interpolation_follows_the_tabulated_function_with_its_slope() {
        let f = gaussian_esf(0.7, 0.0);
        let p = EdgeProfile::from_fn(&f);
        for d in [-1.3, -0.4, 0.0, 0.06, 0.5, 1.1] {
            let (v, s) = p.value_slope(d);
            assert!((v - f(d)).abs() < 2e-3, "P({d}) = {v} against {}", f(d));
            let h = 1e-6;
            let num = (p.value(d + h) - p.value(d - h)) / (2.0 * h);
            assert!((s - num).abs() < 1e-4, "slope at {d}: {s} against {num}");
        }
        assert_eq!(p.value_slope(-9.0), (p.values[0], 0.0));
        assert_eq!(p.value_slope(9.0), (p.values[NODES - 1], 0.0));
    }

    #[test]
    fn the_centroid_is_the_edge_of_a_symmetric_spread_even_with_overshoot() {
        for shift in [-0.3, 0.0, 0.137] {
            let g = EdgeProfile::from_fn(gaussian_esf(0.6, shift));
            assert!((g.centroid_px() - shift).abs() < 2e-3, "Gaussian shifted {shift}: {}", g.centroid_px());
            // A sharpened edge: the step minus a wider blurred copy (symmetric overshoots).
            let (a, b) = (gaussian_esf(0.4, shift), gaussian_esf(0.9, shift));
            let s = EdgeProfile::from_fn(|d| 2.0 * a(d) - b(d));
            assert!((s.centroid_px() - shift).abs() < 2e-3, "sharpened, shifted {shift}: {}", s.centroid_px());
        }
    }
}
