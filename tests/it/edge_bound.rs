//! What each image formation allows (docs/accuracy.md, "What each formation allows"): the
//! Cramér–Rao bound of a straight edge's position per formation of `formations::`, against
//! what the product's edge fit achieves on the same scene.
//!
//! **The bound.** One edge is formed by the simulator's own code
//! ([`tagdeflect_sim::edge_patch`]: exact sub-box areas, the optics before the pixel, the
//! camera's processing after it, a raw Bayer sensor's photosites) at its true direction and
//! sub-pixel position in the scene; each stored value is `clamp(round(mean + noise))`, the
//! noise Gaussian (σ 2 grey levels, added after the processing as the simulator adds it), so a
//! value's information about its mean is taken from that exact distribution
//! ([`level_information`]: the rounding's 1/12 and the clipping of overshoots at 0 and 255
//! included). The parameters are the edge's offset across itself at its middle, its rotation
//! about the middle, and the black and white levels (the fit's nuisances); the Fisher matrix
//! sums each pixel's `J(μ) ∇μ ∇μᵀ` over the fit's band (`RefineOptions`' defaults: 1.5 bits
//! inside the tag, 0.8 outside, 2 px from each corner, 3.5 px bits: a 28 px tag), the
//! offset's and the rotation's derivatives by central differences of the rendered patch. The
//! offset's bound is `(F⁻¹)₀₀`, scaled to each edge's length (the information grows with the
//! band's length). Idealised: one step between two levels (a tag's white data bits inside the
//! border, and its other edges, left out), the fit's own blur width not a nuisance (the
//! learned profile has none). For the raw Bayer sensor the bound is that of the raw mosaic,
//! which holds all the information the product's conversion passes on.
//!
//! **What the fit achieves.** `edge_bias::measure` on the scene rendered twice, with no read
//! noise and with σ 2: each edge fit's middle offset from the true line, noise-free (the
//! bias, with the 8-bit rounding), and the difference between the two renders' fits of the
//! same edge in the same frame (the noise part). The bound is the smallest variance any
//! unbiased estimator can reach for that noise part: where the noise part is at the bound
//! the fit is noise-limited, where the bias is larger than it the fit is bias-limited.
//!
//! `cargo test --test it edge_bound:: -- --ignored --nocapture` (two renders and fits of each
//! scene: about two minutes a formation); `TAGDEFLECT_FORMATIONS=bayer,ellip` chooses scenes
//! (besides the sharp one), `TAGDEFLECT_EDGE_BOUND_SETS=8` fewer frame sets (16 by default),
//! and `TAGDEFLECT_EDGE_MODEL=formation-sites` fits with the physical formation.

use std::collections::HashMap;

use nalgebra::{Matrix4, Vector4};
use tagdeflect_sim::edge_patch::{straight_edge_patch, StraightEdge};
use tagdeflect_sim::SimParams;

use crate::edge_bias::{measure, EdgeSeen};

/// The scenes' tag levels (the simulator's `shade::BLACK`, `shade::WHITE`).
const BLACK_GREY: f32 = 28.0;
const WHITE_GREY: f32 = 228.0;
/// The fit's band across the edge (`RefineOptions::default()`: 1.5 bits inside, 0.8 bits
/// outside, at 3.5 px bits), pixels.
const INNER_BAND_PX: f64 = 1.5 * BIT_PX;
const OUTER_BAND_PX: f64 = 0.8 * BIT_PX;
/// A tag's bit on the reference edge (a 28 px black square of 8 bits), pixels.
const BIT_PX: f64 = 3.5;
/// The band's length on the reference edge (a 28 px edge less 2 px at each end), pixels.
const BAND_LENGTH_PX: f64 = 24.0;
/// The fit keeps this far from each corner (`RefineOptions::margin_px`), pixels.
const CORNER_MARGIN_PX: f64 = 2.0;
/// The patch's side, pixels: the band and the optics' and processing's reach, with room.
const PATCH_PX: usize = 44;
/// Central differences' steps: the offset (px) and the rotation (degrees).
const OFFSET_STEP_PX: f64 = 0.01;
const ROTATION_STEP_DEG: f64 = 0.05;

