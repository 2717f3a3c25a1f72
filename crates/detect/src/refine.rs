//! Sub-pixel corner refinement: fits each edge of a tag's black square to the image.
//!
//! The AprilTag library's corners scatter by about 0.08 px; the measurement needs several
//! times better. For each of the four edges this module fits a blurred-step edge model to the
//! raw pixel values in a band along the edge (away from the corners), by Levenberg–Marquardt
//! over the line's angle and offset, the two grey levels and the blur width:
//!
//! ```text
//! I(n) = B + C · ( S(n) + white · S(−n − g) ),   S(x) = Φ(x / σ)
//! ```
//!
//! where `n` is the signed distance (pixels, outwards positive) of the pixel centre from the
//! edge line, and the second term models the data bit just inside the 1-bit black border when
//! that bit is white (`g` = local bit width; the bit colours are read from the image, so no
//! family table is needed). Adjacent edge lines are then intersected for the corners.
//!
//! Pixels are used at their centres (OpenCV convention) with their own values — no
//! interpolation, which would smooth and bias. With a [`CameraIntrinsics`] the fit runs in
//! undistorted ("ideal") pixel coordinates, where the edges are straight, and the corners are
//! mapped back to distorted pixels. Tag coordinates (which bit a pixel belongs to) come from
//! the homography of the current corners, so the bands follow perspective exactly.
//!
//! Robustness: an edge whose fit fails (too few pixels, no contrast, implausible blur, large
//! residual) leaves its two corners as they were, and a corner that would move more than
//! [`RefineOptions::max_shift_px`] keeps the library's value; both are counted in the
//! [`RefineReport`].
//!
//! **Pixels kept between frames.** Selecting a band's pixels (which pixel lies where
//! relative to the edge and to which bit, through the lens map and the homography) costs
//! as much as fitting them. A tracked tag's fit leaves its selection in an [`EdgeMemory`];
//! the next frame's fit of the same tag reuses it while the corners it starts from are
//! within [`RefineOptions::band_reuse_px`] (0.1 px) of those the selection was made
//! around, reading only the new pixel values. The fit stays continuous in the corners
//! it starts from (tapered weights), so a selection made 0.1 px away changes the result by
//! a small fraction of that: the 3 × 1080p benches (clean and noisy, tags moving up to
//! 0.17 px per frame) give the same displacement RMS to 0.0001 mm with reuse and without,
//! while 0.25 px already worsens the net deflection RMS by 0.0002 mm. In a real test the
//! specimen moves a few µm per frame, so nearly every fit reuses its pixels.

use nalgebra::{Matrix3, Matrix5, Point2, Vector2, Vector5};

use super::apriltag::DetectError;
use super::Detection;
use tagdeflect_core::camera::{apply_homography, CameraIntrinsics, Lens, Undistorted};
use tagdeflect_core::frame::GrayImage;
use tagdeflect_core::tags::cell_homography;

/// Options of the sub-pixel refinement.
#[derive(Debug, Clone, PartialEq)]
pub struct RefineOptions {
    /// A corner that would move further than this (pixels) keeps its input value.
    pub max_shift_px: f64,
    /// How deep into the tag the band reaches, in bits (at most 2 − margin: beyond the
    /// first data bit lie unknown bits).
    pub inner_band_bits: f64,
    /// How far out of the tag the band reaches, in bits (at most the 1-bit white ring).
    pub outer_band_bits: f64,
    /// Distance (pixels) kept from the corners along each edge and from unknown neighbours.
    pub margin_px: f64,
    /// Tags whose bits are narrower than this (pixels) are not refined.
    pub min_bit_px: f64,
    /// The band never reaches further than this from the edge (pixels), inwards or outwards:
    /// enough for the blur, and it bounds the cost on large tags.
    pub max_band_px: f64,
    /// Edges longer than this (pixels) use every other pixel (checkerboard) to bound the cost.
    pub checker_above_px: f64,
    /// Refinement passes (each re-selects the pixels around the previous pass's edges).
    pub passes: u32,
    /// A tag's next fit reuses the pixels its last fit was selected on while its starting
    /// corners stay within this distance (pixels) of that selection's (0: always select
    /// anew); see [`refine_corners_warm`].
    pub band_reuse_px: f64,
}

impl Default for RefineOptions {
    fn default() -> Self {
        Self {
            max_shift_px: 1.5,
            inner_band_bits: 1.5,
            outer_band_bits: 0.8,
            margin_px: 2.0,
            min_bit_px: 2.0,
            max_band_px: 6.0,
            checker_above_px: 120.0,
            passes: 2,
            band_reuse_px: 0.1,
        }
    }
}

