//! One straight edge between two grey levels, formed as the simulator forms its scenes'
//! images ([`straight_edge_patch`]): the exact area of each sub-box on either side of the
//! line, the optics before the pixel ([`crate::render::Optics`], built from the same
//! [`SimParams`] as [`crate::SimRig`]'s), the exposure, the camera's processing after the
//! pixel (the same code as [`crate::SimRig::render`]), and for a raw Bayer sensor its
//! photosites' responses. What it returns is the image's *mean*: the read noise, the
//! digitisation's step and its range are returned beside it, not drawn, so that a caller can
//! take an edge's information from the exact distribution of every stored value (the
//! Cramér–Rao bound of an edge's position per formation, `tests/it/edge_bound.rs`).
//!
//! Not covered: photon shot noise (`full_well_e`; the formations' scenes have none), motion
//! blur, and JPEG (its quantisation of each 8 × 8 block's cosine coefficients is not an
//! additive noise of known variance per pixel).

use crate::render::formation::{bayer_mosaic, RAW_BAYER_RESPONSES};
use crate::render::Optics;
use crate::SimParams;

/// A straight edge through a patch: the line through `centre_px` (pixel coordinates, a
/// pixel's centre at its integer coordinates) at `angle_deg` from the x axis towards y;
/// `white` on the side of its normal `(−sin, cos)`, `black` on the other.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StraightEdge {
    /// A point of the line, pixels.
    pub centre_px: [f64; 2],
    /// The line's direction from the x axis towards the y axis, degrees.
    pub angle_deg: f64,
    /// Grey level (8 bits) on the side away from the normal.
    pub black: f32,
    /// Grey level (8 bits) on the normal's side.
    pub white: f32,
    /// When set, the black side is a bar this wide (pixels), white again beyond it: a
    /// tag's one-bit black border with white data bits inside it.
    pub bar_px: Option<f64>,
}

/// The mean image of a patch and how its values are stored: each stored value is
/// `clamp(round((mean + noise) / step_grey)) · step_grey` within `0 ..= top_grey`, the noise
/// Gaussian of `read_noise_grey`, independent per stored value.
#[derive(Debug, Clone)]
pub struct EdgePatch {
    /// Patch width, pixels.
    pub w: usize,
    /// Patch height, pixels.
    pub h: usize,
    /// The stored values' means, grey levels of 8 bits, row-major (for a raw Bayer sensor:
    /// its photosites, each through its filter's response).
    pub mean: Vec<f32>,
    /// The digitisation's step, grey levels of 8 bits (1 at 8 bits, 1/4 at 10 bits).
    pub step_grey: f64,
    /// The largest stored value, grey levels of 8 bits.
    pub top_grey: f64,
    /// The read noise's σ, grey levels of 8 bits.
    pub read_noise_grey: f64,
}

/// The `w × h` patch of `edge` as the simulator with `params` forms it (see the module's
/// documentation; `params`' scene geometry is not used). The optics and the processing
/// clamp at the patch's border: pixels within the optics' reach (and 2 px for the processing)
/// of the border are not the scene's.
pub fn straight_edge_patch(params: &SimParams, edge: &StraightEdge, w: usize, h: usize) -> EdgePatch {
    let optics = Optics::of(&crate::rig::optics_spec(params));
    let s = optics.scale();
    let fine = sub_box_levels(edge, w * s, h * s, s);
    let mut px = optics.apply(&fine, w * s, h * s);
    crate::sensor::expose(&mut px, w, params.exposure, 0.0, 0);
    let mut mean = crate::render_rig::after_pixels_of(params, px, w, h);
    let (step_grey, top_grey) = if params.bayer_raw {
        mean = bayer_mosaic(&mean, w, &RAW_BAYER_RESPONSES);
        (1.0, 255.0)
    } else {
        let per_grey = (1u64 << params.bit_depth.saturating_sub(8)) as f64;
        (1.0 / per_grey, ((1u64 << params.bit_depth.max(8)) - 1) as f64 / per_grey)
    };
    EdgePatch { w, h, mean, step_grey, top_grey, read_noise_grey: params.noise_sigma }
}

/// Each `1/scale`-pixel sub-box's mean level: the levels weighted by the sub-box's exact
/// area on either side of the line.
fn sub_box_levels(edge: &StraightEdge, wf: usize, hf: usize, scale: usize) -> Vec<f32> {
    let a = edge.angle_deg.to_radians();
    let n = [-a.sin(), a.cos()];
    let c = n[0] * edge.centre_px[0] + n[1] * edge.centre_px[1];
    let step = 1.0 / scale as f64;
    let contrast = (edge.white - edge.black) as f64;
    (0..wf * hf)
        .map(|i| {
            let (x0, y0) = ((i % wf) as f64 * step - 0.5, (i / wf) as f64 * step - 0.5);
            let (xs, ys) = ([x0, x0 + step], [y0, y0 + step]);
            let inner = edge.bar_px.map_or(0.0, |g| box_share_beyond(xs, ys, [-n[0], -n[1]], g - c));
            let white = box_share_beyond(xs, ys, n, c) + inner;
            (edge.black as f64 + contrast * white) as f32
        })
        .collect()
}