/// The standard normal's upper tail `Q(z) = P(Z > z)`, from the complementary error
/// function (Numerical Recipes' `erfcc`, relative error below 1.2e-7 everywhere: the tail
/// bins' probabilities keep their digits).
fn upper_tail(z: f64) -> f64 {
    let x = z / std::f64::consts::SQRT_2;
    let t = 1.0 / (1.0 + 0.5 * x.abs());
    let poly = -1.265_512_23
        + t * (1.000_023_68
            + t * (0.374_091_96
                + t * (0.096_784_18
                    + t * (-0.186_288_06
                        + t * (0.278_868_07 + t * (-1.135_203_98 + t * (1.488_515_87 + t * (-0.822_152_23 + t * 0.170_872_77))))))));
    let erfc = t * (-x * x + poly).exp();
    0.5 * if x >= 0.0 { erfc } else { 2.0 - erfc }
}

fn density(z: f64) -> f64 {
    (-0.5 * z * z).exp() / (2.0 * std::f64::consts::PI).sqrt()
}

/// The probability of `(lo, hi]` under the standard normal, from the nearer tail.
fn bin_probability(lo: f64, hi: f64) -> f64 {
    if lo >= 0.0 {
        upper_tail(lo) - upper_tail(hi)
    } else if hi <= 0.0 {
        upper_tail(-hi) - upper_tail(-lo)
    } else {
        1.0 - upper_tail(hi) - upper_tail(-lo)
    }
}

/// Fisher information about `mean` of one stored value `clamp(round((mean + noise)/step))`
/// (noise Gaussian of `sigma`, values `0 ..= top/step`): `Σ_k (∂P_k/∂mean)² / P_k` over the
/// stored values `k`, the two end values open (clipping). Near `1/(σ² + step²/12)` in the
/// range, less near its ends.
pub(crate) fn level_information(mean: f64, sigma: f64, step: f64, top: f64) -> f64 {
    let last = (top / step).round() as i64;
    let centre = (mean / step).round() as i64;
    let reach = (12.0 * sigma / step).ceil() as i64 + 1;
    let (k0, k1) = ((centre - reach).max(0), (centre + reach).min(last));
    (k0..=k1)
        .map(|k| {
            let lo = if k == 0 { f64::NEG_INFINITY } else { ((k as f64 - 0.5) * step - mean) / sigma };
            let hi = if k == last { f64::INFINITY } else { ((k as f64 + 0.5) * step - mean) / sigma };
            let p = bin_probability(lo, hi);
            let dp = (density(lo) - density(hi)) / sigma;
            if p > 1e-300 {
                dp * dp / p
            } else {
                0.0
            }
        })
        .sum()
}

/// `(F⁻¹)₀₀` of a positive definite Fisher matrix: the first parameter's bound with the
/// others fitted.
fn first_bound(f: &Matrix4<f64>) -> f64 {
    f.try_inverse().map_or(f64::INFINITY, |inv| inv[(0, 0)])
}

/// Σ `info_p · g_p g_pᵀ`.
fn fisher_matrix(grads: &[Vector4<f64>], info: &[f64]) -> Matrix4<f64> {
    grads.iter().zip(info).fold(Matrix4::zeros(), |f, (g, j)| f + *j * g * g.transpose())
}

/// One edge's place in the patch: the line's direction (degrees; its normal out of the tag)
/// and the sub-pixel position of its middle (px, modulo 2: a Bayer mosaic's period).
#[derive(Clone, Copy)]
struct EdgePlace {
    dir_deg: f64,
    mid_mod2_px: [f64; 2],
}

