//! How far a camera's edge fits are from their model: the fits' residuals near the edge
//! against the noise expected there, and the widening of the corners' σ that follows
//! ([`ModelExcess`]).
//!
//! **The noise expected at a grey level** is the camera's own, read from the same fits where
//! the model cannot be wrong: their flat parts, the black border inside the edge and the white
//! ring outside it, where the profile is constant (its slope below [`FLAT_SLOPE`]) and a
//! residual is noise alone. Their two variances are the noise at the black and at the white
//! level, and a pixel on the edge, at grey level `B + C·P(d)`, is expected to have
//! `(1 − P)·var_black + P·var_white` (noise that grows with the light, as a sensor's shot
//! noise does, is followed; constant noise gives the same figure everywhere).
//!
//! **The widening.** Over the pixels on the edge, the ratio of the residuals' variance to that
//! expected, `ρ² = Σ w r² / Σ w var_expected`, is 1 when the model describes the edge (the
//! fit's four parameters take ~4 of an edge's hundred-odd pixels: a few per cent) and
//! `1 + (m / σ)²` with a model error of RMS `m` beside noise `σ`. What such an error does to a
//! fitted edge is unknown per edge (its share along the position's Jacobian), so the corners'
//! σ is widened as a least-squares fit's is when its reduced χ² exceeds 1 (the Birge ratio):
//! by `f = √(1 + max(0, ρ² − 1 − RHO2_TOLERANCE))` ([`widening`]). A fit at the noise level
//! (`ρ² ≤ 1.1`) leaves σ as it is; a model error twice the noise (`ρ² = 5`) widens it by
//! `√4.9 ≈ 2.21`. The sums are the camera's, over every well-fitted edge since the profile
//! was learned (halved when they grow large, so they follow a slow change), so `ρ²` is known
//! to a per cent or better after a frame and the factor does not wander from frame to frame.

use super::band::{pixel_value, EdgeBand};
use super::fit::Line;
use super::profile::{pixel_class, EdgeProfile};
use super::EdgeMemory;
use tagdeflect_core::frame::GrayImage;

/// Below this slope (contrast per pixel) the profile is flat: a pixel there sees one level.
pub const FLAT_SLOPE: f64 = 0.02;
/// `ρ²` up to `1 + RHO2_TOLERANCE` is the model's describing the edge (the fit's own degrees
/// of freedom, the profile's sampling noise): no widening.
pub const RHO2_TOLERANCE: f64 = 0.1;
/// Depth (pixels) beyond the data bits' inner edge from which a pixel beside a white bit no
/// longer sees that edge (as the profile's samples, `refine::profile`).
const WHITE_EDGE_CLEARANCE_PX: f64 = 2.0;
/// An edge whose fit's RMS residual exceeds this fraction of its contrast is not counted (an
/// occlusion, a misread bit: not the model's error).
const MAX_EDGE_RMS: f64 = 0.15;
/// The sums are halved when the edge's weight passes this.
const MAX_WEIGHT: f64 = 1.0e6;
/// Flat-part weight (pixels) needed on each side before the ratio is trusted.
const MIN_FLAT_WEIGHT: f64 = 200.0;

/// The σ widening factor for a ratio `rho2` of the residuals' variance to the noise expected
/// (see the module docs): `√(1 + max(0, ρ² − 1 − RHO2_TOLERANCE))`.
pub fn widening(rho2: f64) -> f64 {
    if !rho2.is_finite() {
        return 1.0;
    }
    (1.0 + (rho2 - 1.0 - RHO2_TOLERANCE).max(0.0)).sqrt()
}

/// A camera's running sums of its edge fits' residuals (see the module docs).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ModelExcess {
    /// Weight and weighted squared residuals of the flat black and white parts.
    black: [f64; 2],
    white: [f64; 2],
    /// On the edge: weighted squared residuals, `Σ w (1 − P)` and `Σ w P`.
    edge_sq: f64,
    edge_dark: f64,
    edge_light: f64,
}

impl ModelExcess {
    /// Adds the residuals of a tag's last fit (`memory`: its bands, fitted lines and the
    /// profile they were fitted with) in `image`; a fit without a profile or without all four
    /// edges adds none.
    pub fn add_tag(&mut self, image: &GrayImage, memory: &EdgeMemory) {
        let (Some(bands), Some(profile)) = (memory.bands.as_ref(), memory.profile.as_deref()) else { return };
        if memory.lines.iter().any(|l| l.is_none()) {
            return;
        }
        for (band, line) in bands.edges.iter().zip(&memory.lines) {
            if let Some(line) = line {
                self.add_edge(image, band, line, profile);
            }
        }
    }

    /// Adds one edge's residuals.
    fn add_edge(&mut self, image: &GrayImage, band: &EdgeBand, line: &Line, profile: &EdgeProfile) {
        let [black, contrast, _] = line.levels;
        if contrast.abs() < 4.0 || !(line.rms < MAX_EDGE_RMS * contrast.abs()) {
            return;
        }
        for p in &band.pixels {
            let u = band.a + band.dir * p.t + band.normal * p.n;
            let d = line.distance(&u);
            if p.white && d + p.gap < WHITE_EDGE_CLEARANCE_PX {
                continue;
            }
            let (value, slope) = profile.class_value_slope(pixel_class(&band.normal, p.index, image.width), d);
            let r = pixel_value(image, p.index) - (black + contrast * value);
            self.add_pixel(p.weight, value, slope, r);
        }
        if self.edge_dark + self.edge_light > MAX_WEIGHT {
            for x in [&mut self.black, &mut self.white] {
                x.iter_mut().for_each(|v| *v *= 0.5);
            }
            for v in [&mut self.edge_sq, &mut self.edge_dark, &mut self.edge_light] {
                *v *= 0.5;
            }
        }
    }

