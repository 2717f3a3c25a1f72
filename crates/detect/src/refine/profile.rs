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
//!
//! **Pixel classes.** Samples are also accumulated per [class](CLASSES) (the edge's
//! orientation × the pixel's mosaic parity), each class re-centred on its own centroid (a
//! bilinear demosaic's kernel at each of the mosaic's pixels is symmetric about it). Which
//! class is fitted with its own profile, its orientation's or the pooled one is decided
//! where it pays — by which predicts held-out edges better than its simpler parent, beyond
//! three standard errors ([`super::profile_classes`]) —
//! when the profile is first learned, and kept ([`ClassChoice`]).

use super::band::{pixel_value, EdgeBand};
use super::fit::{clip_side, Line};
use super::formation::FormationLearner;
use super::kernel2d::{clipped, kernel_mode, site_of, Kernel2d, KernelLearner};
pub(super) use super::profile_classes::pixel_class;
use super::profile_classes::{class_mode, smooth_nodes, smoothed_towards, Samples};
pub use super::profile_classes::{ClassChoice, ClassUse, CLASSES};
use super::profile_curve::centroid_px;
pub(super) use super::profile_curve::interpolate;
use tagdeflect_core::frame::GrayImage;

/// Spacing of the profile's nodes, pixels, by default (see [`node_px`]).
pub const NODE_PX: f64 = 0.125;
/// The profile covers ±this distance from the edge, pixels.
pub const RANGE_PX: f64 = 3.0;
/// Half width of the window (pixels) whose line-spread centroid defines the edge.
pub const CENTRE_HALF_WIDTH_PX: f64 = 1.25;
/// A node 1/8 px wide is known once its samples' tent weights reach this (see
/// [`min_node_weight`]).
const MIN_NODE_WEIGHT_8TH: f64 = 20.0;
/// A pixel class's node 1/8 px wide is known once its samples' tent weights reach this (a
/// class has an eighth of the samples; in the first frame of a camera seeing ten tags, ~12 a
/// node).
const MIN_CLASS_NODE_WEIGHT_8TH: f64 = 6.0;

/// Spacing of the profile's nodes, pixels: [`NODE_PX`], or `TAGDEFLECT_PROFILE_NODE_PX`
/// (0.03–0.25; a measurement switch: docs/accuracy.md, "The node grid").
pub fn node_px() -> f64 {
    static PX: std::sync::OnceLock<f64> = std::sync::OnceLock::new();
    *PX.get_or_init(|| {
        let v = std::env::var("TAGDEFLECT_PROFILE_NODE_PX").ok().and_then(|v| v.parse::<f64>().ok());
        v.filter(|v| (0.03..=0.25).contains(v)).map_or(NODE_PX, |v| RANGE_PX / (RANGE_PX / v).round())
    })
}

/// The number of the profile's nodes.
pub(super) fn nodes() -> usize {
    (2.0 * RANGE_PX / node_px()).round() as usize + 1
}

/// A node is known once its samples' tent weights reach this (the same samples per pixel of
/// distance at any spacing).
pub(super) fn min_node_weight() -> f64 {
    MIN_NODE_WEIGHT_8TH * node_px() / NODE_PX
}

/// A pixel class's node is known once its samples' tent weights reach this.
pub(super) fn min_class_node_weight() -> f64 {
    MIN_CLASS_NODE_WEIGHT_8TH * node_px() / NODE_PX
}
/// A class's profile is built (its missing nodes filled from its parent's, see
/// [`Nodes::filled_from`]) once this fraction of its tested nodes have samples enough.
pub(super) const MIN_KNOWN_FRACTION: f64 = 0.6;
/// Edges needed before a profile is built.
const MIN_EDGES: u64 = 24;
/// A sample further than this (in units of the contrast) from its node's mean is not taken
/// (an occluded pixel, a mislabelled bit); applied once the node has [`min_node_weight`].
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
/// distance (pixels, towards the white side) of a pixel centre from the edge line; pooled over
/// every edge, and per [pixel class](pixel_class) where that class had samples enough.
#[derive(Debug, Clone, PartialEq)]
pub struct EdgeProfile {
    /// `P` at `d = −RANGE_PX + k · NODE_PX`, pooled over every class.
    values: Vec<f64>,
    /// Per pixel class ([`CLASSES`]), the `P` it is fitted with at the same nodes (its own or
    /// its orientation's), or `None`: the pooled one.
    classes: Vec<Option<Vec<f64>>>,
    /// Which profile each class uses.
    choice: ClassChoice,
    /// Edges whose samples built it.
    edges: u64,
    /// The 2-D kernel model, when `TAGDEFLECT_EDGE_MODEL` asks for it and it is learned.
    kernel: Option<Kernel2d>,
}