impl EdgePlace {
    fn edge(&self, offset_px: f64, rotation_deg: f64, levels: (f32, f32), bar_px: Option<f64>) -> StraightEdge {
        let a = self.dir_deg.to_radians();
        let c = 20.0;
        let centre_px = [c + self.mid_mod2_px[0] - offset_px * a.sin(), c + self.mid_mod2_px[1] + offset_px * a.cos()];
        StraightEdge { centre_px, angle_deg: self.dir_deg + rotation_deg, black: levels.0, white: levels.1, bar_px }
    }

    /// The band's pixels: (index, across, along) relative to the middle.
    fn band(&self) -> Vec<usize> {
        let a = self.dir_deg.to_radians();
        let (u, n) = ([a.cos(), a.sin()], [-a.sin(), a.cos()]);
        let c = [20.0 + self.mid_mod2_px[0], 20.0 + self.mid_mod2_px[1]];
        (0..PATCH_PX * PATCH_PX)
            .filter(|i| {
                let q = [(i % PATCH_PX) as f64 - c[0], (i / PATCH_PX) as f64 - c[1]];
                let across = n[0] * q[0] + n[1] * q[1];
                let along = u[0] * q[0] + u[1] * q[1];
                (-INNER_BAND_PX..=OUTER_BAND_PX).contains(&across) && along.abs() <= 0.5 * BAND_LENGTH_PX
            })
            .collect()
    }
}

/// The Fisher matrix of (offset, rotation, black, white) on the reference band: behind the
/// edge all black (`bar_px` none: the tag's data bits there black), or a bar of `bar_px`
/// with white beyond (the data bits white; their edge moves with the border's, as the fit's
/// model has it).
fn edge_fisher(p: &SimParams, place: &EdgePlace, bar_px: Option<f64>) -> Matrix4<f64> {
    let grey = (BLACK_GREY, WHITE_GREY);
    let render = |off: f64, rot: f64, levels: (f32, f32)| straight_edge_patch(p, &place.edge(off, rot, levels, bar_px), PATCH_PX, PATCH_PX);
    let scene = render(0.0, 0.0, grey);
    let (d_plus, d_minus) = (render(OFFSET_STEP_PX, 0.0, grey), render(-OFFSET_STEP_PX, 0.0, grey));
    let (r_plus, r_minus) = (render(0.0, ROTATION_STEP_DEG, grey), render(0.0, -ROTATION_STEP_DEG, grey));
    let (black, white) = (render(0.0, 0.0, (1.0, 0.0)), render(0.0, 0.0, (0.0, 1.0)));
    let band = place.band();
    let diff = |a: &[f32], b: &[f32], i: usize, h: f64| (a[i] as f64 - b[i] as f64) / (2.0 * h);
    let grads: Vec<Vector4<f64>> = band
        .iter()
        .map(|&i| {
            Vector4::new(
                diff(&d_plus.mean, &d_minus.mean, i, OFFSET_STEP_PX),
                diff(&r_plus.mean, &r_minus.mean, i, ROTATION_STEP_DEG.to_radians()),
                black.mean[i] as f64,
                white.mean[i] as f64,
            )
        })
        .collect();
    let info: Vec<f64> =
        band.iter().map(|&i| level_information(scene.mean[i] as f64, scene.read_noise_grey, scene.step_grey, scene.top_grey)).collect();
    fisher_matrix(&grads, &info)
}

/// The offset's bounds (px²) on the reference band, the levels and rotation fitted: the data
/// bits inside the border all black (one step), all white (a bar), half of each (Fisher
/// matrices add along the edge; a tag's bits are about half white); and half of each with
/// the levels and rotation known (`1/F₀₀`).
fn edge_bound(p: &SimParams, place: &EdgePlace) -> [f64; 4] {
    let step = edge_fisher(p, place, None);
    let bar = edge_fisher(p, place, Some(BIT_PX));
    let half = 0.5 * (step + bar);
    [first_bound(&step), first_bound(&bar), first_bound(&half), 1.0 / half[(0, 0)]]
}

/// Each fit's offset bounds (px², [`edge_bound`]), by its edge's place (cached: directions
/// to 0.5°, positions to 1/8 px) and scaled from the reference band to the edge's length.
struct Bounds<'a> {
    params: &'a SimParams,
    cache: HashMap<(i64, i64, i64), [f64; 4]>,
}

