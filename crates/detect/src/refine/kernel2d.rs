//! The camera's image formation as a small 2-D kernel after the pixel's area (a measurement
//! switch, `TAGDEFLECT_EDGE_MODEL=kernel2d`; docs/accuracy.md, "The edge's bias against its
//! angle and its phase").
//!
//! A pixel's value near a straight edge is modelled as its neighbours' white area fractions
//! weighted by a 5 × 5 kernel `K` (sum 1, centroid on the pixel):
//!
//! ```text
//! I = B + C · Σ_o K_o · A(d + n·o)
//! ```
//!
//! `o` the tap's pixel offset, `n` the edge's unit normal (towards white), `d` the pixel
//! centre's distance from the edge and `A` the white fraction of a unit pixel at that
//! distance — exact for a straight edge at any angle (the distribution of `n·u` over the
//! pixel is the sum of two uniform ones, of widths `|n_x|` and `|n_y|`). What a camera does
//! after the pixel with a discrete kernel (sharpening, a blur over the pixels) is then
//! exactly such a `K`, whatever the edge's angle; a bilinear demosaic is one per 2 × 2
//! mosaic site (`kernel2d-sites`). Unlike a tabulated profile, the model has the pixel's
//! kinks exactly where they are and 25 numbers to learn, not a node every 1/8 px.
//!
//! `K` is learned by linear least squares from the same samples as the profile (each
//! well-fitted edge's pixels, `(I − B) / C` against their distance from the fitted line):
//! the normal equations are accumulated per site, and solved with the sum and the centroid
//! constrained and a small ridge on each tap, growing with its squared distance from the
//! centre (near-aligned edges see only the kernel's sums across the edge; the ridge settles
//! what they do not see by putting each sum's weight nearest the pixel: a cross for the
//! sharpening, not the smallest kernel of those sums, which mispredicted a 1° edge by 2 % of
//! the contrast near the pixel's kinks).

use nalgebra::{DMatrix, DVector, Vector2};
use tagdeflect_core::frame::GrayImage;

use super::formation::{response, Light};

/// The kernel's reach, pixels (5 × 5 taps).
const RADIUS: i32 = 2;
/// Taps of the kernel.
pub const TAPS: usize = ((2 * RADIUS + 1) * (2 * RADIUS + 1)) as usize;
/// Mosaic sites (`x % 2 + 2 (y % 2)`).
pub const SITES: usize = 4;
/// Samples a site needs before its kernel is solved.
const MIN_SAMPLES: f64 = 500.0;
/// The ridge, relative to the normal equations' mean diagonal, on each tap times its squared
/// distance from the centre (a compact kernel is preferred).
const RIDGE: f64 = 1e-4;

/// Which edge model the switch asks for: 0 (the default, or `profile`) the learned profile,
/// 1 one kernel, 2 a kernel per mosaic site, 3 the physical formation with one kernel
/// (`formation`), 4 (`formation-sites`) the formation with a kernel per mosaic site where
/// that pays, each camera taking it only where it predicts held-out edges better than its
/// profile ([`super::formation`]; docs/accuracy.md, "The physical formation": it wins or ties
/// on every formation, but it is not the default — its light search costs three quarters of
/// the frame sets a second, and on the sharp low-noise scene the displacement's σ under-covers
/// under it: "The formation as the default: measured, and why not yet").
pub fn kernel_mode() -> u8 {
    static MODE: std::sync::OnceLock<u8> = std::sync::OnceLock::new();
    *MODE.get_or_init(|| match std::env::var("TAGDEFLECT_EDGE_MODEL").as_deref() {
        Ok("profile") => 0,
        Ok("kernel2d") => 1,
        Ok("kernel2d-sites") => 2,
        Ok("formation") => 3,
        Ok("formation-sites") => 4,
        _ => 0,
    })
}

/// The tap offsets `(x, y)`, row-major.
pub(super) fn offsets() -> impl Iterator<Item = (f64, f64)> {
    (-RADIUS..=RADIUS).flat_map(|y| (-RADIUS..=RADIUS).map(move |x| (x as f64, y as f64)))
}