impl EdgeProfile {
    /// A profile tabulated from `f` (e.g. a model ESF; tests and comparisons), the same for
    /// every class.
    pub fn from_fn(f: impl Fn(f64) -> f64) -> Self {
        Self {
            values: (0..nodes()).map(|k| f(node_d(k))).collect(),
            classes: vec![None; CLASSES],
            choice: ClassChoice::default(),
            edges: 0,
            kernel: None,
        }
    }

    /// This profile with `kernel` as its 2-D kernel model (tests).
    #[cfg(test)]
    pub(super) fn with_kernel(self, kernel: Kernel2d) -> Self {
        Self { kernel: Some(kernel), ..self }
    }

    /// The 2-D kernel model the edges are fitted with instead, if any ([`super::kernel2d`]).
    pub fn kernel(&self) -> Option<&Kernel2d> {
        self.kernel.as_ref()
    }

    /// Which profile each pixel class is fitted with.
    pub fn choice(&self) -> ClassChoice {
        self.choice
    }

    /// Edges whose samples built this profile.
    pub fn edges(&self) -> u64 {
        self.edges
    }

    /// How many pixel classes have a profile of their own (the others use the pooled one).
    pub fn own_classes(&self) -> usize {
        self.classes.iter().filter(|c| c.is_some()).count()
    }

    /// The pooled `P(d)` and `dP/dd` (Catmull–Rom between nodes, constant beyond them).
    #[inline(always)]
    pub fn value_slope(&self, d: f64) -> (f64, f64) {
        interpolate(&self.values, d)
    }

    /// `P(d)` and `dP/dd` of pixel class `class` (its own profile, else the pooled one).
    #[inline(always)]
    pub fn class_value_slope(&self, class: usize, d: f64) -> (f64, f64) {
        match self.classes.get(class) {
            Some(Some(v)) => interpolate(v, d),
            _ => interpolate(&self.values, d),
        }
    }

    /// The pooled `P(d)`.
    pub fn value(&self, d: f64) -> f64 {
        self.value_slope(d).0
    }

    /// The centroid (pixels) of the pooled line-spread function `P′` within
    /// ±[`CENTRE_HALF_WIDTH_PX`] of it: the `c` where `∫ (d − c) P′(d) dd` over
    /// `[c − w, c + w]` vanishes.
    pub fn centroid_px(&self) -> f64 {
        centroid_px(&self.values)
    }
}

/// The distance of node `k` from the edge, pixels.
pub(super) fn node_d(k: usize) -> f64 {
    -RANGE_PX + k as f64 * node_px()
}

/// Tent-weighted sums of profile samples on the nodes: weights and values.
#[derive(Debug, Clone)]
pub(super) struct Nodes {
    weight: Vec<f64>,
    sum: Vec<f64>,
}

impl Default for Nodes {
    fn default() -> Self {
        Self { weight: vec![0.0; nodes()], sum: vec![0.0; nodes()] }
    }
}

impl Nodes {
    /// The mean of node `k`'s samples once it has `min_weight`.
    fn mean(&self, k: usize, min_weight: f64) -> Option<f64> {
        (self.weight[k] >= min_weight).then(|| self.sum[k] / self.weight[k])
    }