impl Bounds<'_> {
    fn of(&mut self, e: &EdgeSeen) -> [f64; 4] {
        let key = (
            (e.outward_dir_deg * 2.0).round() as i64,
            (e.mid_px[0].rem_euclid(2.0) * 8.0).round() as i64 % 16,
            (e.mid_px[1].rem_euclid(2.0) * 8.0).round() as i64 % 16,
        );
        let p = self.params;
        let bounds = *self.cache.entry(key).or_insert_with(|| {
            let place = EdgePlace { dir_deg: key.0 as f64 / 2.0, mid_mod2_px: [key.1 as f64 / 8.0, key.2 as f64 / 8.0] };
            edge_bound(p, &place)
        });
        let scale = BAND_LENGTH_PX / (e.length_px - 2.0 * CORNER_MARGIN_PX).max(4.0);
        bounds.map(|b| b * scale)
    }
}

/// One formation's row: fits, the mean bounds ([`edge_bound`]'s four), bias and noise parts.
struct Row {
    fits: usize,
    bounds_px2: [f64; 4],
    bias_rms_px: f64,
    bias_moving_px: f64,
    noise_px2: f64,
    noise_px2_se: f64,
}

fn middle(e: &EdgeSeen) -> f64 {
    0.5 * (e.off_a + e.off_b)
}

/// The scene's noise-free and noisy fits joined by (frame set, edge), with each edge's bound.
fn row_of(p: &SimParams) -> Row {
    let clean = measure(&SimParams { noise_sigma: 0.0, ..p.clone() });
    let noisy = measure(p);
    let by_key: HashMap<_, &EdgeSeen> = clean.iter().map(|e| ((e.set, e.key), e)).collect();
    let mut bounds = Bounds { params: p, cache: HashMap::new() };
    let pairs: Vec<(&EdgeSeen, &EdgeSeen)> = noisy.iter().filter_map(|e| Some((*by_key.get(&(e.set, e.key))?, e))).collect();
    let n = pairs.len().max(1) as f64;
    let mut mean_bounds = [0.0; 4];
    for (c, _) in &pairs {
        let b = bounds.of(c);
        (0..4).for_each(|k| mean_bounds[k] += b[k] / n);
    }
    let noise2: Vec<f64> = pairs.iter().map(|(c, e)| (middle(e) - middle(c)).powi(2)).collect();
    let noise_px2 = noise2.iter().sum::<f64>() / n;
    let noise_var = noise2.iter().map(|v| (v - noise_px2).powi(2)).sum::<f64>() / n;
    Row {
        fits: pairs.len(),
        bounds_px2: mean_bounds,
        bias_rms_px: (pairs.iter().map(|(c, _)| middle(c).powi(2)).sum::<f64>() / n).sqrt(),
        bias_moving_px: bias_about_each_edges_mean(&pairs),
        noise_px2,
        noise_px2_se: (noise_var / n).sqrt(),
    }
}

/// The noise-free middle offsets' RMS about each edge's own mean over the frames: the part
/// of the bias that moves with the tag (what a displacement sees).
fn bias_about_each_edges_mean(pairs: &[(&EdgeSeen, &EdgeSeen)]) -> f64 {
    let mut by_edge: HashMap<_, Vec<f64>> = HashMap::new();
    pairs.iter().for_each(|(c, _)| by_edge.entry(c.key).or_default().push(middle(c)));
    let (s, n) = by_edge.values().filter(|v| v.len() >= 2).fold((0.0, 0usize), |(s, n), v| {
        let m = v.iter().sum::<f64>() / v.len() as f64;
        (s + v.iter().map(|x| (x - m).powi(2)).sum::<f64>(), n + v.len())
    });
    (s / n.max(1) as f64).sqrt()
}