impl RefineOptions {
    /// Checks the options' ranges.
    pub fn validate(&self) -> Result<(), DetectError> {
        let bad = |name, value: f64, expected| Err(DetectError::BadOption { name, value: value.to_string(), expected });
        if !(self.max_shift_px > 0.0 && self.max_shift_px.is_finite()) {
            return bad("subpixel.max_shift_px", self.max_shift_px, "expected a positive number of pixels");
        }
        if !(self.inner_band_bits > 0.2 && self.inner_band_bits <= 2.0) {
            return bad("subpixel.inner_band_bits", self.inner_band_bits, "expected 0.2 to 2.0 bits");
        }
        if !(self.outer_band_bits > 0.2 && self.outer_band_bits <= 1.0) {
            return bad("subpixel.outer_band_bits", self.outer_band_bits, "expected 0.2 to 1.0 bits");
        }
        if !(self.margin_px >= 0.0 && self.margin_px <= 20.0) {
            return bad("subpixel.margin_px", self.margin_px, "expected 0 to 20 pixels");
        }
        if !(self.min_bit_px >= 1.0 && self.min_bit_px.is_finite()) {
            return bad("subpixel.min_bit_px", self.min_bit_px, "expected at least 1 pixel");
        }
        if !(self.max_band_px >= 2.0 && self.max_band_px <= 100.0) {
            return bad("subpixel.max_band_px", self.max_band_px, "expected 2 to 100 pixels");
        }
        if self.checker_above_px.is_nan() || self.checker_above_px < 0.0 {
            return bad("subpixel.checker_above_px", self.checker_above_px, "expected a length in pixels (0 = always)");
        }
        if !(self.band_reuse_px >= 0.0 && self.band_reuse_px <= 2.0) {
            return bad("subpixel.band_reuse_px", self.band_reuse_px, "expected 0 to 2 pixels");
        }
        if self.passes == 0 || self.passes > 10 {
            return bad("subpixel.passes", self.passes as f64, "expected 1 to 10");
        }
        Ok(())
    }
}

/// What happened to one detection's corners.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct RefineReport {
    /// Corners replaced by refined values.
    pub refined: u8,
    /// Corners that kept their input value (fit failed, or moved too far).
    pub kept: u8,
    /// Of `kept`: corners kept because an adjacent edge fit failed or was implausible.
    pub failed_fit: u8,
    /// Of `kept`: corners kept because the refined corner moved more than `max_shift_px`.
    pub too_far: u8,
}

/// Refinement counts over many detections.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct RefineStats {
    /// Detections processed.
    pub tags: u64,
    /// Corners refined.
    pub corners_refined: u64,
    /// Corners that kept the library's value.
    pub corners_kept: u64,
    /// Of `corners_kept`: because an edge fit failed.
    pub failed_fit: u64,
    /// Of `corners_kept`: because the refined corner moved too far.
    pub too_far: u64,
}

impl RefineStats {
    /// Adds one detection's report.
    pub fn add(&mut self, r: &RefineReport) {
        self.tags += 1;
        self.corners_refined += r.refined as u64;
        self.corners_kept += r.kept as u64;
        self.failed_fit += r.failed_fit as u64;
        self.too_far += r.too_far as u64;
    }
}

/// Refines a detection's corners with the default options (see the module docs).
pub fn refine_corners(image: &GrayImage, det: &mut Detection, intrinsics: Option<&CameraIntrinsics>) -> RefineReport {
    refine_corners_with(image, det, intrinsics, &RefineOptions::default())
}

/// Refines a detection's corners in place; corners whose refinement fails or moves too far
/// keep their value. `intrinsics` (optional) straightens lens distortion during the fit.
pub fn refine_corners_with(
    image: &GrayImage,
    det: &mut Detection,
    intrinsics: Option<&CameraIntrinsics>,
    opts: &RefineOptions,
) -> RefineReport {
    refine_corners_warm(image, det, Lens::new(intrinsics), opts, &mut EdgeMemory::default())
}

/// Each edge's fitted black level, contrast and blur width (`None`: not fitted), edges in
/// SPEC order from the bottom edge; the warm start of the next fit of the same tag.
pub type EdgeLevels = [Option<[f64; 3]>; 4];

/// [`refine_corners_with`] through `lens` (e.g. one with the camera's [`IdealPixelMap`](tagdeflect_core::camera::IdealPixelMap)),
/// started from `memory` (the same tag's fit in the previous frame, or the default): the
/// edges' levels are the LM's warm start (fewer iterations), and when the corners to start
/// from are within [`RefineOptions::band_reuse_px`] of those the remembered pixels were
/// selected around, the first pass fits those pixels again instead of selecting them anew.
/// `memory` is replaced by this fit's.
pub fn refine_corners_warm(
    image: &GrayImage,
    det: &mut Detection,
    lens: Lens<'_>,
    opts: &RefineOptions,
    memory: &mut EdgeMemory,
) -> RefineReport {
    let keep_all = RefineReport { refined: 0, kept: 4, failed_fit: 4, too_far: 0 };
    if image.width < 4 || image.height < 4 || image.data.len() < image.width as usize * image.height as usize {
        return keep_all;
    }
    if det.corners.iter().any(|c| !(c.x.is_finite() && c.y.is_finite())) {
        return keep_all;
    }
    let nb = det.family.width_at_border() as f64;
    let original = det.corners;
    // Corners in ideal coordinates.
    let mut ideal: [Vector2<f64>; 4] = original.map(|c| lens.pixel_to_ideal(&c.coords, None));
    let mut ok_edges = [false; 4];
    memory.reused = false;
    for pass in 0..opts.passes {
        let reuse = pass == 0 && memory.bands.as_ref().is_some_and(|b| b.serve(image, nb, &ideal, opts.band_reuse_px));
        let mut fresh: [Option<EdgeBand>; 4] = [None, None, None, None];
        if !reuse {
            let Some(h) = cell_homography(&ideal, nb) else {
                return keep_all;
            };
            let Some(hinv) = h.try_inverse() else {
                return keep_all;
            };
            for (e, band) in fresh.iter_mut().enumerate() {
                *band = select_band(image, &lens, &ideal, &h, &hinv, nb, e, opts);
            }
        }
        let mut lines: [Option<Line>; 4] = [None; 4];
        for (e, line) in lines.iter_mut().enumerate() {
            let band = match (&memory.bands, reuse) {
                (Some(b), true) => Some(&b.edges[e]),
                _ => fresh[e].as_ref(),
            };
            *line = band.and_then(|b| fit_band(image, b, memory.levels[e]));
        }
        memory.levels = lines.map(|l| l.map(|l| l.levels));
        memory.reused |= reuse;
        if !reuse {
            // Remembered only when every edge has its band.
            memory.bands = match fresh {
                [Some(e0), Some(e1), Some(e2), Some(e3)] => Some(std::sync::Arc::new(TagBands {
                    corners: ideal,
                    image_size: (image.width, image.height),
                    nb,
                    edges: [e0, e1, e2, e3],
                })),
                _ => None,
            };
        }
        ok_edges = lines.map(|l| l.is_some());
        let mut next = ideal;
        for (i, c) in next.iter_mut().enumerate() {
            // Corner i lies between edge i−1 (ending at it) and edge i (starting at it).
            if let (Some(a), Some(b)) = (lines[(i + 3) % 4], lines[i]) {
                if let Some(p) = a.intersect(&b) {
                    *c = p;
                }
            }
        }
        ideal = next;
    }
    let mut report = RefineReport::default();
    for i in 0..4 {
        let edges_ok = ok_edges[(i + 3) % 4] && ok_edges[i];
        let p = lens.ideal_to_pixel(&ideal[i]);
        let shift = (p - original[i].coords).norm();
        if !(edges_ok && p.x.is_finite() && p.y.is_finite()) {
            report.kept += 1;
            report.failed_fit += 1;
        } else if shift > opts.max_shift_px {
            report.kept += 1;
            report.too_far += 1;
        } else {
            det.corners[i] = Point2::from(p);
            report.refined += 1;
        }
    }
    report
}