    /// Adds value `v` at node coordinate `x` (0 ≤ x < NODES − 1) with tent weights.
    pub(super) fn add(&mut self, x: f64, v: f64) {
        let k = x as usize;
        let f = x - k as f64;
        for (node, w) in [(k, 1.0 - f), (k + 1, f)] {
            self.weight[node] += w;
            self.sum[node] += w * v;
        }
        if self.weight[k].max(self.weight[k + 1]) > MAX_NODE_WEIGHT {
            // Halving keeps every mean.
            for x in [&mut self.weight, &mut self.sum] {
                x.iter_mut().for_each(|w| *w *= 0.5);
            }
        }
    }

    /// These sums with each node under `min_weight` filled from `parent` (the class's parent's
    /// sums: its orientation's, or the pooled ones): the parent's mean there plus the class's
    /// difference from it, interpolated linearly between the class's nearest known nodes on
    /// either side (held beyond the last). A class sees a quarter of its orientation's pixels,
    /// so on a camera's first frame a few of its nodes miss samples while its shape is known
    /// around them; `None` while fewer than [`MIN_KNOWN_FRACTION`] of the [tested
    /// nodes](tested_nodes) are known, or a node its parent lacks is missing.
    pub(super) fn filled_from(&self, parent: &Nodes, min_weight: f64) -> Option<Nodes> {
        let known = |k: usize| self.weight[k] >= min_weight;
        let tested = tested_nodes();
        let count = tested.clone().filter(|&k| known(k)).count();
        if (count as f64) < MIN_KNOWN_FRACTION * tested.clone().count() as f64 {
            return None;
        }
        let diff = |k: usize| self.sum[k] / self.weight[k] - parent.sum[k] / parent.weight[k];
        let mut filled = self.clone();
        let n = self.weight.len();
        for k in (0..n).filter(|&k| !known(k) && parent.weight[k] > 0.0) {
            let below = (0..k).rev().find(|&j| known(j) && parent.weight[j] > 0.0);
            let above = (k + 1..n).find(|&j| known(j) && parent.weight[j] > 0.0);
            let d = match (below, above) {
                (Some(a), Some(b)) => diff(a) + (diff(b) - diff(a)) * (k - a) as f64 / (b - a) as f64,
                (Some(a), None) => diff(a),
                (None, Some(b)) => diff(b),
                (None, None) => return None,
            };
            filled.weight[k] = min_weight;
            filled.sum[k] = min_weight * (parent.sum[k] / parent.weight[k] + d);
        }
        Some(filled)
    }

    /// [`Nodes::curve`] of these sums [filled from](Nodes::filled_from) `parent`.
    pub(super) fn filled_curve(&self, parent: &Nodes, min_weight: f64) -> Option<Vec<f64>> {
        self.filled_from(parent, min_weight)?.curve(min_weight)
    }

    /// The profile of these samples (see the module docs) — its black side pinned to 0, its
    /// white end to 1, re-centred on its line-spread centroid — or `None` while a node from
    /// 2.5 px inside the edge to [`CENTRE_HALF_WIDTH_PX`] outside it has less than
    /// `min_weight`.
    pub(super) fn curve(&self, min_weight: f64) -> Option<Vec<f64>> {
        let known = |k: usize| self.weight[k] >= min_weight;
        let (n, centre) = (self.weight.len(), (RANGE_PX / node_px()).round() as usize);
        let (first, need_last) = (*tested_nodes().start(), *tested_nodes().end());
        if !tested_nodes().all(known) {
            return None;
        }
        let lo = (0..=first).rev().take_while(|&k| known(k)).last().unwrap_or(first);
        let hi = (need_last..n).take_while(|&k| known(k)).last().unwrap_or(need_last);
        let mean = |k: usize| self.sum[k] / self.weight[k];
        let values: Vec<f64> = (0..n).map(|k| mean(k.clamp(lo, hi))).collect();
        // Black side: the nodes 2.25 px and more inside the edge.
        let black_nodes = lo..=centre - (2.25 / node_px()).round() as usize;
        let black = black_nodes.clone().map(|k| values[k]).sum::<f64>() / black_nodes.count() as f64;
        let white = values[hi];
        if !(white - black > 0.5) {
            return None;
        }
        let raw: Vec<f64> = values.iter().map(|v| (v - black) / (white - black)).collect();
        let c = centroid_px(&raw);
        // Re-centred: the table's node k takes the raw profile at node k's distance + c.
        Some((0..n).map(|k| interpolate(&raw, node_d(k) + c).0).collect())
    }
}

