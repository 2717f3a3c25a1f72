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

use nalgebra::{Matrix3, Matrix5, Point2, Vector2, Vector5};

use super::apriltag::DetectError;
use super::Detection;
use crate::camera::{apply_homography, CameraIntrinsics, Lens, Undistorted};
use crate::frame::GrayImage;
use crate::tags::cell_homography;

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
    refine_corners_warm(image, det, Lens::new(intrinsics), opts, &mut [None; 4])
}

/// Each edge's fitted black level, contrast and blur width (`None`: not fitted), edges in
/// SPEC order from the bottom edge; the warm start of the next fit of the same tag.
pub type EdgeLevels = [Option<[f64; 3]>; 4];

/// [`refine_corners_with`] through `lens` (e.g. one with the camera's [`IdealPixelMap`](crate::camera::IdealPixelMap)),
/// started from `levels` (e.g. the same tag's fit in the previous frame: the fit then needs
/// fewer iterations), which are replaced by this fit's.
pub fn refine_corners_warm(
    image: &GrayImage,
    det: &mut Detection,
    lens: Lens<'_>,
    opts: &RefineOptions,
    levels: &mut EdgeLevels,
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
    for _ in 0..opts.passes {
        let Some(h) = cell_homography(&ideal, nb) else {
            return keep_all;
        };
        let Some(hinv) = h.try_inverse() else {
            return keep_all;
        };
        let mut lines: [Option<Line>; 4] = [None; 4];
        for (e, line) in lines.iter_mut().enumerate() {
            *line = fit_edge(image, &lens, &ideal, &h, &hinv, nb, e, opts, levels[e]);
        }
        *levels = lines.map(|l| l.map(|l| l.levels));
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

/// Inverse of [`edge_to_tag`].
fn tag_to_edge(e: usize, t: &Vector2<f64>, nb: f64) -> (f64, f64) {
    match e {
        0 => (t.x, nb - t.y),
        1 => (nb - t.y, nb - t.x),
        2 => (nb - t.x, t.y),
        _ => (t.y, t.x),
    }
}

/// One pixel used by an edge fit.
struct Sample {
    /// Position relative to the edge's first corner, along the edge (px, ideal).
    t: f64,
    /// Position relative to the edge line, outwards (px, ideal).
    n: f64,
    /// Pixel value.
    value: f64,
    /// Distance (px) from the edge to the inner side of the border bit here.
    gap: f64,
    /// The data bit inside the border here is white.
    white: bool,
    /// Weight (tapers to 0 over 1 px at the band's limits, so the fit is continuous in the
    /// corners it starts from).
    weight: f64,
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

/// Fits edge `e` (from corner `e` to corner `e+1`); `None` when the fit is not trustworthy.
#[allow(clippy::too_many_arguments)]
fn fit_edge(
    image: &GrayImage,
    lens: &Lens,
    ideal: &[Vector2<f64>; 4],
    h: &Matrix3<f64>,
    hinv: &Matrix3<f64>,
    nb: f64,
    e: usize,
    opts: &RefineOptions,
    warm: Option<[f64; 3]>,
) -> Option<Line> {
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
    let (mut white_ref, mut black_ref, mut nref) = (0.0, 0.0, 0.0);
    for k in 0..nbits {
        let along = k as f64 + 0.5;
        let p0 = to_px(along, 0.0)?;
        let p1 = to_px(along, 1.0)?;
        gap[k] = (p1 - p0).dot(&-normal).abs().max(0.5);
        let sample = |u: Vector2<f64>| {
            let p = lens.ideal_to_pixel(&u);
            image.sample(p.x, p.y)
        };
        inner_val[k] = sample(to_px(along, 1.5)?);
        white_ref += sample(to_px(along, -0.5)?);
        black_ref += sample(to_px(along, 0.5)?);
        nref += 1.0;
    }
    white_ref /= nref;
    black_ref /= nref;
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
    let mut samples: Vec<Sample> = Vec::with_capacity(((x1 - x0 + 1) * (y1 - y0 + 1) / 2) as usize);
    let stride = image.width as usize;
    let checker = len > opts.checker_above_px;
    for y in y0..=y1 {
        let mut prev: Option<Undistorted> = None;
        for x in x0..=x1 {
            // Long edges have pixels to spare: a checkerboard half keeps the fit unbiased.
            if checker && (x + y) % 2 == 1 {
                continue;
            }
            let p = Vector2::new(x as f64, y as f64);
            if poly_edges.iter().any(|(n, r)| orient * (n.dot(&p) - r) > pad) {
                continue;
            }
            let u = lens.pixel_centre_to_ideal(x, y, &mut prev);
            let Some(tag) = apply_homography(hinv, &u) else { continue };
            let (along, depth) = tag_to_edge(e, &tag, nb);
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
            let value = image.data[y as usize * stride + x as usize] as f64;
            let d = u - a;
            samples.push(Sample { t: d.dot(&dir), n: d.dot(&normal), value, gap: gap[k], white: white[k], weight });
        }
    }
    if samples.len() < 12 || samples.iter().map(|s| s.weight).sum::<f64>() < 8.0 {
        return None;
    }

    // Levenberg–Marquardt over (angle, offset, B, C, sigma).
    let mut x = match warm {
        Some([bl, c, sg]) => Vector5::new(0.0, 0.0, bl, c, sg),
        None => Vector5::new(0.0, 0.0, black_ref, contrast0, 0.8),
    };
    // One pass over the samples gives the cost and the normal equations of the model
    // I = B + C·(Φ(n/σ) + white·Φ((−n − gap)/σ)), n = n₀·cos a + t·sin a − offset.
    // JᵀWJ is symmetric: only its upper triangle is accumulated, written out (the
    // Jacobian's B column is 1).
    let table: &[[f64; 8]] = &PHI_TABLE;
    let normal_eq = |x: &Vector5<f64>| -> (f64, Matrix5<f64>, Vector5<f64>) {
        let (sn, cs) = x[0].sin_cos();
        let (off, bl, c, inv_sg) = (x[1], x[2], x[3], 1.0 / x[4]);
        let mut u = [0.0f64; 15];
        let mut g = [0.0f64; 5];
        let mut cost = 0.0;
        for s in &samples {
            let n = s.n * cs + s.t * sn - off;
            let dn_dang = -s.n * sn + s.t * cs;
            let z1 = n * inv_sg;
            let (cdf1, pdf1) = phi_pdf_in(table, z1);
            let mut val = cdf1;
            let mut dval_dn = pdf1 * inv_sg;
            let mut dval_ds = -z1 * pdf1 * inv_sg;
            if s.white {
                let z2 = (-n - s.gap) * inv_sg;
                let (cdf2, pdf2) = phi_pdf_in(table, z2);
                val += cdf2;
                dval_dn -= pdf2 * inv_sg;
                dval_ds -= z2 * pdf2 * inv_sg;
            }
            let r = bl + c * val - s.value;
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
        let mut jtj = Matrix5::<f64>::zeros();
        let mut k = 0;
        for a in 0..5 {
            for b in a..5 {
                jtj[(a, b)] = u[k];
                jtj[(b, a)] = u[k];
                k += 1;
            }
        }
        (cost, jtj, Vector5::from(g))
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
        // Converged when the edge would no longer move (1e-4 px, a hundredth of the corner
        // noise; the 3 × 1080p bench gives the same figures as with 1e-5 px) and the blur
        // has settled: the last, tiny step is taken without evaluating the cost again.
        if moved < 1e-4 && step[4].abs() < 1e-2 {
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
    finish(&x, &samples, current, contrast0, bit_px, a, dir, normal)
}

/// Checks a fitted edge and turns it into a line.
#[allow(clippy::too_many_arguments)]
fn finish(
    x: &Vector5<f64>,
    samples: &[Sample],
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
    use crate::tags::TagFamily;

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