/// A line `normal · p = rho` in ideal coordinates (unit normal).
#[derive(Debug, Clone, Copy)]
struct Line {
    normal: Vector2<f64>,
    rho: f64,
    /// Fitted black level, contrast and blur (warm start of the next pass).
    levels: [f64; 3],
}

impl Line {
    fn intersect(&self, other: &Line) -> Option<Vector2<f64>> {
        let det = self.normal.x * other.normal.y - self.normal.y * other.normal.x;
        if det.abs() < 0.1 {
            return None;
        }
        let x = (self.rho * other.normal.y - other.rho * self.normal.y) / det;
        let y = (self.normal.x * other.rho - other.normal.x * self.rho) / det;
        Some(Vector2::new(x, y))
    }
}

/// Tag coordinates of edge `e` (SPEC order: bottom, right, top, left edge): maps
/// (along, depth) in bits — along from the edge's first corner, depth inwards — to tag (x, y).
fn edge_to_tag(e: usize, along: f64, depth: f64, nb: f64) -> Vector2<f64> {
    match e {
        0 => Vector2::new(along, nb - depth),
        1 => Vector2::new(nb - depth, nb - along),
        2 => Vector2::new(nb - along, depth),
        _ => Vector2::new(depth, along),
    }
}

/// [`tag_to_edge`] as a matrix on homogeneous tag coordinates.
fn edge_axes(e: usize, nb: f64) -> Matrix3<f64> {
    match e {
        0 => Matrix3::new(1.0, 0.0, 0.0, 0.0, -1.0, nb, 0.0, 0.0, 1.0),
        1 => Matrix3::new(0.0, -1.0, nb, -1.0, 0.0, nb, 0.0, 0.0, 1.0),
        2 => Matrix3::new(-1.0, 0.0, nb, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0),
        _ => Matrix3::new(0.0, 1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0),
    }
}

/// Inverse of [`edge_to_tag`] (what [`edge_axes`] does in the fit; kept as the reference).
#[cfg(test)]
fn tag_to_edge(e: usize, t: &Vector2<f64>, nb: f64) -> (f64, f64) {
    match e {
        0 => (t.x, nb - t.y),
        1 => (nb - t.y, nb - t.x),
        2 => (nb - t.x, t.y),
        _ => (t.y, t.x),
    }
}

/// One pixel of an edge's band: where it lies relative to the edge, what it sees of the tag
/// there, and its weight — everything but its value.
#[derive(Debug, Clone, Copy)]
struct BandPixel {
    /// Position relative to the edge's first corner, along the edge (px, ideal).
    t: f64,
    /// Position relative to the edge line, outwards (px, ideal).
    n: f64,
    /// Index of the pixel in the image's data.
    index: usize,
    /// Distance (px) from the edge to the inner side of the border bit here.
    gap: f64,
    /// The data bit inside the border here is white.
    white: bool,
    /// Weight (tapers to 0 over 1 px at the band's limits, so the fit is continuous in the
    /// corners it starts from).
    weight: f64,
}

/// The pixels an edge is fitted on, chosen around the corners of the pass that selected
/// them, and the frame of the fit (first corner `a`, direction, outward normal).
#[derive(Debug, Clone)]
struct EdgeBand {
    a: Vector2<f64>,
    dir: Vector2<f64>,
    normal: Vector2<f64>,
    /// Edge length, px (ideal).
    len: f64,
    /// Bit width along the edge, px.
    bit_px: f64,
    /// Per bit along the edge, where the white ring and the black border are sampled
    /// (distorted pixels): the contrast reference of every fit on this band.
    refs: Vec<[Vector2<f64>; 2]>,
    /// The pixels, those beside a black data bit (or the black corner cells) first.
    pixels: Vec<BandPixel>,
    /// How many pixels come first.
    black: usize,
}