/// The white fraction of a unit pixel whose centre is `t` from an edge with normal
/// components of magnitudes `a ≥ b`, and its derivative in `t`.
#[inline(always)]
pub(super) fn area(t: f64, a: f64, b: f64) -> (f64, f64) {
    if b < 1e-6 {
        let x = t / a + 0.5;
        return if x <= 0.0 {
            (0.0, 0.0)
        } else if x >= 1.0 {
            (1.0, 0.0)
        } else {
            (x, 1.0 / a)
        };
    }
    let x = t + 0.5 * (a + b);
    let ab = a * b;
    if x <= 0.0 {
        (0.0, 0.0)
    } else if x <= b {
        (x * x / (2.0 * ab), x / ab)
    } else if x <= a {
        ((x - 0.5 * b) / a, 1.0 / a)
    } else if x < a + b {
        let r = a + b - x;
        (1.0 - r * r / (2.0 * ab), r / ab)
    } else {
        (1.0, 0.0)
    }
}

/// The normal's magnitudes, larger first.
pub(super) fn widths(normal: &Vector2<f64>) -> (f64, f64) {
    let (x, y) = (normal.x.abs(), normal.y.abs());
    (x.max(y), x.min(y))
}

/// A mosaic site of pixel `index` in an image `width` wide.
pub fn site_of(index: usize, width: u32) -> usize {
    let w = width.max(1) as usize;
    (index % w) % 2 + 2 * ((index / w) % 2)
}

/// Whether the camera clipped pixel `index` (its 8-bit level at 0 or 255): a linear model
/// does not hold there (a sharpened edge's overshoot).
pub fn clipped(image: &GrayImage, index: usize) -> bool {
    matches!(image.data.get(index), Some(0 | 255))
}

/// The learned kernels: one, or one per mosaic site.
#[derive(Debug, Clone, PartialEq)]
pub struct Kernel2d {
    taps: Vec<[f64; TAPS]>,
    /// The light's side before the pixel (blur and aperture), `None`: the whole pixel's
    /// area of a sharp image.
    light: Option<Light>,
}

impl Kernel2d {
    /// The identity (a pixel's own area: a sharp camera).
    pub fn identity() -> Self {
        let mut k = [0.0; TAPS];
        k[TAPS / 2] = 1.0;
        Self { taps: vec![k], light: None }
    }

    /// Kernels given tap by tap (row-major, 5 × 5): one, or one per mosaic site.
    pub fn from_taps(taps: Vec<[f64; TAPS]>) -> Self {
        assert!(taps.len() == 1 || taps.len() == SITES, "one kernel or one per site");
        Self { taps, light: None }
    }

    /// These kernels after the light's side `light` (blur before the pixel, aperture).
    pub fn with_light(self, light: Light) -> Self {
        Self { light: Some(light), ..self }
    }

    /// The light's side before the pixel, when modelled ([`super::formation`]).
    pub fn light(&self) -> Option<&Light> {
        self.light.as_ref()
    }

    /// The kernel of mosaic site `site` (`site` 0 when there is one).
    pub fn site(&self, site: usize) -> &[f64; TAPS] {
        &self.taps[if self.taps.len() == SITES { site } else { 0 }]
    }

    /// The model along an edge of unit normal `normal` (towards white).
    pub fn along(&self, normal: &Vector2<f64>) -> EdgeKernel<'_> {
        let ((a, b), sigma) = match &self.light {
            Some(l) => (l.widths(normal), l.sigma_across(normal)),
            None => (widths(normal), 0.0),
        };
        let mut delta = [0.0; TAPS];
        for (d, (x, y)) in delta.iter_mut().zip(offsets()) {
            *d = normal.x * x + normal.y * y;
        }
        EdgeKernel { kernel: self, delta, a, b, sigma }
    }
}

/// A kernel along one edge: the taps' offsets across it, the aperture's projected widths
/// and the blur's σ across it (0: none).
pub struct EdgeKernel<'a> {
    kernel: &'a Kernel2d,
    delta: [f64; TAPS],
    a: f64,
    b: f64,
    sigma: f64,
}

impl EdgeKernel<'_> {
    /// The model's `P(d)` and `dP/dd` at a pixel of mosaic site `site`, `d` from the edge
    /// (positive towards white); `mirrored`: the inner edge of the white bits, whose white
    /// side is the other way (`d` then measured towards it).
    #[inline(always)]
    pub fn value_slope(&self, site: usize, d: f64, mirrored: bool) -> (f64, f64) {
        let k = self.kernel.site(site);
        let s = if mirrored { -1.0 } else { 1.0 };
        let (mut v, mut g) = (0.0, 0.0);
        for (w, delta) in k.iter().zip(&self.delta) {
            if *w != 0.0 {
                let (av, ag) = response(d + s * delta, self.a, self.b, self.sigma);
                v += w * av;
                g += w * ag;
            }
        }
        (v, g)
    }
}