/// The share of the box `xs × ys` where `n·p > c`: the box clipped by the half-plane
/// (Sutherland–Hodgman), its area by the shoelace formula.
pub fn box_share_beyond(xs: [f64; 2], ys: [f64; 2], n: [f64; 2], c: f64) -> f64 {
    let corners = [[xs[0], ys[0]], [xs[1], ys[0]], [xs[1], ys[1]], [xs[0], ys[1]]];
    let side = |p: &[f64; 2]| n[0] * p[0] + n[1] * p[1] - c;
    let mut poly: Vec<[f64; 2]> = Vec::with_capacity(6);
    for k in 0..4 {
        let (p, q) = (corners[k], corners[(k + 1) % 4]);
        let (sp, sq) = (side(&p), side(&q));
        if sp > 0.0 {
            poly.push(p);
        }
        if (sp > 0.0) != (sq > 0.0) {
            let t = sp / (sp - sq);
            poly.push([p[0] + t * (q[0] - p[0]), p[1] + t * (q[1] - p[1])]);
        }
    }
    let area: f64 = (0..poly.len())
        .map(|k| {
            let (p, q) = (poly[k], poly[(k + 1) % poly.len()]);
            p[0] * q[1] - q[0] * p[1]
        })
        .sum();
    0.5 * area.abs() / ((xs[1] - xs[0]) * (ys[1] - ys[0]))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_box_is_shared_by_the_line_as_its_area_says() {
        // Half of the unit box beyond x = 0.5; a quarter beyond the diagonal's corner
        // triangle x + y > 1.5 is 1/8; all of it, none of it.
        let n = [1.0, 0.0];
        assert!((box_share_beyond([0.0, 1.0], [0.0, 1.0], n, 0.5) - 0.5).abs() < 1e-12);
        let d = [1.0 / 2f64.sqrt(), 1.0 / 2f64.sqrt()];
        assert!((box_share_beyond([0.0, 1.0], [0.0, 1.0], d, 1.5 / 2f64.sqrt()) - 0.125).abs() < 1e-12);
        assert_eq!(box_share_beyond([0.0, 1.0], [0.0, 1.0], n, -1.0), 1.0);
        assert_eq!(box_share_beyond([0.0, 1.0], [0.0, 1.0], n, 2.0), 0.0);
    }

    #[test]
    fn a_sharp_aligned_edge_is_the_pixels_area_and_a_blurred_one_its_gaussian() {
        // A horizontal edge at y = 10.3: row 10 (its pixel spans 9.5–10.5) is 20 % white.
        let edge = StraightEdge { centre_px: [16.0, 10.3], angle_deg: 0.0, black: 28.0, white: 228.0, bar_px: None };
        let p = SimParams { noise_sigma: 2.0, blur_sigma: 0.0, ..SimParams::default() };
        let patch = straight_edge_patch(&p, &edge, 32, 20);
        let at = |y: usize| patch.mean[y * 32 + 16] as f64;
        assert!((at(10) - (28.0 + 200.0 * 0.2)).abs() < 1e-3, "{}", at(10));
        assert_eq!((at(9), at(11)), (28.0, 228.0));
        assert_eq!((patch.step_grey, patch.top_grey, patch.read_noise_grey), (1.0, 255.0, 2.0));
        // A bar 3.5 px wide: white again from y = 6.8, so row 7 (6.5–7.5) is 30 % white.
        let bar = straight_edge_patch(&p, &StraightEdge { bar_px: Some(3.5), ..edge }, 32, 20);
        assert!((bar.mean[7 * 32 + 16] as f64 - (28.0 + 200.0 * 0.3)).abs() < 1e-3, "{}", bar.mean[7 * 32 + 16]);
        assert_eq!((bar.mean[6 * 32 + 16], bar.mean[8 * 32 + 16], bar.mean[10 * 32 + 16]), (228.0, 28.0, patch.mean[10 * 32 + 16]));
        // Blurred before the pixel: the pixel's mean of Φ((y − 10.3)/σ), by quadrature. The
        // optics' Gaussian sampled every half pixel (its sub-box grid at σ 0.7) over
        // half-pixel sub-boxes acts as a Gaussian of variance σ² + (1/2)²/12 (a sum over
        // kinked ramps one sub-box apart; 0.715 px for 0.7): against σ itself the pixels
        // differ by up to 0.004 of the contrast, against that by less than 1e-3.
        let sigma = 0.7;
        let blurred = straight_edge_patch(&SimParams { blur_sigma: sigma, ..p }, &edge, 32, 20);
        let sigma_eff = (sigma * sigma + 0.25 / 12.0).sqrt();
        for y in 8..13 {
            let mean_phi =
                |s: f64| (0..1000).map(|k| phi_cdf((y as f64 - 0.5 + (k as f64 + 0.5) / 1000.0 - 10.3) / s)).sum::<f64>() / 1000.0;
            let got = (blurred.mean[y * 32 + 16] as f64 - 28.0) / 200.0;
            assert!((got - mean_phi(sigma_eff)).abs() < 1e-3, "row {y}: {got} against {}", mean_phi(sigma_eff));
            assert!((got - mean_phi(sigma)).abs() < 5e-3, "row {y}: {got} against {}", mean_phi(sigma));
        }
    }

    /// The standard normal's distribution function (Abramowitz & Stegun 7.1.26, 1.5e-7).
    fn phi_cdf(z: f64) -> f64 {
        let x = z.abs() / 2f64.sqrt();
        let t = 1.0 / (1.0 + 0.327_591_1 * x);
        let poly = t * (0.254_829_592 + t * (-0.284_496_736 + t * (1.421_413_741 + t * (-1.453_152_027 + t * 1.061_405_429))));
        let erf = 1.0 - poly * (-x * x).exp();
        0.5 * (1.0 + z.signum() * erf)
    }
}