/// The bands of a tag's four edges and the corners (ideal) they were selected around:
/// reused by the tag's next fit while its corners stay within
/// [`RefineOptions::band_reuse_px`] of these (see [`EdgeMemory`]).
#[derive(Debug)]
pub struct TagBands {
    corners: [Vector2<f64>; 4],
    image_size: (u32, u32),
    nb: f64,
    edges: [EdgeBand; 4],
}

impl TagBands {
    /// Whether a fit of `image` around `corners` may use these bands.
    fn serve(&self, image: &GrayImage, nb: f64, corners: &[Vector2<f64>; 4], within_px: f64) -> bool {
        within_px > 0.0
            && self.image_size == (image.width, image.height)
            && self.nb == nb
            && self.corners.iter().zip(corners).all(|(a, b)| (a - b).norm() <= within_px)
    }
}

/// What a tag's fit in one frame leaves for the same tag's fit in the next frame of the
/// same camera: each edge's levels (the LM's warm start) and the pixels it used.
#[derive(Debug, Clone, Default)]
pub struct EdgeMemory {
    /// Each edge's fitted levels.
    pub levels: EdgeLevels,
    bands: Option<std::sync::Arc<TagBands>>,
    reused: bool,
}

impl PartialEq for EdgeMemory {
    /// Equal levels and the very same remembered pixels.
    fn eq(&self, other: &Self) -> bool {
        let same_bands = match (&self.bands, &other.bands) {
            (Some(a), Some(b)) => std::sync::Arc::ptr_eq(a, b),
            (None, None) => true,
            _ => false,
        };
        self.levels == other.levels && self.reused == other.reused && same_bands
    }
}

impl EdgeMemory {
    /// Whether the fit that left this memory reused the pixels selected in an earlier frame.
    pub fn reused_bands(&self) -> bool {
        self.reused
    }
}

/// 1 inside `[lo, hi]` more than 1 px from its ends, tapering linearly to 0 at the ends.
fn taper(x: f64, lo: f64, hi: f64) -> f64 {
    ((x - lo).min(hi - x)).clamp(0.0, 1.0)
}

/// Beyond |x| = [`PHI_MAX`] the standard normal CDF is 0 or 1 and the density 0 to within
/// 1e-16 (the band's far pixels cost nothing).
const PHI_MAX: f64 = 8.5;
/// Nodes of the [`PHI_TABLE`] per unit of `x`.
const PHI_NODES_PER_UNIT: f64 = 64.0;

/// Per interval `[i/64, (i+1)/64]`, `i = 0 .. 8.5 · 64`, the cubic Hermite interpolants
/// of Φ and of φ in `t ∈ [0, 1]` as polynomial coefficients `[Φ: c0..c3, φ: d0..d3]`,
/// built from the values at the nodes and the exact slopes (Φ′ = φ, φ′ = −xφ), so both are
/// within ~1e-10 of the true functions. Φ at the nodes is integrated from φ by Simpson's
/// rule on 16 sub-intervals per interval (error ~1e-18).
static PHI_TABLE: std::sync::LazyLock<Vec<[f64; 8]>> = std::sync::LazyLock::new(|| {
    let h = 1.0 / PHI_NODES_PER_UNIT;
    let n = (PHI_MAX * PHI_NODES_PER_UNIT) as usize;
    let pdf = |z: f64| (-0.5 * z * z).exp() * 0.398_942_280_401_432_7;
    let mut nodes = Vec::with_capacity(n + 1);
    let mut cdf = 0.5;
    for i in 0..=n {
        let z = i as f64 * h;
        nodes.push((z, cdf, pdf(z)));
        let sub = 16;
        let dz = h / sub as f64;
        let mut acc = pdf(z) + pdf(z + h);
        for k in 1..sub {
            acc += if k % 2 == 1 { 4.0 } else { 2.0 } * pdf(z + k as f64 * dz);
        }
        cdf += acc * dz / 3.0;
    }
    // Hermite from values f0, f1 and slopes m0, m1 (per unit of t).
    let cubic = |f0: f64, f1: f64, m0: f64, m1: f64| [f0, m0, 3.0 * (f1 - f0) - 2.0 * m0 - m1, 2.0 * (f0 - f1) + m0 + m1];
    nodes
        .windows(2)
        .map(|w| {
            let ((z0, c0, p0), (z1, c1, p1)) = (w[0], w[1]);
            let c = cubic(c0, c1, h * p0, h * p1);
            let d = cubic(p0, p1, -h * z0 * p0, -h * z1 * p1);
            [c[0], c[1], c[2], c[3], d[0], d[1], d[2], d[3]]
        })
        .collect()
});

/// Standard normal CDF and density at `x` (see [`phi_pdf_in`]).
#[cfg(test)]
fn phi_pdf(x: f64) -> (f64, f64) {
    phi_pdf_in(&PHI_TABLE, x)
}

