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
//! bilinear demosaic's kernel at each of the mosaic's pixels is symmetric about it), and a
//! class with samples enough *and a profile that differs from its parent's beyond its own
//! sampling noise* is fitted with its own profile, the others with their parent's: the
//! orientation's profile (itself used only where it differs from the pooled one so), else
//! the pooled one ([`ClassChoice`], decided when the profile is first learned and kept).
//! How pixels are classed is [`class_mode`]'s.

use super::band::{pixel_value, EdgeBand};
use super::fit::Line;
use nalgebra::{Matrix3, Vector2, Vector3};
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
/// A pixel class's node is known once its samples' tent weights reach this (a class has an
/// eighth of the samples; in the first frame of a camera seeing ten tags, ~12 a node).
const MIN_CLASS_NODE_WEIGHT: f64 = 6.0;
/// A class (or an orientation's) profile is used in place of its parent's only when its node
/// means differ in shape from the parent's profile by a χ² (over their standard errors
/// counting edges, see `Nodes::differs`) above its degrees of freedom `ν` by this many of its
/// standard deviations `√(2ν)` (4: a class of the parent's profile passes by chance about once
/// in ten thousand decisions for Gaussian node errors; adjacent nodes share samples and the
/// standard errors are themselves estimated from a few edges, which widens χ²'s spread,
/// still leaving it below one in a hundred).
pub const CLASS_CHI2_SIGMAS: f64 = 4.0;
/// A node enters the class decision once this many edges reached it (its standard error
/// counts edges, [`Nodes::mean_var`]).
const MIN_NODE_EDGES: f64 = 5.0;
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
}

/// Which profile a pixel class is fitted with.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ClassUse {
    /// The camera's pooled profile.
    #[default]
    Pooled,
    /// The profile of the class's edge orientation (both parities of both axes).
    Orientation,
    /// The class's own profile.
    Own,
}

/// Each pixel class's [`ClassUse`] (index: the class, see [`CLASSES`]).
pub type ClassChoice = [ClassUse; CLASSES];

