//! Band selection: which pixels near an edge of a tag's black square its fit uses, where
//! each lies relative to the edge and to which bit (through the lens map and the
//! homography of the current corners), and with what weight; and the bands a tag's fit
//! leaves for its next frame ([`TagBands`]).

use nalgebra::{Matrix3, Vector2};

use super::RefineOptions;
use tagdeflect_core::camera::{apply_homography, Lens, Undistorted};
use tagdeflect_core::frame::GrayImage;

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
pub(super) struct BandPixel {
    /// Position relative to the edge's first corner, along the edge (px, ideal).
    pub(super) t: f64,
    /// Position relative to the edge line, outwards (px, ideal).
    pub(super) n: f64,
    /// Index of the pixel in the image's data.
    pub(super) index: usize,
    /// Distance (px) from the edge to the inner side of the border bit here.
    pub(super) gap: f64,
    /// A white data bit lies within two bits along the edge, inside: the pixel may see its
    /// blurred inner edge and is fitted with the model's second edge (weighted by
    /// `fit::along_white`).
    pub(super) white: bool,
    /// The bit along the edge the pixel lies beside.
    pub(super) cell: u32,
    /// Weight (tapers to 0 over 1 px at the band's limits, so the fit is continuous in the
    /// corners it starts from).
    pub(super) weight: f64,
}

/// The pixels an edge is fitted on, chosen around the corners of the pass that selected
/// them, and the frame of the fit (first corner `a`, direction, outward normal).
#[derive(Debug, Clone)]
pub(super) struct EdgeBand {
    pub(super) a: Vector2<f64>,
    pub(super) dir: Vector2<f64>,
    pub(super) normal: Vector2<f64>,
    /// Edge length, px (ideal).
    pub(super) len: f64,
    /// Bit width along the edge, px.
    pub(super) bit_px: f64,
    /// Per bit along the edge, where the white ring and the black border are sampled
    /// (distorted pixels): the contrast reference of every fit on this band.
    pub(super) refs: Vec<[Vector2<f64>; 2]>,
    /// Where each bit along the edge begins (px along the edge from `a`, at the border bit's
    /// inner side, so perspective is followed), one more for where the last ends.
    pub(super) bounds: Vec<f64>,
    /// Per bit along the edge, whether the data bit inside the border is white.
    pub(super) white_cells: Vec<bool>,
    /// The pixels, those that cannot see a white data bit first.
    pub(super) pixels: Vec<BandPixel>,
    /// How many pixels come first.
    pub(super) black: usize,
}

/// The bands of a tag's four edges and the corners (ideal) they were selected around:
/// reused by the tag's next fit while its corners stay within
/// [`RefineOptions::band_reuse_px`] of these (see [`EdgeMemory`]).
#[derive(Debug)]
pub(super) struct TagBands {
    pub(super) corners: [Vector2<f64>; 4],
    pub(super) image_size: (u32, u32),
    pub(super) nb: f64,
    pub(super) edges: [EdgeBand; 4],
}

impl TagBands {
    /// Whether a fit of `image` around `corners` may use these bands.
    pub(super) fn serve(&self, image: &GrayImage, nb: f64, corners: &[Vector2<f64>; 4], within_px: f64) -> bool {
        within_px > 0.0
            && self.image_size == (image.width, image.height)
            && self.nb == nb
            && self.corners.iter().zip(corners).all(|(a, b)| (a - b).norm() <= within_px)
    }
}

/// 1 inside `[lo, hi]` more than 1 px from its ends, tapering linearly to 0 at the ends.
fn taper(x: f64, lo: f64, hi: f64) -> f64 {
    ((x - lo).min(hi - x)).clamp(0.0, 1.0)
}

/// Selects the band of edge `e` (from corner `e` to corner `e+1`) around the corners
/// `ideal`; `None` when the edge cannot be fitted (too short, too few pixels, no contrast).
#[allow(clippy::too_many_arguments)]
pub(super) fn select_band(
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
    // Where each cell begins along the edge (px from `a`), at the border bit's inner side.
    let bounds: Vec<f64> = (0..=nbits).map(|j| to_px(j as f64, 1.0).map(|p| (p - a).dot(&dir))).collect::<Option<_>>()?;
    let (white_ref, black_ref) = reference_levels(image, &refs);
    let contrast0 = white_ref - black_ref;
    if contrast0.abs() < 4.0 {
        return None;
    }
    let threshold = 0.5 * (white_ref + black_ref);
    // Border cells (the first and last `border_bits`) are black inside; data cells are read
    // from the image (behind a 2-bit border they read black too).
    let bb = opts.border_bits.max(1) as usize;
    let white: Vec<bool> =
        (0..nbits).map(|k| k >= bb && k + bb < nbits && ((inner_val[k] - threshold) * contrast0.signum()) > 0.0).collect();

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
            let near_white = white[k.saturating_sub(2)..=(k + 2).min(nbits - 1)].iter().any(|&w| w);
            pixels.push(BandPixel { t: d.dot(&dir), n: d.dot(&normal), index, gap: gap[k], white: near_white, cell: k as u32, weight });
        }
    }
    if pixels.len() < 12 || pixels.iter().map(|s| s.weight).sum::<f64>() < 8.0 {
        return None;
    }
    // Pixels that cannot see a white data bit first (see `NormalSums::add`).
    let (mut pixels, beside_white): (Vec<BandPixel>, Vec<BandPixel>) = pixels.into_iter().partition(|p| !p.white);
    let black = pixels.len();
    pixels.extend(beside_white);
    Some(EdgeBand { a, dir, normal, len, bit_px, refs, bounds, white_cells: white, pixels, black })
}

/// The grey level of the pixel at `index` of `image`: the one place the edge fits and the
/// profile's samples read pixel values: a full-depth frame's level scaled to 0–255.
#[inline(always)]
pub(super) fn pixel_value(image: &GrayImage, index: usize) -> f64 {
    f64::from(image.level(index))
}

/// The values of `band`'s pixels in `image` (see [`pixel_value`]).
pub(super) fn band_values(image: &GrayImage, band: &EdgeBand) -> Vec<f64> {
    band.pixels.iter().map(|p| pixel_value(image, p.index)).collect()
}

/// Mean grey level of the white ring and of the black border at `refs` (one pair per bit
/// along the edge, distorted pixels).
pub(super) fn reference_levels(image: &GrayImage, refs: &[[Vector2<f64>; 2]]) -> (f64, f64) {
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

/// Test support: a band of one pixel at `(t, n)` from the edge (beside a white bit when
/// `white`), on an edge along x with its outward normal y, bits 4 px wide.
#[cfg(test)]
pub(super) fn one_pixel_band(t: f64, n: f64, white: bool) -> EdgeBand {
    let pixel = BandPixel { t, n, index: 0, gap: 4.0, white, cell: (t / 4.0) as u32, weight: 0.8 };
    EdgeBand {
        a: Vector2::zeros(),
        dir: Vector2::new(1.0, 0.0),
        normal: Vector2::new(0.0, 1.0),
        len: 20.0,
        bit_px: 4.0,
        refs: Vec::new(),
        bounds: vec![0.0, 4.0, 8.0, 12.0, 16.0, 20.0],
        white_cells: vec![false, true, true, false, true],
        pixels: vec![pixel],
        black: usize::from(!white),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
}