/// Where the fit stands against the half-white bound: at the bound (its noise part's
/// variance within 1.25× the bound's, 12 % in RMS), bias-limited (its moving bias above the
/// noise part's RMS), else inefficient.
fn reading(r: &Row) -> &'static str {
    let efficiency = r.bounds_px2[2] / r.noise_px2;
    let noise_rms = r.noise_px2.sqrt();
    match (efficiency >= 0.8, r.bias_moving_px > noise_rms) {
        (true, false) => "at the bound",
        (true, true) => "at the bound, bias-limited",
        (false, true) => "bias-limited, inefficient",
        (false, false) => "inefficient",
    }
}

/// One row of the printed table, asserting only the bounds' order and that the noise part
/// is not below the smallest bound (every data bit white) beyond three standard errors.
fn table_line(name: &str, r: &Row, sharp_half_px2: f64) -> String {
    let [step, bar, half, known] = r.bounds_px2;
    assert!(
        half.is_finite() && bar > 0.0 && bar <= half && half <= step && known <= half * (1.0 + 1e-9),
        "{name}: bounds {:?}",
        r.bounds_px2
    );
    assert!(r.noise_px2 + 3.0 * r.noise_px2_se >= bar, "{name}: noise part {} px² below the bound {bar} px²", r.noise_px2);
    format!(
        "| {name} | {} | {:.4} px | {:.2}× | {:.4} px | {:.4} px | {:.4} px | {:.4} px ± {:.1} % | {:.4} px | {:.4} px | {:.2} | {} |",
        r.fits,
        half.sqrt(),
        (half / sharp_half_px2).sqrt(),
        step.sqrt(),
        bar.sqrt(),
        known.sqrt(),
        r.noise_px2.sqrt(),
        50.0 * r.noise_px2_se / r.noise_px2,
        r.bias_rms_px,
        r.bias_moving_px,
        half / r.noise_px2,
        reading(r)
    )
}

#[test]
#[ignore = "a measurement of minutes (two renders and fits per formation): run with --ignored --nocapture"]
fn edge_position_bound_per_formation_against_the_fit() {
    let only: Vec<String> = std::env::var("TAGDEFLECT_FORMATIONS")
        .map(|v| v.split(',').map(|s| s.trim().to_lowercase()).filter(|s| !s.is_empty()).collect())
        .unwrap_or_default();
    let sets: u32 = std::env::var("TAGDEFLECT_EDGE_BOUND_SETS").ok().and_then(|v| v.parse().ok()).unwrap_or(16);
    let chosen = |k: usize, name: &str| k == 0 || only.is_empty() || only.iter().any(|o| name.to_lowercase().contains(o.as_str()));
    let mut lines = Vec::new();
    let mut sharp_half = None;
    for (_, (name, _, p)) in crate::formations::formation_scenes().into_iter().enumerate().filter(|(k, (n, _, _))| chosen(*k, n)) {
        if p.jpeg_quality.is_some() || p.bit_depth != 8 {
            continue; // JPEG: no additive noise model; 10/12 bits: not asked of this table.
        }
        let r = row_of(&SimParams { frame_sets: sets, noise_sigma: 2.0, ..p });
        assert!(r.fits > 100, "{name}: only {} edge fits joined", r.fits);
        let line = table_line(name, &r, *sharp_half.get_or_insert(r.bounds_px2[2]));
        println!("BOUND {line}");
        lines.push(line);
    }
    println!("| formation | edge fits | bound, bits half white | × sharp's | bound, bits black | bound, bits white | bound, levels known | noise part (RMS) | bias (RMS) | bias about each edge's mean | bound²/noise² | reading |");
    println!("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |");
    lines.iter().for_each(|l| println!("{l}"));
    assert!(!lines.is_empty(), "no scene chosen");
}