impl EdgeProfile {
    /// A profile tabulated from `f` (e.g. a model ESF; tests and comparisons), the same for
    /// every class.
    pub fn from_fn(f: impl Fn(f64) -> f64) -> Self {
        Self { values: (0..NODES).map(|k| f(node_d(k))).collect(), classes: vec![None; CLASSES], choice: ClassChoice::default(), edges: 0 }
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

/// `P(d)` and `dP/dd` of the tabulated `values` (Catmull–Rom between nodes, constant beyond).
#[inline(always)]
fn interpolate(v: &[f64], d: f64) -> (f64, f64) {
    let u = (d + RANGE_PX) / NODE_PX;
    if !(u > 0.0) {
        return (v[0], 0.0);
    }
    if u >= (NODES - 1) as f64 {
        return (v[NODES - 1], 0.0);
    }
    // 0 < u < NODES − 1: truncation is the floor.
    let i = u as usize;
    let t = u - i as f64;
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

/// The centroid of the tabulated profile's line-spread function (see
/// [`EdgeProfile::centroid_px`]).
fn centroid_px(values: &[f64]) -> f64 {
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

/// The distance of node `k` from the edge, pixels.
fn node_d(k: usize) -> f64 {
    -RANGE_PX + k as f64 * NODE_PX
}

/// Pixel classes with a profile each: the edge's orientation (its normal nearer the image's
/// x or y axis) × the pixel's place in a 2 × 2 mosaic (column and row parity). An astigmatic
/// blur spreads a near-vertical edge differently from a near-horizontal one, and a colour
/// sensor's demosaic interpolates each of the mosaic's four pixels from different neighbours.
pub const CLASSES: usize = 8;

/// How pixels are classed: 0 (the default) one pooled profile, 1 by edge orientation, 2 by
/// orientation and mosaic parity (both: every class with samples enough uses its own
/// profile), 3 by orientation and parity, each class using its own profile only where it
/// differs from its parent's beyond its sampling noise ([`CLASS_CHI2_SIGMAS`]). Measured on
/// the formations' scenes (docs/accuracy.md, "A class only where it pays"): every class used
/// (modes 1, 2) costs the scenes one profile describes (the sharp scene 0.0033 → 0.0051 mm);
/// the decision (mode 3) keeps the sharp scene's 0.0033 mm and takes the Bayer mosaic's gain
/// (0.0242 → 0.0099 mm) but still takes classes on the sharpened scene (0.0064 → 0.0098 mm
/// with its standard errors counting edges; 0.0102 counting pixels) and a little on the fill
/// factor's (0.0058 → 0.0062 mm; 0.0074): a class there differs from its parent beyond its
/// sampling noise yet does not pay, so it is not the default. `TAGDEFLECT_PROFILE_CLASSES` (`auto`, `orientation`,
/// `parity`) chooses a mode for a measurement.
fn class_mode() -> u8 {
    static MODE: std::sync::OnceLock<u8> = std::sync::OnceLock::new();
    *MODE.get_or_init(|| match std::env::var("TAGDEFLECT_PROFILE_CLASSES").as_deref() {
        Ok("auto") => 3,
        Ok("orientation") => 1,
        Ok("parity") => 2,
        _ => 0,
    })
}

/// The [class](CLASSES) of the pixel at `index` of an image `width` pixels wide on an edge of
/// outward `normal` (ideal pixels; their axes are the image's); [`CLASSES`] when pixels are
/// not classed (see [`class_mode`]).
#[inline]
pub(super) fn pixel_class(normal: &Vector2<f64>, index: usize, width: u32) -> usize {
    class_in_mode(class_mode(), normal, index, width)
}

/// [`pixel_class`] in classing mode `mode`.
fn class_in_mode(mode: u8, normal: &Vector2<f64>, index: usize, width: u32) -> usize {
    let orient = usize::from(normal.y.abs() > normal.x.abs());
    match mode {
        0 => CLASSES,
        1 => 4 * orient,
        _ => {
            let w = width.max(1) as usize;
            4 * orient + (index % w) % 2 + 2 * ((index / w) % 2)
        }
    }
}

/// Tent-weighted sums of profile samples on the nodes: weights, values, squared values and
/// squared weights (a node mean's standard error counting pixels); and, per node, the sums
/// over edges of each edge's own sums there (a node mean's standard error counting edges,
/// [`Nodes::mean_var`]).
#[derive(Debug, Clone)]
struct Nodes {
    weight: Vec<f64>,
    sum: Vec<f64>,
    sum_sq: Vec<f64>,
    weight_sq: Vec<f64>,
    /// Over the closed edges `e`, with `S_e`, `W_e` edge `e`'s sums of `w·v` and `w` at the
    /// node: `Σ S_e²`, `Σ S_e W_e`, `Σ W_e²` and the number of edges.
    edge_ss: Vec<f64>,
    edge_sw: Vec<f64>,
    edge_ww: Vec<f64>,
    edges: Vec<f64>,
    /// The open edge's `S_e` and `W_e` at each node.
    open_s: Vec<f64>,
    open_w: Vec<f64>,
}

impl Default for Nodes {
    fn default() -> Self {
        let zeros = || vec![0.0; NODES];
        Self {
            weight: zeros(),
            sum: zeros(),
            sum_sq: zeros(),
            weight_sq: zeros(),
            edge_ss: zeros(),
            edge_sw: zeros(),
            edge_ww: zeros(),
            edges: zeros(),
            open_s: zeros(),
            open_w: zeros(),
        }
    }
}

impl Nodes {
    /// The mean of node `k`'s samples once it has `min_weight`.
    fn mean(&self, k: usize, min_weight: f64) -> Option<f64> {
        (self.weight[k] >= min_weight).then(|| self.sum[k] / self.weight[k])
    }

    /// Adds value `v` at node coordinate `x` (0 ≤ x < NODES − 1) with tent weights; to the
    /// open edge's sums too when `EDGES` (the class decision's, [`Nodes::mean_var`]).
    fn add<const EDGES: bool>(&mut self, x: f64, v: f64) {
        let k = x as usize;
        let f = x - k as f64;
        for (node, w) in [(k, 1.0 - f), (k + 1, f)] {
            self.weight[node] += w;
            self.sum[node] += w * v;
            self.sum_sq[node] += w * v * v;
            self.weight_sq[node] += w * w;
            if EDGES {
                self.open_s[node] += w * v;
                self.open_w[node] += w;
            }
        }
        if self.weight[k].max(self.weight[k + 1]) > MAX_NODE_WEIGHT {
            // Halving keeps every mean and the effective sample counts' ratios.
            for x in [&mut self.weight, &mut self.sum, &mut self.sum_sq, &mut self.open_s, &mut self.open_w] {
                x.iter_mut().for_each(|w| *w *= 0.5);
            }
            for x in [&mut self.weight_sq, &mut self.edge_ss, &mut self.edge_sw, &mut self.edge_ww] {
                x.iter_mut().for_each(|w| *w *= 0.25);
            }
        }
    }

    /// Closes the open edge: its sums at each node it reached join the per-edge sums.
    fn close_edge(&mut self) {
        for k in 0..NODES {
            let (s, w) = (self.open_s[k], self.open_w[k]);
            if w > 0.0 {
                self.edge_ss[k] += s * s;
                self.edge_sw[k] += s * w;
                self.edge_ww[k] += w * w;
                self.edges[k] += 1.0;
                (self.open_s[k], self.open_w[k]) = (0.0, 0.0);
            }
        }
    }

    /// The squared standard error of node `k`'s mean with **each edge one sample** (the
    /// pixels of one edge share its fitted distance, levels and phase, so their errors at a
    /// node are not independent): the spread of the edges' own sums about the mean, the
    /// cluster (sandwich) estimate `G/(G − 1) · Σ_e (S_e − m W_e)² / W²` over the `G` edges
    /// that reached the node. Never below the pixel-count estimate (the samples' weighted
    /// variance over their effective count `(Σw)²/Σw²`), which bounds it where few edges make
    /// the spread itself uncertain. `None` when fewer than [`MIN_NODE_EDGES`] edges reached
    /// the node: its mean's error is not known.
    fn mean_var(&self, k: usize) -> Option<f64> {
        let (w, g) = (self.weight[k], self.edges[k]);
        if g < MIN_NODE_EDGES || !(w > 0.0) {
            return None;
        }
        let mean = self.sum[k] / w;
        let pixels = (self.sum_sq[k] / w - mean * mean).max(0.0) * self.weight_sq[k] / (w * w);
        let spread = (self.edge_ss[k] - 2.0 * mean * self.edge_sw[k] + mean * mean * self.edge_ww[k]).max(0.0);
        let edges = g / (g - 1.0) * spread / (w * w);
        Some(edges.max(pixels))
    }

    /// Whether these samples' profile differs in shape from `parent` beyond its sampling
    /// noise: their node means `m_k` (nodes from 2.5 px inside the edge to
    /// [`CENTRE_HALF_WIDTH_PX`] outside it with `min_weight`) fitted as
    /// `a + b · P(d_k) + c · P′(d_k)` (`P` the parent) by weighted least squares (weights the
    /// inverse squared standard errors counting edges, [`Nodes::mean_var`], at least 10⁻⁴ of
    /// the contrast; nodes reached by fewer than [`MIN_NODE_EDGES`] edges left out), and
    /// `χ² > ν + CLASS_CHI2_SIGMAS · √(2ν)` with `ν = n − 3`. The level, scale and shift are
    /// left out because each class's profile is pinned to 0 and 1 and centred on its own
    /// line-spread centroid: they are never a class's difference, and their estimates' noise
    /// (one white node sets the scale) would otherwise count as one.
    fn differs(&self, parent: &[f64], min_weight: f64) -> bool {
        self.shape_chi2(parent, min_weight).is_some_and(|(chi2, nu)| chi2 > nu + CLASS_CHI2_SIGMAS * (2.0 * nu).sqrt())
    }

    /// The χ² of [`Nodes::differs`] and its degrees of freedom `ν`, when `ν ≥ 3`.
    fn shape_chi2(&self, parent: &[f64], min_weight: f64) -> Option<(f64, f64)> {
        let rows: Vec<(Vector3<f64>, f64, f64)> = tested_nodes()
            .filter(|&k| self.weight[k] >= min_weight)
            .filter_map(|k| {
                let (p, slope) = interpolate(parent, node_d(k));
                let (var, edges) = (self.mean_var(k)?.max(1e-8), self.edges[k]);
                // 1/var from G edges' spread is biased high by (G − 1)/(G − 3) (the inverse of
                // a χ²_{G−1} variate's mean): corrected, so that χ² has its expected mean ν.
                Some((Vector3::new(1.0, p, slope), self.sum[k] / self.weight[k], (edges - 3.0) / (edges - 1.0) / var))
            })
            .collect();
        let nu = rows.len() as f64 - 3.0;
        if nu < 3.0 {
            return None;
        }
        let (mut ata, mut atb) = (Matrix3::<f64>::zeros(), Vector3::<f64>::zeros());
        for (x, y, w) in &rows {
            ata += (*w * x) * x.transpose();
            atb += (*w * *y) * x;
        }
        let beta = ata.try_inverse()? * atb;
        let chi2: f64 = rows.iter().map(|(x, y, w)| w * (y - x.dot(&beta)).powi(2)).sum();
        Some((chi2, nu))
    }

    /// The profile of these samples (see the module docs) — its black side pinned to 0, its
    /// white end to 1, re-centred on its line-spread centroid — or `None` while a node from
    /// 2.5 px inside the edge to [`CENTRE_HALF_WIDTH_PX`] outside it has less than
    /// `min_weight`.
    fn curve(&self, min_weight: f64) -> Option<Vec<f64>> {
        let known = |k: usize| self.weight[k] >= min_weight;
        let centre = (RANGE_PX / NODE_PX) as usize;
        let (first, need_last) = (*tested_nodes().start(), *tested_nodes().end());
        if !tested_nodes().all(known) {
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
        let raw: Vec<f64> = values.iter().map(|v| (v - black) / (white - black)).collect();
        let c = centroid_px(&raw);
        // Re-centred: the table's node k takes the raw profile at node k's distance + c.
        Some((0..NODES).map(|k| interpolate(&raw, node_d(k) + c).0).collect())
    }
}

/// The nodes a profile needs (from 2.5 px inside the edge to [`CENTRE_HALF_WIDTH_PX`]
/// outside it), on which a class is tested against its parent.
fn tested_nodes() -> std::ops::RangeInclusive<usize> {
    let centre = (RANGE_PX / NODE_PX) as usize;
    centre - (2.5 / NODE_PX) as usize..=centre + (CENTRE_HALF_WIDTH_PX / NODE_PX).ceil() as usize
}

/// A camera's accumulation of edge samples (see the module docs): pooled, and per pixel
/// class.
#[derive(Debug, Clone)]
pub struct ProfileLearner {
    pooled: Nodes,
    classes: Vec<Nodes>,
    /// Per edge orientation, its four classes' samples together (the per-edge sums of a
    /// group cannot be merged from its classes').
    orientations: Vec<Nodes>,
    edges: u64,
}

impl Default for ProfileLearner {
    fn default() -> Self {
        Self { pooled: Nodes::default(), classes: vec![Nodes::default(); CLASSES], orientations: vec![Nodes::default(); 2], edges: 0 }
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
            let v = (pixel_value(image, p.index) - black) / contrast;
            self.add_sample(pixel_class(&band.normal, p.index, image.width), d, v);
        }
        self.close_edge();
    }

    /// Ends an edge's samples: what follows is another edge's (see [`Nodes::mean_var`]).
    fn close_edge(&mut self) {
        for n in self.classes.iter_mut().chain(self.orientations.iter_mut()) {
            n.close_edge();
        }
    }

    /// Adds one sample `(d, v)` of a pixel of class `class` (unweighted: the band's tapers
    /// keep the fit continuous; every pixel's value is as good a sample of the profile).
    fn add_sample(&mut self, class: usize, d: f64, v: f64) {
        let x = (d + RANGE_PX) / NODE_PX;
        if !(x >= 0.0 && x < (NODES - 1) as f64) {
            return;
        }
        let near = if x.fract() < 0.5 { x as usize } else { x as usize + 1 };
        if self.pooled.mean(near, MIN_NODE_WEIGHT).is_some_and(|m| (v - m).abs() > MAX_DEVIATION) {
            return;
        }
        self.pooled.add::<false>(x, v);
        if let Some(nodes) = self.classes.get_mut(class) {
            nodes.add::<true>(x, v);
            self.orientations[class / 4].add::<true>(x, v);
        }
    }

    /// The profile of the samples so far (see the module docs), or `None` while too few
    /// edges or nodes are known: the nodes from 2.5 px inside the edge to
    /// [`CENTRE_HALF_WIDTH_PX`] outside it must all be. A class whose nodes have fewer
    /// samples ([`MIN_CLASS_NODE_WEIGHT`]) uses the pooled profile.
    ///
    /// Which class uses which profile is decided here ([`class_mode`]); `keep` is a decision
    /// made earlier to keep instead (a class then keeps its model for the whole test: see
    /// `crate::learned`); a kept class whose profile cannot be built now uses its parent's.
    pub fn build(&self, keep: Option<&ClassChoice>) -> Option<EdgeProfile> {
        self.build_in(class_mode(), keep)
    }

    /// [`ProfileLearner::build`] in classing mode `mode`.
    fn build_in(&self, mode: u8, keep: Option<&ClassChoice>) -> Option<EdgeProfile> {
        if self.edges < MIN_EDGES {
            return None;
        }
        let values = self.pooled.curve(MIN_NODE_WEIGHT)?;
        let own: Vec<Option<Vec<f64>>> = match mode {
            0 => vec![None; CLASSES],
            _ => self.classes.iter().map(|n| n.curve(MIN_CLASS_NODE_WEIGHT)).collect(),
        };
        let (classes, choice) = match mode {
            0 => (own, ClassChoice::default()),
            1 | 2 => {
                let choice = std::array::from_fn(|c| if own[c].is_some() { ClassUse::Own } else { ClassUse::Pooled });
                (own, choice)
            }
            _ => self.decided_classes(&values, own, keep),
        };
        Some(EdgeProfile { values, classes, choice, edges: self.edges })
    }

    /// Each class's profile where it differs from its parent's beyond its sampling noise
    /// ([`Nodes::differs`]): an orientation's profile against the pooled one, a class's own
    /// against its orientation's where that is used, else against the pooled one; or as
    /// `keep` says.
    fn decided_classes(
        &self,
        pooled: &[f64],
        own: Vec<Option<Vec<f64>>>,
        keep: Option<&ClassChoice>,
    ) -> (Vec<Option<Vec<f64>>>, ClassChoice) {
        let mut classes = vec![None; CLASSES];
        let mut choice = ClassChoice::default();
        for o in 0..2 {
            let group = &self.orientations[o];
            let oriented = group.curve(MIN_CLASS_NODE_WEIGHT);
            let use_oriented = match (keep, &oriented) {
                (Some(k), Some(_)) => k[4 * o..4 * o + 4].contains(&ClassUse::Orientation),
                (None, Some(_)) => group.differs(pooled, MIN_CLASS_NODE_WEIGHT),
                (_, None) => false,
            };
            let parent = if use_oriented { oriented.as_deref().unwrap_or(pooled) } else { pooled };
            for c in 4 * o..4 * o + 4 {
                let own_used = match (keep, &own[c]) {
                    (Some(k), Some(_)) => k[c] == ClassUse::Own,
                    (None, Some(_)) => self.classes[c].differs(parent, MIN_CLASS_NODE_WEIGHT),
                    (_, None) => false,
                };
                (classes[c], choice[c]) = if own_used {
                    (own[c].clone(), ClassUse::Own)
                } else if use_oriented {
                    (oriented.clone(), ClassUse::Orientation)
                } else {
                    (None, ClassUse::Pooled)
                };
            }
        }
        (classes, choice)
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
    fn uniform(seed: &mut u64) -> f64 {
        *seed ^= *seed << 13;
        *seed ^= *seed >> 7;
        *seed ^= *seed << 17;
        (*seed >> 11) as f64 / (1u64 << 53) as f64
    }

    /// A standard normal number (Box–Muller).
    fn gauss(seed: &mut u64) -> f64 {
        (-2.0 * uniform(seed).max(1e-12).ln()).sqrt() * (std::f64::consts::TAU * uniform(seed)).cos()
    }

    /// `n` samples a class of `esf` with Gaussian noise of σ `noise` (a fixed pseudo-random
    /// sequence), at phases spread over the profile, 25 samples an edge.
    fn noisy_samples(learner: &mut ProfileLearner, class: usize, esf: &dyn Fn(f64) -> f64, n: usize, noise: f64, seed: &mut u64) {
        for i in 0..n {
            let d = -2.99 + 5.98 * uniform(seed);
            learner.add_sample(class, d, esf(d) + noise * gauss(seed));
            if i % 25 == 24 {
                learner.close_edge();
            }
        }
        learner.close_edge();
    }

    /// `edges` edges' samples of `esf` as a pixel class sees a near-axis-aligned edge: every
    /// other column (distances `φ + 2j`, `φ` the edge's phase), 12 pixels at each (the rows),
    /// and what one edge's fit shares among its pixels — its distance off by `offset_px`
    /// (RMS) and its contrast by 1 % — besides each pixel's noise `noise`.
    fn edge_samples(
        learner: &mut ProfileLearner,
        class: usize,
        esf: &dyn Fn(f64) -> f64,
        edges: usize,
        offset_px: f64,
        noise: f64,
        seed: &mut u64,
    ) {
        for _ in 0..edges {
            let (phase, delta, scale) = (2.0 * uniform(seed), offset_px * gauss(seed), 1.0 + 0.01 * gauss(seed));
            for k in 0..3 {
                let d = -2.99 + phase + 2.0 * k as f64;
                for _ in 0..12 {
                    learner.add_sample(class, d, scale * esf(d + delta) + noise * gauss(seed));
                }
            }
            learner.close_edge();
        }
    }

    #[test]
    fn a_class_is_taken_for_a_shape_difference_not_for_its_edges_shared_errors() {
        // 100 edges a class (a camera seeing 25 tags, or a few frames of one seeing ten), each edge's pixels
        // sharing its distance error (0.03 px RMS) and contrast error (1 %), pixel noise 1.5 %
        // of the contrast. Counted as independent pixels these errors looked like a shape.
        let learn = |sigma_of: &dyn Fn(usize) -> f64| {
            let mut learner = ProfileLearner::default();
            let mut seed = 0x9e37_79b9_7f4a_7c15_u64;
            for c in 0..CLASSES {
                edge_samples(&mut learner, c, &gaussian_esf(sigma_of(c), 0.0), 100, 0.03, 0.015, &mut seed);
            }
            learner.edges = MIN_EDGES;
            learner
        };
        let same = learn(&|_| 0.6).build_in(3, None).expect("enough samples");
        assert_eq!(same.choice(), [ClassUse::Pooled; CLASSES], "one profile with shared per-edge errors");
        // A real shape difference under the same errors: one parity of each orientation blurred
        // more (a mosaic), and the orientations differing (an astigmatic blur).
        let mosaic = learn(&|c| if c % 2 == 1 { 0.8 } else { 0.5 }).build_in(3, None).expect("enough samples");
        assert_eq!(mosaic.choice(), [ClassUse::Own; CLASSES], "each parity differs from the pooled mix");
        let astig = learn(&|c| if c < 4 { 0.5 } else { 0.8 }).build_in(3, None).expect("enough samples");
        assert_eq!(astig.choice(), [ClassUse::Orientation; CLASSES]);
    }

    #[test]
    fn a_class_is_used_only_where_it_differs_from_its_parent_beyond_its_sampling_noise() {
        // ~12 samples a node per class (the first frame of a camera seeing ten tags), noise
        // 0.015 of the contrast (σ 2 grey levels on a contrast of 130).
        let (n, noise) = (600, 0.015);
        let (sharp, wide) = (gaussian_esf(0.5, 0.0), gaussian_esf(0.8, 0.0));
        let learn = |esf_of: &dyn Fn(usize) -> f64| {
            let mut learner = ProfileLearner::default();
            let mut seed = 0x2545_f491_4f6c_dd1d_u64;
            for c in 0..CLASSES {
                let sigma = esf_of(c);
                noisy_samples(&mut learner, c, &gaussian_esf(sigma, 0.0), n, noise, &mut seed);
            }
            learner.edges = MIN_EDGES;
            learner
        };
        // One profile everywhere: every class keeps the pooled one (its own would only add
        // its sampling noise).
        let same = learn(&|_| 0.6).build_in(3, None).expect("enough samples");
        assert_eq!(same.choice(), [ClassUse::Pooled; CLASSES]);
        assert_eq!(same.own_classes(), 0);
        // An astigmatic blur: the two orientations differ, the parities do not.
        let astig = learn(&|c| if c < 4 { 0.5 } else { 0.8 });
        let p = astig.build_in(3, None).expect("enough samples");
        assert_eq!(p.choice(), [ClassUse::Orientation; CLASSES]);
        for d in [-0.6, -0.2, 0.3] {
            assert!((p.class_value_slope(1, d).0 - sharp(d)).abs() < 0.01, "orientation 0 at {d}");
            assert!((p.class_value_slope(6, d).0 - wide(d)).abs() < 0.01, "orientation 1 at {d}");
        }
        // A mosaic: one parity of each orientation differs.
        let mosaic = learn(&|c| if c % 2 == 1 { 0.8 } else { 0.5 }).build_in(3, None).expect("enough samples");
        assert_eq!(mosaic.choice(), [ClassUse::Own; CLASSES], "each parity differs from the pooled mix");
        // A decision made earlier is kept by a rebuild, whatever the samples say now.
        let kept = astig.build_in(3, Some(&[ClassUse::Pooled; CLASSES])).expect("enough samples");
        assert_eq!(kept.choice(), [ClassUse::Pooled; CLASSES]);
        assert_eq!(kept.class_value_slope(6, 0.3), kept.value_slope(0.3));
        // Pooled mode never classes; the forced modes use every class with samples enough.
        assert_eq!(astig.build_in(0, None).unwrap().own_classes(), 0);
        assert_eq!(astig.build_in(2, None).unwrap().choice(), [ClassUse::Own; CLASSES]);
    }
}