/// Standard normal CDF and density at `x` from `table` ([`PHI_TABLE`]): two cubics in the
/// position within the interval (no `exp` and no division in the edge fit's inner loop).
/// Exactly antisymmetric about 0 (Φ(−x) = 1 − Φ(x)), so it adds no bias.
#[inline(always)]
fn phi_pdf_in(table: &[[f64; 8]], x: f64) -> (f64, f64) {
    let a = x.abs();
    if a.is_nan() || a >= PHI_MAX {
        return (if x > 0.0 { 1.0 } else { 0.0 }, 0.0);
    }
    let u = a * PHI_NODES_PER_UNIT;
    // 0 ≤ u < 544: truncation is the floor, and interval i exists.
    let i = u as usize;
    let t = u - i as f64;
    let k = &table[i];
    let cdf = k[0] + t * (k[1] + t * (k[2] + t * k[3]));
    let pdf = k[4] + t * (k[5] + t * (k[6] + t * k[7]));
    if x >= 0.0 {
        (cdf, pdf)
    } else {
        (1.0 - cdf, pdf)
    }
}

/// Selects the band of edge `e` (from corner `e` to corner `e+1`) around the corners
/// `ideal`; `None` when the edge cannot be fitted (too short, too few pixels, no contrast).
#[allow(clippy::too_many_arguments)]
fn select_band(
    image: &GrayImage,
    lens: &Lens,
    ideal: &[Vector2<f64>; 4],
    h: &Matrix3<f64>,
    hinv: &Matrix3<f64>,
    nb: f64,
    e: usize,
    opts: &RefineOptions,
) -> Option<EdgeBand> {
    let a = ideal[e];
    let b = ideal[(e + 1) % 4];
    let len = (b - a).norm();
    if !(len.is_finite() && len > 1e-6) {
        return None;
    }
    let bit_px = len / nb;
    if bit_px < opts.min_bit_px {
        return None;
    }
    let dir = (b - a) / len;
    let centroid = (ideal[0] + ideal[1] + ideal[2] + ideal[3]) / 4.0;
    let mut normal = Vector2::new(-dir.y, dir.x);
    if (centroid - a).dot(&normal) > 0.0 {
        normal = -normal;
    }
    let nbits = nb as usize;

    // Local bit width (px) and colour of the data bit inside the border, per cell along the edge.
    let to_px = |along: f64, depth: f64| -> Option<Vector2<f64>> { apply_homography(h, &edge_to_tag(e, along, depth, nb)) };
    let mut gap = vec![bit_px; nbits];
    let mut inner_val = vec![0.0; nbits];
    let mut refs = Vec::with_capacity(nbits);
    for k in 0..nbits {
        let along = k as f64 + 0.5;
        let p0 = to_px(along, 0.0)?;
        let p1 = to_px(along, 1.0)?;
        gap[k] = (p1 - p0).dot(&-normal).abs().max(0.5);
        inner_val[k] = sample_at(image, lens.ideal_to_pixel(&to_px(along, 1.5)?));
        refs.push([lens.ideal_to_pixel(&to_px(along, -0.5)?), lens.ideal_to_pixel(&to_px(along, 0.5)?)]);
    }
    let (white_ref, black_ref) = reference_levels(image, &refs);
    let contrast0 = white_ref - black_ref;
    if contrast0.abs() < 4.0 {
        return None;
    }
    let threshold = 0.5 * (white_ref + black_ref);
    // Border cells (first and last) are black inside; data cells are read from the image.
    let white: Vec<bool> =
        (0..nbits).map(|k| k != 0 && k + 1 != nbits && ((inner_val[k] - threshold) * contrast0.signum()) > 0.0).collect();

    // Band limits, pixels (depth inwards positive) and bits.
    let inner_px = (opts.inner_band_bits * bit_px).min(2.0 * bit_px - opts.margin_px).min(opts.max_band_px);
    let outer_px = (opts.outer_band_bits * bit_px).min(bit_px - opts.margin_px).min(opts.max_band_px).max(1.5);
    let along_min_px = opts.margin_px.max(0.25 * bit_px);
    if inner_px <= 1.0 || len - 2.0 * along_min_px < 2.0 {
        return None;
    }
    let depth_max = inner_px / bit_px * 1.3;
    let depth_min = -outer_px / bit_px * 1.3;
    let (along_min, along_max) = (along_min_px / bit_px, nb - along_min_px / bit_px);

    // Candidate pixels: the band's bounding box in distorted pixels.
    let mut poly = Vec::with_capacity(4);
    for (al, de) in [(along_min, depth_min), (along_max, depth_min), (along_max, depth_max), (along_min, depth_max)] {
        poly.push(lens.ideal_to_pixel(&to_px(al, de)?));
    }
    let pad = 1.5;
    let xmin = poly.iter().map(|p| p.x).fold(f64::MAX, f64::min) - pad;
    let xmax = poly.iter().map(|p| p.x).fold(f64::MIN, f64::max) + pad;
    let ymin = poly.iter().map(|p| p.y).fold(f64::MAX, f64::min) - pad;
    let ymax = poly.iter().map(|p| p.y).fold(f64::MIN, f64::max) + pad;
    let x0 = xmin.ceil().max(0.0) as i64;
    let x1 = xmax.floor().min(image.width as f64 - 1.0) as i64;
    let y0 = ymin.ceil().max(0.0) as i64;
    let y1 = ymax.floor().min(image.height as f64 - 1.0) as i64;
    if x1 < x0 || y1 < y0 || (x1 - x0 + 1) * (y1 - y0 + 1) > 4_000_000 {
        return None;
    }
    // Convex polygon test (padded) to skip most of a diagonal band's bounding box.
    let poly_edges: Vec<(Vector2<f64>, f64)> = (0..4)
        .map(|i| {
            let p = poly[i];
            let q = poly[(i + 1) % 4];
            let d = q - p;
            let nrm = Vector2::new(d.y, -d.x).normalize();
            (nrm, nrm.dot(&p))
        })
        .collect();
    let orient = {
        let c = (poly[0] + poly[1] + poly[2] + poly[3]) / 4.0;
        if poly_edges.iter().all(|(n, r)| n.dot(&c) - r <= 0.0) {
            1.0
        } else {
            -1.0
        }
    };

    // About half of the bounding box lies in the band.
    let mut pixels: Vec<BandPixel> = Vec::with_capacity(((x1 - x0 + 1) * (y1 - y0 + 1) / 2) as usize);
    let stride = image.width as usize;
    let checker = len > opts.checker_above_px;
    // Ideal pixel → (along, depth, 1) of this edge, up to scale: the inverse homography
    // followed by the edge's axes.
    let to_edge = edge_axes(e, nb) * hinv;
    for y in y0..=y1 {
        // The row's pixels inside the padded polygon: each of its sides bounds x.
        let (mut lo, mut hi) = (x0 as f64, x1 as f64);
        for (n, r) in &poly_edges {
            // orient·(n·p − r) ≤ pad  ⇔  a·x ≤ b.
            let (a, b) = (orient * n.x, pad + orient * (r - n.y * y as f64));
            if a > 1e-12 {
                hi = hi.min(b / a);
            } else if a < -1e-12 {
                lo = lo.max(b / a);
            } else if b < 0.0 {
                hi = lo - 1.0;
            }
        }
        // (NaN bounds skip the row too.)
        if lo.partial_cmp(&hi).is_none_or(|o| o == std::cmp::Ordering::Greater) {
            continue;
        }
        let mut prev: Option<Undistorted> = None;
        for x in (lo.ceil() as i64).max(x0)..=(hi.floor() as i64).min(x1) {
            // Long edges have pixels to spare: a checkerboard half keeps the fit unbiased.
            if checker && (x + y) % 2 == 1 {
                continue;
            }
            let u = lens.pixel_centre_to_ideal(x, y, &mut prev);
            let Some(ad) = apply_homography(&to_edge, &u) else { continue };
            let (along, depth) = (ad.x, ad.y);
            if !(along.is_finite() && depth.is_finite()) || along < along_min || along > along_max || depth < depth_min || depth > depth_max
            {
                continue;
            }
            // `along` ≥ `along_min` > 0 here: truncation is the floor.
            let k = (along as usize).min(nbits - 1);
            let depth_px = depth * gap[k];
            let mut weight = taper(depth_px, -outer_px, inner_px) * taper(along * bit_px, along_min_px, len - along_min_px);
            // Deep pixels near a colour change between inner cells see an unmodelled edge.
            if depth > 0.5 {
                let frac = along - k as f64;
                if k > 0 && white[k - 1] != white[k] {
                    weight *= (frac * gap[k] - opts.margin_px + 1.0).clamp(0.0, 1.0);
                }
                if k + 1 < nbits && white[k + 1] != white[k] {
                    weight *= ((1.0 - frac) * gap[k] - opts.margin_px + 1.0).clamp(0.0, 1.0);
                }
            }
            if weight <= 0.0 {
                continue;
            }
            let d = u - a;
            let index = y as usize * stride + x as usize;
            pixels.push(BandPixel { t: d.dot(&dir), n: d.dot(&normal), index, gap: gap[k], white: white[k], weight });
        }
    }
    if pixels.len() < 12 || pixels.iter().map(|s| s.weight).sum::<f64>() < 8.0 {
        return None;
    }
    // Pixels beside black data bits first (see `NormalSums::add`).
    let (mut pixels, beside_white): (Vec<BandPixel>, Vec<BandPixel>) = pixels.into_iter().partition(|p| !p.white);
    let black = pixels.len();
    pixels.extend(beside_white);
    Some(EdgeBand { a, dir, normal, len, bit_px, refs, pixels, black })
}

