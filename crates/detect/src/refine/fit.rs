//! The edge-model fit: Levenberg–Marquardt of the blurred-step model (see the parent
//! module's docs) to the values of a band's pixels, on a tabulated normal CDF and density,
//! and the fitted edge line.

use nalgebra::{Matrix5, Vector2, Vector5};

use super::band::{band_values, reference_levels, BandPixel, EdgeBand};
use super::lm::{minimize, EdgeModel};
use tagdeflect_core::frame::GrayImage;

/// A line `normal · p = rho` in ideal coordinates (unit normal).
#[derive(Debug, Clone, Copy)]
pub(super) struct Line {
    normal: Vector2<f64>,
    rho: f64,
    /// Fitted black level, contrast and blur (warm start of the next pass).
    pub(super) levels: [f64; 3],
    /// Weighted RMS residual of the fit, grey levels.
    pub(super) rms: f64,
}

impl Line {
    /// Signed distance (pixels, outwards positive) of the ideal point `p` from the line.
    pub(super) fn distance(&self, p: &Vector2<f64>) -> f64 {
        self.normal.dot(p) - self.rho
    }

    pub(super) fn intersect(&self, other: &Line) -> Option<Vector2<f64>> {
        let det = self.normal.x * other.normal.y - self.normal.y * other.normal.x;
        if det.abs() < 0.1 {
            return None;
        }
        let x = (self.rho * other.normal.y - other.rho * self.normal.y) / det;
        let y = (self.normal.x * other.rho - other.normal.x * self.rho) / det;
        Some(Vector2::new(x, y))
    }
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
#[inline(always)]
pub(super) fn phi_pdf(x: f64) -> (f64, f64) {
    phi_pdf_in(&PHI_TABLE, x)
}

/// The along-edge factor of the white data bits' inner edge for a pixel at `t_px` (pixels
/// along the edge from its first corner, beside bit `cell`): the blurred indicator of the
/// white bits along the edge, `Σ_white j [Φ((t − t_j)/σ) − Φ((t − t_{j+1})/σ)]` with `t_j`
/// where bit `j` begins (`bounds`) and `σ` the blur (pixels). Inside a long run of white bits
/// it is 1, beside a black bit far from white ones 0; near a colour change it is what a
/// blurred square's corner gives: with a Gaussian blur the white square
/// `{t ∈ [t_j, t_{j+1}], depth > 1 bit}` blurs to the product of its two edges' profiles, so
/// the model's second edge times this factor is exact there. Modelled as 0/1 instead, the
/// second edge ran at full strength to the very end of a white bit and was absent beside
/// it: too bright on the white side of every colour change, which the fit met by pulling
/// the whole edge inwards — by more the smaller the bits in pixels, so the far side of a
/// tilted board shrank more than the near side, and a calibration on a tag board came out
/// with fx low (docs/calibration.md).
pub(super) fn along_white(table: &[[f64; 8]], white: &[bool], bounds: &[f64], t_px: f64, cell: usize, blur_px: f64) -> f64 {
    let inv = 1.0 / blur_px;
    let mut w = 0.0;
    // Bits further than two away contribute less than Φ(−2 bits / σ) (bits ≥ 2 px: < 1e-3).
    for j in cell.saturating_sub(2)..=(cell + 2).min(white.len() - 1) {
        if white[j] {
            w += (phi_pdf_in(table, (t_px - bounds[j]) * inv).0 - phi_pdf_in(table, (t_px - bounds[j + 1]) * inv).0).abs();
        }
    }
    w.clamp(0.0, 1.0)
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

/// Effective blur (pixels, as the plain model fits it) below which an edge's fit models the
/// pixel's area: the blurred step averaged over one pixel across the edge ([`pixel_step`]).
/// Every sensor integrates light over its pixels; a Gaussian blur of a fitted width absorbs
/// that while the optics blur more than the pixel (an edge of 0.6 px optical blur fits
/// ~0.67 px, the box's variance 1/12 px² added), but a sharper edge's profile is a ramp, not
/// a Gaussian step, and a Gaussian fitted to a ramp sampled at pixel centres is biased by the
/// edge's sub-pixel phase. For optics that blur before the pixel integrates (a Gaussian PSF
/// of σ, then the pixel box) the plain model's phase error on a straight edge is ±0.011 px
/// at σ = 0.3 px (effective 0.42), ±0.0023 px at 0.45 (0.53), ±0.0004 px at 0.6 (0.67), and
/// the pixel-area model's none; hence 0.55. Measured (2026-12-05, 3 × 1280x960 renders, tags
/// ~28 px, a 1.5 mm ramp; control test's sharp scene, σ = 0.3 px; net deflection against
/// truth, temporal): threshold 0.40 → 0.55, full sets 1.12 → 0.91 µm RMS, the partial
/// recording's partial sets 1.92 → 0.81 µm, largest 7.4 → 2.2 µm. (Earlier figures, on a
/// simulator that blurred after its pixels were integrated, are in docs/accuracy.md.) It
/// costs two table look-ups instead of one per pixel and term (~13 % fewer frame sets/s on
/// 3 × 1080p when every edge uses it), paid by sharp edges only.
pub(crate) const SHARP_PX: f64 = 0.55;

/// Variance of one pixel's box across the edge, px².
const PIXEL_VAR: f64 = 1.0 / 12.0;

/// The Gaussian blur of the pixel-area model that gives the effective blur `eff` (px).
fn area_sigma(eff: f64) -> f64 {
    (eff * eff - PIXEL_VAR).max(0.05 * 0.05).sqrt()
}

/// The blurred step averaged over one pixel's width across the edge, at `z` = n/σ with the
/// half width `h` = 0.5/σ: (S, dS/dz, σ·dS/dσ) where S = (G(z+h) − G(z−h))/(2h),
/// G(z) = zΦ(z) + φ(z) (G′ = Φ, and d[σG(a/σ)]/dσ = φ(a/σ)). As `h` → 0 it is the point
/// model's (Φ(z), φ(z), −zφ(z)).
#[inline(always)]
fn pixel_step(table: &[[f64; 8]], z: f64, h: f64) -> (f64, f64, f64) {
    let (c0, p0) = phi_pdf_in(table, z - h);
    let (c1, p1) = phi_pdf_in(table, z + h);
    let inv = 0.5 / h;
    (((z + h) * c1 + p1 - (z - h) * c0 - p0) * inv, (c1 - c0) * inv, (p1 - p0) * inv)
}

/// The blurred step at a pixel centre: (Φ(z), φ(z), −zφ(z)) (see [`pixel_step`]).
#[inline(always)]
fn point_step(table: &[[f64; 8]], z: f64) -> (f64, f64, f64) {
    let (c, p) = phi_pdf_in(table, z);
    (c, p, -z * p)
}

/// Fits the edge model to the pixels of `band` in `image`; `None` when the fit is not
/// trustworthy. `warm`: the edge's levels from an earlier fit (its blur the effective one).
/// An edge sharper than [`SHARP_PX`] is fitted with the pixel's area: at once when its warm
/// start says so, else refitted from the plain fit.
pub(super) fn fit_band(image: &GrayImage, band: &EdgeBand, warm: Option<[f64; 3]>) -> Option<Line> {
    let EdgeBand { a, dir, normal, bit_px, .. } = *band;
    let (white_ref, black_ref) = reference_levels(image, &band.refs);
    let contrast0 = white_ref - black_ref;
    if contrast0.abs() < 4.0 {
        return None;
    }
    let values = band_values(image, band);
    let [bl, c, eff] = warm.unwrap_or([black_ref, contrast0, super::DEFAULT_BLUR_PX]);
    let table: &[[f64; 8]] = &PHI_TABLE;
    // The white bits' inner edge along the edge, at the blur the fit starts from (the edge's
    // last fit, or the default): a function of the pixels and the warm start only, so a fit
    // of remembered pixels equals one of the same pixels selected anew.
    let beside_white = &band.pixels[band.black..];
    let aw: Vec<f64> =
        beside_white.iter().map(|p| along_white(table, &band.white_cells, &band.bounds, p.t, p.cell as usize, eff)).collect();
    let data = FitData { band, values: &values, aw: &aw, table };
    let (x, cost, area) = if eff < SHARP_PX {
        let (x, cost) = data.lm::<true>(Vector5::new(0.0, 0.0, bl, c, area_sigma(eff)));
        (x, cost, true)
    } else {
        let (x, cost) = data.lm::<false>(Vector5::new(0.0, 0.0, bl, c, eff));
        if x[4] < SHARP_PX {
            let mut x0 = x;
            x0[4] = area_sigma(x[4]);
            let (x, cost) = data.lm::<true>(x0);
            (x, cost, true)
        } else {
            (x, cost, false)
        }
    };
    // The levels (warm start, plausibility) carry the effective blur.
    let mut x = x;
    if area {
        x[4] = (x[4] * x[4] + PIXEL_VAR).sqrt();
    }
    finish(&x, &band.pixels, cost, contrast0, bit_px, a, dir, normal)
}

/// What an edge's fit runs on: the band, its pixels' values and their along-edge factors.
struct FitData<'a> {
    band: &'a EdgeBand,
    values: &'a [f64],
    aw: &'a [f64],
    table: &'a [[f64; 8]],
}

impl FitData<'_> {
    /// Levenberg–Marquardt over (angle, offset, B, C, σ) from `x`, with the pixel's area
    /// modelled when `AREA`: the parameters and the weighted cost.
    fn lm<const AREA: bool>(&self, x: Vector5<f64>) -> (Vector5<f64>, f64) {
        minimize(&StepModel::<AREA>(self), x)
    }