/// The nodes a profile needs (from 2.5 px inside the edge to [`CENTRE_HALF_WIDTH_PX`]
/// outside it), on which a class is tested against its parent.
pub(super) fn tested_nodes() -> std::ops::RangeInclusive<usize> {
    let (h, centre) = (node_px(), (RANGE_PX / node_px()).round() as usize);
    centre - (2.5 / h).round() as usize..=centre + (CENTRE_HALF_WIDTH_PX / h - 1e-9).ceil() as usize
}

/// A camera's accumulation of edge samples (see the module docs): pooled, and per pixel
/// class.
#[derive(Debug, Clone)]
pub struct ProfileLearner {
    pooled: Nodes,
    classes: Vec<Nodes>,
    /// Per edge orientation, its four classes' samples together.
    orientations: Vec<Nodes>,
    /// The classed samples kept for the class decision (until [`ProfileLearner::decided`]).
    samples: Samples,
    edges: u64,
    kernel: KernelLearner,
    /// The samples of the physical formation's model, when the switch asks for it.
    formation: FormationLearner,
}

impl Default for ProfileLearner {
    fn default() -> Self {
        Self {
            pooled: Nodes::default(),
            classes: vec![Nodes::default(); CLASSES],
            orientations: vec![Nodes::default(); 2],
            samples: Samples::default(),
            edges: 0,
            kernel: KernelLearner::default(),
            formation: FormationLearner::default(),
        }
    }
}

impl ProfileLearner {
    /// Edges accumulated.
    pub fn edges(&self) -> u64 {
        self.edges
    }

    /// Forgets every sample (the formation's light last found is kept as its next start).
    pub fn clear(&mut self) {
        let mut formation = std::mem::take(&mut self.formation);
        formation.clear();
        *self = Self { formation, ..Self::default() };
    }