/// Mean grey level of the white ring and of the black border at `refs` (one pair per bit
/// along the edge, distorted pixels).
fn reference_levels(image: &GrayImage, refs: &[[Vector2<f64>; 2]]) -> (f64, f64) {
    let (mut white, mut black) = (0.0, 0.0);
    for [w, b] in refs {
        white += sample_at(image, *w);
        black += sample_at(image, *b);
    }
    let n = refs.len() as f64;
    (white / n, black / n)
}

fn sample_at(image: &GrayImage, p: Vector2<f64>) -> f64 {
    image.sample(p.x, p.y)
}

/// Fits the edge model to the pixels of `band` in `image`; `None` when the fit is not
/// trustworthy. `warm`: the edge's levels from an earlier fit.
fn fit_band(image: &GrayImage, band: &EdgeBand, warm: Option<[f64; 3]>) -> Option<Line> {
    let EdgeBand { a, dir, normal, len, bit_px, .. } = *band;
    let (white_ref, black_ref) = reference_levels(image, &band.refs);
    let contrast0 = white_ref - black_ref;
    if contrast0.abs() < 4.0 {
        return None;
    }
    let values: Vec<f64> = band.pixels.iter().map(|p| image.data[p.index] as f64).collect();

    // Levenberg–Marquardt over (angle, offset, B, C, sigma).
    let mut x = match warm {
        Some([bl, c, sg]) => Vector5::new(0.0, 0.0, bl, c, sg),
        None => Vector5::new(0.0, 0.0, black_ref, contrast0, 0.8),
    };
    // One pass over the samples gives the cost and the normal equations (`NormalSums`);
    // JᵀWJ is symmetric: only its upper triangle is accumulated, written out.
    let table: &[[f64; 8]] = &PHI_TABLE;
    let (plain, beside_white) = band.pixels.split_at(band.black);
    let (plain_values, beside_white_values) = values.split_at(band.black);
    let normal_eq = |x: &Vector5<f64>| -> (f64, Matrix5<f64>, Vector5<f64>) {
        let mut sums = NormalSums::default();
        sums.add::<false>(plain, plain_values, x, table);
        sums.add::<true>(beside_white, beside_white_values, x, table);
        let u = &sums.u;
        let mut jtj = Matrix5::<f64>::zeros();
        let mut k = 0;
        for a in 0..5 {
            for b in a..5 {
                jtj[(a, b)] = u[k];
                jtj[(b, a)] = u[k];
                k += 1;
            }
        }
        (sums.cost, jtj, Vector5::from(sums.g))
    };
    let (mut current, mut jtj, mut jtr) = normal_eq(&x);
    let mut lambda = 1e-6;
    for _ in 0..40 {
        let mut damped = jtj;
        for d in 0..5 {
            damped[(d, d)] += lambda * jtj[(d, d)].max(1e-9);
        }
        let Some(step) = damped.cholesky().map(|c| c.solve(&(-jtr))) else {
            lambda *= 10.0;
            if lambda > 1e8 {
                break;
            }
            continue;
        };
        let moved = step[0].abs() * len + step[1].abs();
        let mut cand = x + step;
        cand[4] = cand[4].clamp(0.05, 3.0 * bit_px + 5.0);
        // Converged when the step would move the edge by less than 1e-3 px (a tenth of the
        // corner noise; Gauss–Newton converges quadratically here, so what remains after
        // this step is far smaller; the 3 × 1080p benches, clean and noisy, give the same
        // figures to the last digit as with 1e-4 px, for a quarter fewer evaluations) and
        // the blur has settled: the last, tiny step is taken without evaluating the cost.
        if moved < 1e-3 && step[4].abs() < 1e-2 {
            x = cand;
            break;
        }
        let (c, j2, r2) = normal_eq(&cand);
        if c.is_finite() && c <= current {
            x = cand;
            current = c;
            jtj = j2;
            jtr = r2;
            lambda = (lambda * 0.1).max(1e-9);
        } else {
            lambda *= 10.0;
            if lambda > 1e8 {
                break;
            }
        }
    }
    finish(&x, &band.pixels, current, contrast0, bit_px, a, dir, normal)
}