#[test]
fn a_stored_values_information_is_the_rounded_gaussians() {
    // Within the range: near 1/(σ² + 1/12) (Sheppard's correction), for any phase of the
    // mean against the rounding; with a step far below σ, 1/σ².
    for mean in [100.0, 100.25, 100.5] {
        let j = level_information(mean, 2.0, 1.0, 255.0);
        assert!((j * (4.0 + 1.0 / 12.0) - 1.0).abs() < 0.005, "mean {mean}: {j}");
    }
    let fine = level_information(100.3, 2.0, 1.0 / 256.0, 255.0 + 255.0 / 256.0);
    assert!((fine * 4.0 - 1.0).abs() < 1e-4, "{fine}");
    // Clipped: a mean far above the top says almost nothing; at the top, about half.
    assert!(level_information(275.0, 2.0, 1.0, 255.0) < 1e-6);
    let at_top = level_information(255.0, 2.0, 1.0, 255.0) * 4.0;
    assert!(at_top > 0.3 && at_top < 0.8, "{at_top}");
}

#[test]
fn the_fisher_matrix_of_a_sampled_gaussian_step_is_the_closed_form() {
    // I(x) = B + C Φ((x − d)/s) at integer x, noise σ: ∂I/∂d = −C φ/s, so with B, C known
    // F₀₀ = Σ (C φ/s)²/σ². With them fitted the bound is larger; over a wide range of
    // samples around a centred step (the levels then known from the far samples, and the
    // offset's even slope orthogonal to the odd Φ − ½) it tends to the known-level one.
    let (c, s, sigma) = (200.0, 0.8, 2.0);
    let phi_cdf = |z: f64| 1.0 - upper_tail(z);
    for (d, half_range) in [(0.3, 10), (0.0, 10), (0.0, 400)] {
        let xs: Vec<f64> = (-half_range..=half_range).map(|x| x as f64).collect();
        let grads: Vec<Vector4<f64>> = xs
            .iter()
            .map(|x| {
                let z = (x - d) / s;
                // (offset, a parameter seen by one far sample only, B, C)
                Vector4::new(-c * density(z) / s, if *x == xs[0] { 1.0 } else { 0.0 }, 1.0, phi_cdf(z))
            })
            .collect();
        let info = vec![1.0 / (sigma * sigma); xs.len()];
        let f = fisher_matrix(&grads, &info);
        let closed: f64 = xs.iter().map(|x| (c * density((x - d) / s) / s).powi(2) / (sigma * sigma)).sum();
        assert!((f[(0, 0)] / closed - 1.0).abs() < 1e-12, "{} against {closed}", f[(0, 0)]);
        let bound = first_bound(&f);
        assert!(bound >= 1.0 / closed * (1.0 - 1e-9), "{bound} below {}", 1.0 / closed);
        if half_range == 400 {
            assert!((bound * closed - 1.0).abs() < 0.01, "wide: {bound} against {}", 1.0 / closed);
        }
    }
}

#[test]
fn the_rendered_edges_bound_is_the_closed_form_of_its_pixels() {
    // A sharp horizontal edge at y = 20.3 inside row 20 (19.5–20.5): only that row's pixels
    // see the offset, each with slope C = 200 grey levels/px and mean 28 + 0.2·200, so with
    // the levels known F₀₀ = (the band's columns) · C² · J(68), J near 1/(σ² + 1/12).
    let p = SimParams { blur_sigma: 0.0, noise_sigma: 2.0, ..SimParams::default() };
    let place = EdgePlace { dir_deg: 0.0, mid_mod2_px: [0.0, 0.3] };
    let f = edge_fisher(&p, &place, None);
    let (fitted, known) = (first_bound(&f), 1.0 / f[(0, 0)]);
    let columns = place.band().iter().filter(|&&i| i / PATCH_PX == 20).count() as f64;
    let j = level_information(28.0 + 0.2 * 200.0, 2.0, 1.0, 255.0);
    assert!((j * (4.0 + 1.0 / 12.0) - 1.0).abs() < 0.005, "{j}");
    let closed = columns * 200.0 * 200.0 * j;
    assert!((known * closed - 1.0).abs() < 1e-3, "known levels: {known} against {}", 1.0 / closed);
    assert!(fitted >= known && fitted < 1.5 * known, "fitted {fitted}, known {known}");
}