    /// Adds one pixel of weight `w` where the profile is `value` with `slope`, its residual
    /// `r` (grey levels).
    fn add_pixel(&mut self, w: f64, value: f64, slope: f64, r: f64) {
        if slope.abs() < FLAT_SLOPE {
            let side = if value < 0.5 { &mut self.black } else { &mut self.white };
            side[0] += w;
            side[1] += w * r * r;
        } else {
            let p = value.clamp(0.0, 1.0);
            self.edge_sq += w * r * r;
            self.edge_dark += w * (1.0 - p);
            self.edge_light += w * p;
        }
    }

    /// `ρ²`: the residuals' variance on the edge over the noise expected there, once the flat
    /// parts have weight enough.
    pub fn rho2(&self) -> Option<f64> {
        if self.black[0] < MIN_FLAT_WEIGHT || self.white[0] < MIN_FLAT_WEIGHT || self.edge_dark + self.edge_light <= 0.0 {
            return None;
        }
        let (var_black, var_white) = (self.black[1] / self.black[0], self.white[1] / self.white[0]);
        let expected = self.edge_dark * var_black + self.edge_light * var_white;
        (expected > 0.0).then(|| self.edge_sq / expected)
    }

    /// The widening these residuals call for: [`widening`] of [`ModelExcess::rho2`], 1 until
    /// known.
    pub fn factor(&self) -> f64 {
        self.rho2().map_or(1.0, widening)
    }
}

/// Whether the corners' σ is widened by the edge fits' residual energy:
/// `TAGDEFLECT_SIGMA_WIDENING=residuals` (a measurement), read once per process (`on` is the
/// estimate from the corners' scatter across phases, `tagdeflect_estimate::measure`). Off by
/// default: measured on the formations' scenes
/// (docs/accuracy.md) it over-covers (100 % within 2σ on the sharpened and elliptical scenes)
/// and, through the temporal estimate's weights, moves the positions (the Bayer scene
/// 0.0242 → 0.0515 mm). When it is off a camera gathers no residuals at all
/// (`crate::learned`): the sums cost a pass over every fitted edge's pixels a frame.
pub fn widening_switch() -> bool {
    static ON: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *ON.get_or_init(|| std::env::var("TAGDEFLECT_SIGMA_WIDENING").is_ok_and(|v| v == "residuals"))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A pseudo-random standard normal sequence (xorshift, Box–Muller).
    fn normal(seed: &mut u64) -> f64 {
        let mut uniform = || {
            *seed ^= *seed << 13;
            *seed ^= *seed >> 7;
            *seed ^= *seed << 17;
            ((*seed >> 11) as f64 + 0.5) / (1u64 << 53) as f64
        };
        (-2.0 * uniform().ln()).sqrt() * (std::f64::consts::TAU * uniform()).cos()
    }

    /// Residuals of an edge's pixels: noise of variance `(1 − P)·black² + P·white²` at the
    /// grey level `P`, plus on the edge a model error of RMS `model` times that noise (a
    /// pixel-phase pattern, which does not average away).
    fn excess_of(black: f64, white: f64, model: f64) -> ModelExcess {
        let mut e = ModelExcess::default();
        let mut seed = 0x9e37_79b9_7f4a_7c15_u64;
        let esf = |d: f64| 1.0 / (1.0 + (-d / 0.35).exp());
        for k in 0..40_000 {
            let d = -4.0 + 6.5 * ((k as f64 * 0.618_034) % 1.0);
            let (value, slope) = (esf(d), esf(d) * (1.0 - esf(d)) / 0.35);
            let sigma = (black * black * (1.0 - value) + white * white * value).sqrt();
            let error = if slope.abs() < FLAT_SLOPE { 0.0 } else { model * sigma * std::f64::consts::SQRT_2 * (7.3 * d).sin() };
            e.add_pixel(1.0, value, slope, sigma * normal(&mut seed) + error);
        }
        e
    }

    #[test]
    fn residuals_at_the_noise_level_leave_sigma_unchanged() {
        for (black, white) in [(2.0, 2.0), (1.5, 4.0)] {
            let e = excess_of(black, white, 0.0);
            let rho2 = e.rho2().expect("flat parts seen");
            assert!((rho2 - 1.0).abs() < 0.05, "noise {black} → {white}: ρ² {rho2}");
            assert_eq!(e.factor(), 1.0);
        }
        assert_eq!(ModelExcess::default().factor(), 1.0, "1 until known");
    }

    #[test]
    fn a_model_error_twice_the_noise_widens_sigma_by_the_documented_factor() {
        assert!((widening(5.0) - 4.9f64.sqrt()).abs() < 1e-12);
        assert_eq!(widening(1.1), 1.0);
        assert_eq!(widening(0.7), 1.0);
        for (black, white) in [(2.0, 2.0), (1.5, 4.0)] {
            let e = excess_of(black, white, 2.0);
            let rho2 = e.rho2().unwrap();
            assert!((rho2 - 5.0).abs() < 0.3, "noise {black} → {white}: ρ² {rho2}");
            let f = e.factor();
            assert!((f - 4.9f64.sqrt()).abs() < 0.07, "factor {f} against √4.9");
        }
    }
}