/// The weighted cost and normal equations of an edge fit, accumulated over samples.
#[derive(Default)]
struct NormalSums {
    cost: f64,
    /// Upper triangle of JᵀWJ, row by row.
    u: [f64; 15],
    /// JᵀWr.
    g: [f64; 5],
}

impl NormalSums {
    /// Adds `samples` with their `values` (all with `white` equal to `WHITE`: the samples are partitioned so
    /// that the loop has no data-dependent branch) at parameters `x` = (angle, offset, B,
    /// C, σ) of the model I = B + C·(Φ(n/σ) + white·Φ((−n − gap)/σ)),
    /// n = n₀·cos a + t·sin a − offset. The Jacobian's B column is 1.
    #[inline(always)]
    fn add<const WHITE: bool>(&mut self, samples: &[BandPixel], values: &[f64], x: &Vector5<f64>, table: &[[f64; 8]]) {
        let (sn, cs) = x[0].sin_cos();
        let (off, bl, c, inv_sg) = (x[1], x[2], x[3], 1.0 / x[4]);
        let (mut u, mut g, mut cost) = (self.u, self.g, self.cost);
        for (s, &value) in samples.iter().zip(values) {
            debug_assert_eq!(s.white, WHITE);
            let n = s.n * cs + s.t * sn - off;
            let dn_dang = -s.n * sn + s.t * cs;
            let z1 = n * inv_sg;
            let (cdf1, pdf1) = phi_pdf_in(table, z1);
            let mut val = cdf1;
            let mut dval_dn = pdf1 * inv_sg;
            let mut dval_ds = -z1 * pdf1 * inv_sg;
            if WHITE {
                let z2 = (-n - s.gap) * inv_sg;
                let (cdf2, pdf2) = phi_pdf_in(table, z2);
                val += cdf2;
                dval_dn -= pdf2 * inv_sg;
                dval_ds -= z2 * pdf2 * inv_sg;
            }
            let r = bl + c * val - value;
            let (j0, j1, j3, j4) = (c * dval_dn * dn_dang, -c * dval_dn, val, c * dval_ds);
            let w = s.weight;
            cost += w * r * r;
            let (w0, w1, w3, w4) = (j0 * w, j1 * w, j3 * w, j4 * w);
            u[0] += w0 * j0;
            u[1] += w0 * j1;
            u[2] += w0;
            u[3] += w0 * j3;
            u[4] += w0 * j4;
            u[5] += w1 * j1;
            u[6] += w1;
            u[7] += w1 * j3;
            u[8] += w1 * j4;
            u[9] += w;
            u[10] += w * j3;
            u[11] += w * j4;
            u[12] += w3 * j3;
            u[13] += w3 * j4;
            u[14] += w4 * j4;
            g[0] += w0 * r;
            g[1] += w1 * r;
            g[2] += w * r;
            g[3] += w3 * r;
            g[4] += w4 * r;
        }
        (self.u, self.g, self.cost) = (u, g, cost);
    }
}