    /// The class decision is made and kept: the samples kept for it are dropped, and no
    /// more are kept.
    pub fn decided(&mut self) {
        self.samples.finish();
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
            let v = (pixel_value(image, p.index) - black) / contrast;
            let site = site_of(p.index, image.width);
            match kernel_mode() {
                0 => {}
                1 | 2 if !clipped(image, p.index) => self.kernel.add(site, &band.normal, d, v),
                1 | 2 => {}
                // The formation keeps a clipped pixel censored, on the side of `v` it bounds.
                _ => self.formation.push(site, &band.normal, d, v, clip_side(image, p.index) * contrast.signum() as i8),
            }
            self.add_sample(pixel_class(&band.normal, p.index, image.width), d, v);
        }
        self.close_edge();
    }

    /// Ends an edge's samples: what follows is another edge's (the class decision scores
    /// edges).
    pub(super) fn close_edge(&mut self) {
        self.samples.close_edge();
        self.formation.close_edge();
    }

    /// Adds one sample `(d, v)` of a pixel of class `class` (unweighted: the band's tapers
    /// keep the fit continuous; every pixel's value is as good a sample of the profile).
    pub(super) fn add_sample(&mut self, class: usize, d: f64, v: f64) {
        let x = (d + RANGE_PX) / node_px();
        if !(x >= 0.0 && x < (nodes() - 1) as f64) {
            return;
        }
        let near = if x.fract() < 0.5 { x as usize } else { x as usize + 1 };
        if self.pooled.mean(near, min_node_weight()).is_some_and(|m| (v - m).abs() > MAX_DEVIATION) {
            return;
        }
        self.pooled.add(x, v);
        if let Some(nodes) = self.classes.get_mut(class) {
            nodes.add(x, v);
            self.orientations[class / 4].add(x, v);
            self.samples.push(class, d, v);
        }
    }

    /// The profile of the samples so far (see the module docs), or `None` while too few
    /// edges or nodes are known: the nodes from 2.5 px inside the edge to
    /// [`CENTRE_HALF_WIDTH_PX`] outside it must all be. A class whose nodes have fewer
    /// samples ([`min_class_node_weight`]) uses the pooled profile.
    ///
    /// Which class uses which profile is decided here ([`class_mode`]); `keep` is a decision
    /// made earlier to keep instead (a class then keeps its model for the whole test: see
    /// `crate::learned`); a kept class whose profile cannot be built now uses its parent's.
    pub fn build(&mut self, keep: Option<&ClassChoice>) -> Option<EdgeProfile> {
        self.build_in(class_mode(), keep)
    }

    /// Whether a build searches the formation's light (`TAGDEFLECT_EDGE_MODEL=formation` /
    /// `formation-sites`): dozens of trials over the kept samples, so a camera runs its
    /// rebuilds beside the frame loop on a copy of the learner (`crate::learned`).
    pub fn searches_formation() -> bool {
        matches!(kernel_mode(), 3 | 4)
    }

    /// After a build on a copy of this learner (`done`, see [`Self::searches_formation`]):
    /// the light it found is the next search's start here.
    pub fn take_search_start(&mut self, done: &ProfileLearner) {
        self.formation.start_from(done.formation.warm_light());
    }

    /// [`ProfileLearner::build`] in classing mode `mode`.
    pub(super) fn build_in(&mut self, mode: u8, keep: Option<&ClassChoice>) -> Option<EdgeProfile> {
        if self.edges < MIN_EDGES {
            return None;
        }
        let values = self.pooled.curve(min_node_weight())?;
        let own: Vec<Option<Vec<f64>>> = match mode {
            0 => vec![None; CLASSES],
            _ => {
                let oriented = self.oriented_curves(&values);
                let own = |(c, n): (usize, &Nodes)| {
                    let parent = oriented[c / 4].as_deref().unwrap_or(&values);
                    n.filled_curve(&self.orientations[c / 4], min_class_node_weight()).map(|v| smoothed_towards(&v, parent, smooth_nodes()))
                };
                self.classes.iter().enumerate().map(own).collect()
            }
        };
        let (classes, choice) = match mode {
            0 => (own, ClassChoice::default()),
            1 | 2 => {
                let choice = std::array::from_fn(|c| if own[c].is_some() { ClassUse::Own } else { ClassUse::Pooled });
                (own, choice)
            }
            _ => self.decided_classes(own, keep),
        };
        let kernel = match kernel_mode() {
            1 | 2 => self.kernel.solve(kernel_mode() == 2),
            3 | 4 => self.formation.solve(kernel_mode() == 4),
            _ => None,
        };
        Some(EdgeProfile { values, classes, choice, edges: self.edges, kernel })
    }

    /// Each class's profile as decided where it pays ([`Samples::decide`]), or as `keep`
    /// says: its own, else (not built, or the decision's) its orientation's, else the pooled
    /// one; with the choice as applied.
    fn decided_classes(&self, own: Vec<Option<Vec<f64>>>, keep: Option<&ClassChoice>) -> (Vec<Option<Vec<f64>>>, ClassChoice) {
        let wanted = keep.copied().unwrap_or_else(|| self.samples.decide());
        let oriented = self.pooled.curve(min_node_weight()).map_or_else(|| vec![None; 2], |pooled| self.oriented_curves(&pooled));
        let mut classes = vec![None; CLASSES];
        let mut choice = ClassChoice::default();
        for c in 0..CLASSES {
            let oriented = &oriented[c / 4];
            (classes[c], choice[c]) = match wanted[c] {
                ClassUse::Own if own[c].is_some() => (own[c].clone(), ClassUse::Own),
                ClassUse::Own | ClassUse::Orientation if oriented.is_some() => (oriented.clone(), ClassUse::Orientation),
                _ => (None, ClassUse::Pooled),
            };
        }
        (classes, choice)
    }

    /// Each edge orientation's profile (its missing nodes filled from the pooled sums, its
    /// difference from `pooled`, the pooled profile, smoothed: [`smoothed_towards`]).
    fn oriented_curves(&self, pooled: &[f64]) -> Vec<Option<Vec<f64>>> {
        let curve = |n: &Nodes| n.filled_curve(&self.pooled, min_class_node_weight()).map(|v| smoothed_towards(&v, pooled, smooth_nodes()));
        self.orientations.iter().map(curve).collect()
    }

    /// Marks the samples as enough for a profile (tests that add samples, not edges).
    #[cfg(test)]
    pub(super) fn set_edges_for_tests(&mut self) {
        self.edges = MIN_EDGES;
    }
}