/// The kernels' normal equations, per site.
#[derive(Debug, Clone)]
pub struct KernelLearner {
    ata: Vec<DMatrix<f64>>,
    aty: Vec<DVector<f64>>,
    count: Vec<f64>,
}

impl Default for KernelLearner {
    fn default() -> Self {
        Self { ata: vec![DMatrix::zeros(TAPS, TAPS); SITES], aty: vec![DVector::zeros(TAPS); SITES], count: vec![0.0; SITES] }
    }
}

impl KernelLearner {
    /// Adds the sample `v = (I − B) / C` of a pixel of mosaic site `site`, `d` from the
    /// fitted edge of unit normal `normal`.
    pub fn add(&mut self, site: usize, normal: &Vector2<f64>, d: f64, v: f64) {
        let (a, b) = widths(normal);
        let mut row = [0.0; TAPS];
        for (r, (x, y)) in row.iter_mut().zip(offsets()) {
            *r = area(d + normal.x * x + normal.y * y, a, b).0;
        }
        self.add_row(site, &row, v);
    }

    /// Adds the sample `v` of a pixel of mosaic site `site` whose taps' responses are `row`.
    pub(super) fn add_row(&mut self, site: usize, row: &[f64; TAPS], v: f64) {
        // The lower triangle, column by column (nalgebra's storage order).
        let (ata, aty) = (self.ata[site].as_mut_slice(), self.aty[site].as_mut_slice());
        for (i, col) in ata.chunks_exact_mut(TAPS).enumerate() {
            let ri = row[i];
            if ri == 0.0 {
                continue;
            }
            aty[i] += ri * v;
            for (c, r) in col[i..].iter_mut().zip(&row[i..]) {
                *c += ri * r;
            }
        }
        self.count[site] += 1.0;
    }

    /// The kernels (one over every site's samples, or one per site), or `None` while a
    /// site has too few samples.
    pub fn solve(&self, per_site: bool) -> Option<Kernel2d> {
        let groups: Vec<Vec<usize>> = if per_site { (0..SITES).map(|s| vec![s]).collect() } else { vec![(0..SITES).collect()] };
        let taps = groups.iter().map(|g| self.solve_sites(g)).collect::<Option<Vec<_>>>()?;
        Some(Kernel2d { taps, light: None })
    }