/// Checks a fitted edge and turns it into a line.
#[allow(clippy::too_many_arguments)]
fn finish(
    x: &Vector5<f64>,
    samples: &[BandPixel],
    cost: f64,
    contrast0: f64,
    bit_px: f64,
    a: Vector2<f64>,
    dir: Vector2<f64>,
    normal: Vector2<f64>,
) -> Option<Line> {
    let (ang, off, c, sg) = (x[0], x[1], x[3], x[4]);
    let wsum: f64 = samples.iter().map(|s| s.weight).sum();
    let rms = (cost / wsum.max(1e-9)).sqrt();
    let plausible = ang.abs() < 0.2
        && off.abs() < 3.0
        && c * contrast0 > 0.0
        && c.abs() >= 0.3 * contrast0.abs()
        && c.abs() >= 4.0
        && sg > 0.1
        && sg < 0.6 * bit_px + 2.0
        && rms < 0.3 * c.abs();
    if !plausible {
        return None;
    }
    let (sn, cs) = ang.sin_cos();
    // n = (p − a)·(cs·normal + sn·dir) − off = 0.
    let nrm = normal * cs + dir * sn;
    Some(Line { normal: nrm, rho: nrm.dot(&a) + off, levels: [x[2], c, sg] })
}

#[cfg(test)]
mod tests {
    use super::*;
    use tagdeflect_core::tags::TagFamily;

    #[test]
    fn phi_matches_known_values() {
        let phi = |x| phi_pdf(x).0;
        assert!((phi(0.0) - 0.5).abs() < 1e-15);
        assert!((phi(1.0) - 0.841_344_746_068_543).abs() < 1e-10);
        assert!((phi(-1.96) - 0.024_997_895_148_220_4).abs() < 1e-10);
        assert!((phi(3.0) - 0.998_650_101_968_370).abs() < 1e-10);
        assert!((phi(8.4) - 1.0).abs() < 1e-13 && phi_pdf(8.4).1 < 1e-15, "{:?}", phi_pdf(8.4));
        // Continuous at and between nodes, with the density as its slope.
        for x in [0.0078125, 0.5, 1.234, 2.0 + 1.0 / 128.0, 5.5] {
            let d = 1e-6;
            let slope = (phi(x + d) - phi(x - d)) / (2.0 * d);
            assert!((slope - phi_pdf(x).1).abs() < 1e-8, "slope at {x}");
        }
        assert!((phi_pdf(1.0).1 - 0.241_970_725).abs() < 3e-9);
        assert_eq!(phi_pdf(9.0), (1.0, 0.0));
        assert_eq!(phi_pdf(-9.0), (0.0, 0.0));
        for x in [0.3, 1.7, 4.0] {
            assert!((phi(x) + phi(-x) - 1.0).abs() < 1e-15, "antisymmetry at {x}");
        }
    }

    #[test]
    fn edge_tag_maps_are_inverse() {
        for e in 0..4 {
            let t = edge_to_tag(e, 2.3, 0.7, 8.0);
            let (al, de) = tag_to_edge(e, &t, 8.0);
            assert!((al - 2.3).abs() < 1e-12 && (de - 0.7).abs() < 1e-12, "edge {e}");
            let m = edge_axes(e, 8.0) * nalgebra::Vector3::new(t.x, t.y, 1.0);
            assert!((m.x - 2.3).abs() < 1e-12 && (m.y - 0.7).abs() < 1e-12 && m.z == 1.0, "edge {e}: {m:?}");
        }
        // Edge 0 starts at the bottom-left corner and runs to the bottom-right one.
        assert_eq!(edge_to_tag(0, 0.0, 0.0, 8.0), Vector2::new(0.0, 8.0));
        assert_eq!(edge_to_tag(1, 0.0, 0.0, 8.0), Vector2::new(8.0, 8.0));
        assert_eq!(edge_to_tag(2, 0.0, 0.0, 8.0), Vector2::new(8.0, 0.0));
        assert_eq!(edge_to_tag(3, 0.0, 0.0, 8.0), Vector2::new(0.0, 0.0));
    }

    #[test]
    fn options_validate() {
        assert!(RefineOptions::default().validate().is_ok());
        assert!(RefineOptions { passes: 0, ..Default::default() }.validate().is_err());
        assert!(RefineOptions { max_shift_px: f64::NAN, ..Default::default() }.validate().is_err());
    }

    #[test]
    fn flat_image_keeps_corners() {
        let img = GrayImage { width: 100, height: 100, data: vec![128; 10_000] };
        let mut det = Detection {
            family: TagFamily::Tag36h11,
            id: 0,
            corners: [Point2::new(20.0, 80.0), Point2::new(80.0, 80.0), Point2::new(80.0, 20.0), Point2::new(20.0, 20.0)],
            decision_margin: 50.0,
            hamming: 0,
        };
        let before = det.corners;
        let r = refine_corners(&img, &mut det, None);
        assert_eq!(r, RefineReport { refined: 0, kept: 4, failed_fit: 4, too_far: 0 });
        assert_eq!(det.corners, before);
    }
}