    /// The weighted cost and normal equations at `x` (one pass over the samples,
    /// [`NormalSums`]; JᵀWJ is symmetric: only its upper triangle is accumulated).
    fn normal_equations<const AREA: bool>(&self, x: &Vector5<f64>) -> (f64, Matrix5<f64>, Vector5<f64>) {
        let (plain, beside_white) = self.band.pixels.split_at(self.band.black);
        let (plain_values, beside_white_values) = self.values.split_at(self.band.black);
        let mut sums = NormalSums::default();
        sums.add::<false, AREA>(plain, plain_values, &[], x, self.table);
        sums.add::<true, AREA>(beside_white, beside_white_values, self.aw, x, self.table);
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
    }
}

/// The blurred-step model (at the pixel's centre, or over its area when `AREA`) as an
/// [`EdgeModel`].
struct StepModel<'a, const AREA: bool>(&'a FitData<'a>);

impl<const AREA: bool> EdgeModel<5> for StepModel<'_, AREA> {
    fn normal_equations(&self, x: &Vector5<f64>) -> (f64, Matrix5<f64>, Vector5<f64>) {
        self.0.normal_equations::<AREA>(x)
    }

    fn step_to(&self, x: &Vector5<f64>, step: &Vector5<f64>) -> Vector5<f64> {
        let mut cand = x + step;
        cand[4] = cand[4].clamp(0.05, 3.0 * self.0.band.bit_px + 5.0);
        cand
    }

    /// Converged when the step would move the edge by less than 1e-3 px (a tenth of the
    /// corner noise; the 3 × 1080p benches, clean and noisy, give the same figures to the
    /// last digit as with 1e-4 px, for a quarter fewer evaluations) and the blur has settled.
    fn converged(&self, step: &Vector5<f64>) -> bool {
        step[0].abs() * self.0.band.len + step[1].abs() < 1e-3 && step[4].abs() < 1e-2
    }
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
    /// C, σ) of the model I = B + C·(S(n/σ) + w·S((−n − gap)/σ)), `S` the blurred step at the
    /// pixel's centre (Φ) or, when `AREA`, averaged over the pixel ([`pixel_step`]),
    /// n = n₀·cos a + t·sin a − offset, `w` the sample's [`along_white`] (in `aw`, one per
    /// sample when `WHITE`; held fixed during the fit). The Jacobian's B column is 1.
    #[inline(always)]
    fn add<const WHITE: bool, const AREA: bool>(
        &mut self,
        samples: &[BandPixel],
        values: &[f64],
        aw: &[f64],
        x: &Vector5<f64>,
        table: &[[f64; 8]],
    ) {
        let (sn, cs) = x[0].sin_cos();
        let (off, bl, c, inv_sg) = (x[1], x[2], x[3], 1.0 / x[4]);
        let h = 0.5 * inv_sg;
        let (mut u, mut g, mut cost) = (self.u, self.g, self.cost);
        debug_assert!(!WHITE || aw.len() == samples.len());
        for (i, (s, &value)) in samples.iter().zip(values).enumerate() {
            debug_assert_eq!(s.white, WHITE);
            let n = s.n * cs + s.t * sn - off;
            let dn_dang = -s.n * sn + s.t * cs;
            let z1 = n * inv_sg;
            let (cdf1, pdf1, dpdf1) = if AREA { pixel_step(table, z1, h) } else { point_step(table, z1) };
            let mut val = cdf1;
            let mut dval_dn = pdf1 * inv_sg;
            let mut dval_ds = dpdf1 * inv_sg;
            if WHITE {
                let z2 = (-n - s.gap) * inv_sg;
                let (cdf2, pdf2, dpdf2) = if AREA { pixel_step(table, z2, h) } else { point_step(table, z2) };
                let wa = aw[i];
                val += wa * cdf2;
                dval_dn -= wa * pdf2 * inv_sg;
                dval_ds += wa * dpdf2 * inv_sg;
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

/// Which bound the camera clipped pixel `index` at: +1 at its top level (255), −1 at 0, 0
/// not clipped (the same pixels as `kernel2d::clipped`).
pub(super) fn clip_side(image: &GrayImage, index: usize) -> i8 {
    match image.data.get(index) {
        Some(255) => 1,
        Some(0) => -1,
        _ => 0,
    }
}

/// The residual `model − value` of a pixel clipped at side `side` ([`clip_side`]), censored
/// (Tobit-style): a clipped pixel says only that the light was at least its level (top) or
/// at most it (bottom), so a model on that side of it is not wrong there (residual 0) and a
/// model on the other side is wrong by the whole difference. Dropping such pixels (as the
/// linear kernel's fit did) throws away that one-sided constraint, which on a sharpened
/// edge's overshoot is where the shape is; fitting them as values pulls the model down to the
/// clip. `side` 0: the residual as it is.
#[inline(always)]
pub(super) fn censored_residual(r_model_minus_value: f64, side: i8) -> f64 {
    match side {
        1 if r_model_minus_value >= 0.0 => 0.0,
        -1 if r_model_minus_value <= 0.0 => 0.0,
        _ => r_model_minus_value,
    }
}

/// Checks a fitted edge and turns it into a line.
#[allow(clippy::too_many_arguments)]
pub(super) fn finish(
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
    Some(Line { normal: nrm, rho: nrm.dot(&a) + off, levels: [x[2], c, sg], rms })
}

#[cfg(test)]
mod tests {
    use super::super::lm::check_one_pixel_jacobian;
    use super::*;

    #[test]
    fn white_bits_along_the_edge_are_blurred_squares() {
        let table: &[[f64; 8]] = &PHI_TABLE;
        let bounds = [0.0, 4.0, 8.0, 12.0, 16.0];
        let f = |white: &[bool], t: f64| along_white(table, white, &bounds, t, (t / 4.0).floor().clamp(0.0, 3.0) as usize, 0.8);
        let lone = [false, true, false, false];
        // Inside a lone white bit, its two ends' blur: 1 − 2 Φ(−2.5).
        assert!((f(&lone, 6.0) - (1.0 - 2.0 * phi_pdf(-2.5).0)).abs() < 1e-9);
        // At its end half, beside it the spill, far away nothing.
        assert!((f(&lone, 8.0) - 0.5).abs() < 1e-3);
        assert!((f(&lone, 10.0) - phi_pdf(-2.5).0).abs() < 1e-3);
        assert!(f(&lone, 15.0) < 1e-9);
        // Between two white bits the edge runs on at full strength.
        let pair = [false, true, true, false];
        assert!((f(&pair, 8.0) - 1.0).abs() < 1e-6);
    }

    #[test]
    fn the_pixel_area_step_is_the_mean_over_the_pixel_with_its_derivatives() {
        let table: &[[f64; 8]] = &PHI_TABLE;
        // S(n; σ) for a pixel of width 1: the mean of Φ((n − u)/σ) over u in [−½, ½], by
        // the midpoint rule on 2000 points.
        let mean = |n: f64, sg: f64| (0..2000).map(|k| phi_pdf((n - (-0.5 + (k as f64 + 0.5) / 2000.0)) / sg).0).sum::<f64>() / 2000.0;
        for (n, sg) in [(0.0, 0.3), (0.2, 0.3), (-0.45, 0.2), (0.7, 0.5), (1.3, 0.4), (-2.0, 0.6)] {
            let (v, dz, ds) = pixel_step(table, n / sg, 0.5 / sg);
            assert!((v - mean(n, sg)).abs() < 1e-6, "S at n {n}, σ {sg}: {v} against {}", mean(n, sg));
            // dS/dn = dz / σ and dS/dσ = ds / σ, against central differences.
            let d = 1e-5;
            let s_of = |n: f64, sg: f64| pixel_step(table, n / sg, 0.5 / sg).0;
            let dn = (s_of(n + d, sg) - s_of(n - d, sg)) / (2.0 * d);
            let dsg = (s_of(n, sg + d) - s_of(n, sg - d)) / (2.0 * d);
            assert!((dz / sg - dn).abs() < 1e-5, "dS/dn at n {n}, σ {sg}: {} against {dn}", dz / sg);
            assert!((ds / sg - dsg).abs() < 1e-5, "dS/dσ at n {n}, σ {sg}: {} against {dsg}", ds / sg);
        }
        // A pixel far narrower than the blur: the point model.
        let (v, dz, ds) = pixel_step(table, 0.8, 1e-3);
        let (pv, pz, ps) = point_step(table, 0.8);
        assert!((v - pv).abs() < 1e-5 && (dz - pz).abs() < 1e-5 && (ds - ps).abs() < 1e-5, "{v} {dz} {ds} against {pv} {pz} {ps}");
        assert!((area_sigma((0.6f64 * 0.6 + PIXEL_VAR).sqrt()) - 0.6).abs() < 1e-12);
    }

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
    fn the_step_models_jacobians_match_finite_differences() {
        let table: &[[f64; 8]] = &PHI_TABLE;
        for (t, n, white) in [(6.0, -0.4, true), (9.3, 0.7, true), (14.0, -1.2, false), (2.5, 0.3, false)] {
            let band = super::super::band::one_pixel_band(t, n, white);
            let aw = if white { vec![0.83] } else { vec![] };
            let values = [250.0];
            let data = FitData { band: &band, values: &values, aw: &aw, table };
            for x in [Vector5::<f64>::new(0.03, 0.2, 40.0, 150.0, 0.7), Vector5::new(-0.05, -0.3, 35.0, 160.0, 0.4)] {
                let p = band.pixels[0];
                let nn = p.n * x[0].cos() + p.t * x[0].sin() - x[1];
                let (sharp, mid) = (data.normal_equations::<false>(&x), data.normal_equations::<true>(&x));
                // The residual from the cost (one pixel: cost = w r²), its sign from the model.
                for (model_cost, area) in [(sharp.0, false), (mid.0, true)] {
                    let (step, _, _) = if area { pixel_step(table, nn / x[4], 0.5 / x[4]) } else { point_step(table, nn / x[4]) };
                    let mut val = step;
                    if white {
                        let z2 = (-nn - p.gap) / x[4];
                        val += aw[0] * if area { pixel_step(table, z2, 0.5 / x[4]).0 } else { point_step(table, z2).0 };
                    }
                    let r = x[2] + x[3] * val - values[0];
                    assert!((model_cost - p.weight * r * r).abs() < 1e-9 * (1.0 + model_cost), "cost at {t} {n}");
                    if area {
                        check_one_pixel_jacobian(&StepModel::<true>(&data), &x, p.weight, r, 1e-4);
                    } else {
                        check_one_pixel_jacobian(&StepModel::<false>(&data), &x, p.weight, r, 1e-4);
                    }
                }
            }
        }
    }
}