#[cfg(test)]
pub(super) mod tests {
    use super::super::profile_classes::class_in_mode;
    use super::*;
    use nalgebra::Vector2;

    pub(crate) fn gaussian_esf(sigma: f64, shift: f64) -> impl Fn(f64) -> f64 {
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
        assert_eq!(p.value_slope(9.0), (p.values[nodes() - 1], 0.0));
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

    #[test]
    fn each_pixel_class_learns_its_own_profile_and_falls_back_to_the_pooled_one() {
        // Pixels are classed by the edge's orientation and their mosaic parity.
        let (vertical_edge, horizontal_edge) = (Vector2::new(-1.0, 0.05), Vector2::new(0.1, 1.0));
        assert_eq!(class_in_mode(2, &vertical_edge, 2 * 10 + 3, 10), 1);
        assert_eq!(class_in_mode(2, &vertical_edge, 3 * 10 + 4, 10), 2);
        assert_eq!(class_in_mode(2, &horizontal_edge, 3 * 10 + 3, 10), 7);
        assert_eq!(class_in_mode(1, &horizontal_edge, 3 * 10 + 3, 10), 4);
        assert_eq!(class_in_mode(0, &horizontal_edge, 3 * 10 + 3, 10), CLASSES);
        // Class 0 sees a sharp edge, class 1 a blurred one, the others none.
        let (sharp, wide) = (gaussian_esf(0.45, 0.0), gaussian_esf(0.9, 0.0));
        let mut learner = ProfileLearner::default();
        for k in 0..6000 {
            let d = -2.99 + 5.98 * ((k as f64 * 0.618_034) % 1.0);
            learner.add_sample(0, d, sharp(d));
            learner.add_sample(1, d, wide(d));
        }
        learner.edges = MIN_EDGES;
        let p = learner.build_in(2, None).expect("enough samples");
        assert_eq!(p.own_classes(), 2);
        for d in [-1.0, -0.3, 0.2, 0.8] {
            assert!((p.class_value_slope(0, d).0 - sharp(d)).abs() < 5e-3, "class 0 at {d}");
            assert!((p.class_value_slope(1, d).0 - wide(d)).abs() < 5e-3, "class 1 at {d}");
            assert_eq!(p.class_value_slope(5, d), p.value_slope(d), "class 5 falls back at {d}");
            let pooled = 0.5 * (sharp(d) + wide(d));
            assert!((p.value(d) - pooled).abs() < 1e-2, "pooled at {d}: {} against {pooled}", p.value(d));
        }
    }

    /// A uniform number in [0, 1) from a xorshift state.
    pub(crate) fn uniform(seed: &mut u64) -> f64 {
        *seed ^= *seed << 13;
        *seed ^= *seed >> 7;
        *seed ^= *seed << 17;
        (*seed >> 11) as f64 / (1u64 << 53) as f64
    }

    /// A standard normal number (Box–Muller).
    pub(crate) fn gauss(seed: &mut u64) -> f64 {
        (-2.0 * uniform(seed).max(1e-12).ln()).sqrt() * (std::f64::consts::TAU * uniform(seed)).cos()
    }
}