    /// One kernel from the samples of `sites`: least squares with the sum 1 and the
    /// centroid 0 (a Lagrange system), and the ridge.
    fn solve_sites(&self, sites: &[usize]) -> Option<[f64; TAPS]> {
        let mut ata = DMatrix::<f64>::zeros(TAPS, TAPS);
        let mut aty = DVector::<f64>::zeros(TAPS);
        let mut n = 0.0;
        for &s in sites {
            ata += &self.ata[s];
            aty += &self.aty[s];
            n += self.count[s];
        }
        if n < MIN_SAMPLES * sites.len() as f64 {
            return None;
        }
        for i in 0..TAPS {
            for j in 0..i {
                ata[(j, i)] = ata[(i, j)];
            }
        }
        let ridge = RIDGE * ata.trace() / TAPS as f64;
        let m = TAPS + 3;
        let mut kkt = DMatrix::<f64>::zeros(m, m);
        let mut rhs = DVector::<f64>::zeros(m);
        kkt.view_mut((0, 0), (TAPS, TAPS)).copy_from(&ata);
        for (i, (x, y)) in offsets().enumerate() {
            kkt[(i, i)] += ridge * (x * x + y * y);
            rhs[i] = aty[i];
            for (c, g) in [1.0, x, y].into_iter().enumerate() {
                kkt[(i, TAPS + c)] = g;
                kkt[(TAPS + c, i)] = g;
            }
        }
        rhs[TAPS] = 1.0;
        let x = kkt.lu().solve(&rhs)?;
        let mut k = [0.0; TAPS];
        k.iter_mut().zip(x.iter()).for_each(|(k, x)| *k = *x);
        k.iter().all(|v| v.is_finite()).then_some(k)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A unit pixel's white area by sub-sampling.
    fn area_sampled(t: f64, normal: &Vector2<f64>) -> f64 {
        let n = 400;
        let mut white = 0;
        for i in 0..n {
            for j in 0..n {
                let u = Vector2::new((i as f64 + 0.5) / n as f64 - 0.5, (j as f64 + 0.5) / n as f64 - 0.5);
                white += usize::from(normal.dot(&u) + t > 0.0);
            }
        }
        white as f64 / (n * n) as f64
    }

    #[test]
    fn a_pixels_white_area_and_its_slope_match_sub_sampling_at_any_angle() {
        for deg in [0.0f64, 0.7, 12.0, 30.0, 45.0, 63.0] {
            let normal = Vector2::new(deg.to_radians().sin(), deg.to_radians().cos());
            let (a, b) = widths(&normal);
            for t in [-0.9, -0.6, -0.31, -0.05, 0.0, 0.2, 0.44, 0.7] {
                let (v, g) = area(t, a, b);
                assert!((v - area_sampled(t, &normal)).abs() < 3e-3, "{deg}° at {t}: {v}");
                let h = 1e-6;
                let fd = (area(t + h, a, b).0 - area(t - h, a, b).0) / (2.0 * h);
                assert!((g - fd).abs() < 1e-4, "{deg}° at {t}: slope {g} against {fd}");
            }
        }
    }

    /// The pixels of a straight edge (normal at `deg` from y, offset `c`) through the 3 × 3
    /// sharpening kernel of amount 1: (site, normal, d, value) of the pixels near the edge.
    fn sharpened_edge(deg: f64, c: f64) -> Vec<(usize, Vector2<f64>, f64, f64)> {
        let normal = Vector2::new(deg.to_radians().sin(), deg.to_radians().cos());
        let (a, b) = widths(&normal);
        let at = |x: i32, y: i32| area(normal.x * x as f64 + normal.y * y as f64 - c, a, b).0;
        let mut out = Vec::new();
        for y in -6..=6 {
            for x in -12..=12 {
                let v = 2.0 * at(x, y) - 0.25 * (at(x - 1, y) + at(x + 1, y) + at(x, y - 1) + at(x, y + 1));
                let d = normal.x * x as f64 + normal.y * y as f64 - c;
                if d.abs() < 2.5 {
                    out.push((((x & 1) + 2 * (y & 1)) as usize, normal, d, v));
                }
            }
        }
        out
    }

    #[test]
    fn a_sharpening_kernel_is_learned_from_near_aligned_edges_and_predicts_another_one() {
        let mut learner = KernelLearner::default();
        for (k, deg) in [0.3, 0.8, 1.4, 89.2, 89.7, 90.5].into_iter().enumerate() {
            for j in 0..8 {
                for (site, normal, d, v) in sharpened_edge(deg, 0.13 * j as f64 + 0.05 * k as f64) {
                    learner.add(site, &normal, d, v);
                }
            }
        }
        let kernel = learner.solve(false).expect("enough samples");
        // The kernel's sums across a near-horizontal edge are the sharpening's: −1/4, 3/2, −1/4.
        let k = kernel.site(0);
        let row = |y: usize| (0..5).map(|x| k[5 * y + x]).sum::<f64>();
        for (y, want) in [(1, -0.25), (2, 1.5), (3, -0.25)] {
            assert!((row(y) - want).abs() < 2e-3, "row {y}: {}", row(y));
        }
        // An edge at an angle and phases not among those learned, within their range, is
        // predicted to 0.5 % of the contrast (measured 0.37 %; at 3°, beyond them, 0.79 %:
        // the kernel's structure along the edge is what near-aligned edges see least; with a
        // plain ridge towards zero 1.8 % and 4.2 %).
        let worst = |deg: f64| {
            sharpened_edge(deg, 0.37)
                .iter()
                .map(|(site, normal, d, v)| (kernel.along(normal).value_slope(*site, *d, false).0 - v).abs())
                .fold(0.0, f64::max)
        };
        println!("worst misfit at 1.1°: {:.4}, at 3°: {:.4}", worst(1.1), worst(3.0));
        assert!(worst(1.1) < 0.005, "worst misfit at 1.1°: {}", worst(1.1));
    }
}
