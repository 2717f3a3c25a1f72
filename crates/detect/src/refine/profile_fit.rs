//! The edge fit with a camera's learned profile ([`super::profile`]): the model of
//! [`super::fit`] with the profile in place of the blurred step,
//!
//! ```text
//! I(n) = B + C · ( P(n) + white · P(−n − g) )
//! ```
//!
//! by the same Levenberg–Marquardt over the line's angle and offset and the two levels (the
//! blur is no parameter: the profile carries it), with `P′` in the Jacobian. The white bits'
//! factor along the edge is the profile's too: a white run `[t_j, t_k]` seen through it is
//! `P(t − t_j) − P(t − t_k)`.

use nalgebra::{Matrix4, Vector4, Vector5};

use super::band::{pixel_value, reference_levels, BandPixel, EdgeBand};
use super::fit::{censored_residual, clip_side, finish, Line};
use super::kernel2d::{clipped, site_of, EdgeKernel};
use super::lm::{minimize, EdgeModel};
use super::profile::{pixel_class, EdgeProfile};
use tagdeflect_core::frame::GrayImage;

/// The along-edge factor of the white data bits' inner edge (see `fit::along_white`) through
/// the profile.
fn along_white(profile: &EdgeProfile, band: &EdgeBand, t_px: f64, cell: usize) -> f64 {
    let (white, bounds) = (&band.white_cells, &band.bounds);
    let mut w = 0.0;
    for j in cell.saturating_sub(2)..=(cell + 2).min(white.len() - 1) {
        if white[j] {
            w += profile.value(t_px - bounds[j]) - profile.value(t_px - bounds[j + 1]);
        }
    }
    w.clamp(0.0, 1.0)
}

/// Fits the profile model to the pixels of `band`; `None` when the fit is not trustworthy
/// (the caller then fits the parametric model). `warm`: the edge's levels from an earlier
/// fit; the blur they carry is kept for the parametric fit.
pub(super) fn fit_band_profile(image: &GrayImage, band: &EdgeBand, warm: Option<[f64; 3]>, profile: &EdgeProfile) -> Option<Line> {
    let (white_ref, black_ref) = reference_levels(image, &band.refs);
    let contrast0 = white_ref - black_ref;
    if contrast0.abs() < 4.0 {
        return None;
    }
    let [bl, c, blur] = warm.unwrap_or([black_ref, contrast0, super::DEFAULT_BLUR_PX]);
    // The 2-D kernel is linear: a pixel the camera clipped is left out of its fit, except
    // with the physical formation, which fits it censored (`fit::censored_residual`).
    let kernel = profile.kernel().map(|k| k.along(&band.normal));
    let censoring = profile.kernel().is_some_and(|k| k.light().is_some());
    let pixels: Vec<BandPixel> =
        band.pixels.iter().copied().filter(|p| kernel.is_none() || censoring || !clipped(image, p.index)).collect();
    let clips: Vec<i8> = pixels.iter().map(|p| if censoring { clip_side(image, p.index) } else { 0 }).collect();
    let values: Vec<f64> = pixels.iter().map(|p| pixel_value(image, p.index)).collect();
    let aw: Vec<f64> = pixels.iter().map(|p| if p.white { along_white(profile, band, p.t, p.cell as usize) } else { 0.0 }).collect();
    let class_of = |i: usize| if kernel.is_some() { site_of(i, image.width) } else { pixel_class(&band.normal, i, image.width) };
    let classes: Vec<usize> = pixels.iter().map(|p| class_of(p.index)).collect();
    let data =
        ProfileData { pixels: &pixels, values: &values, aw: &aw, classes: &classes, clips: &clips, profile, kernel: kernel.as_ref() };
    let (x, cost) = lm(band, &data, Vector4::new(0.0, 0.0, bl, c));
    let EdgeBand { a, dir, normal, bit_px, .. } = *band;
    finish(&Vector5::new(x[0], x[1], x[2], x[3], blur), &pixels, cost, contrast0, bit_px, a, dir, normal)
}

/// What a profile fit runs on: the band's pixels, their values, along-edge white factors,
/// pixel classes (mosaic sites with a kernel) and clipped sides (`fit::clip_side`, 0 where
/// not censored), and the profile (or the 2-D kernel along this edge).
struct ProfileData<'a> {
    pixels: &'a [BandPixel],
    values: &'a [f64],
    aw: &'a [f64],
    classes: &'a [usize],
    clips: &'a [i8],
    profile: &'a EdgeProfile,
    kernel: Option<&'a EdgeKernel<'a>>,
}

/// The weighted cost, JᵀWJ and JᵀWr of the model at `x` = (angle, offset, B, C).
fn normal_equations(data: &ProfileData<'_>, x: &Vector4<f64>) -> (f64, Matrix4<f64>, Vector4<f64>) {
    let (sn, cs) = x[0].sin_cos();
    let (off, bl, c) = (x[1], x[2], x[3]);
    let (mut cost, mut jtj, mut jtr) = (0.0, Matrix4::<f64>::zeros(), Vector4::<f64>::zeros());
    let profile = data.profile;
    for ((((s, &value), &wa), &class), &clip) in data.pixels.iter().zip(data.values).zip(data.aw).zip(data.classes).zip(data.clips) {
        let n = s.n * cs + s.t * sn - off;
        let model = |d: f64, mirrored: bool| match data.kernel {
            Some(k) => k.value_slope(class, d, mirrored),
            None => profile.class_value_slope(class, d),
        };
        let (mut val, mut slope) = model(n, false);
        if wa > 0.0 {
            let (v2, s2) = model(-n - s.gap, true);
            val += wa * v2;
            slope -= wa * s2;
        }
        let r = censored_residual(bl + c * val - value, clip);
        if r == 0.0 && clip != 0 {
            // A clipped pixel the model agrees with: no residual, and no slope either.
            continue;
        }
        let dn_dang = -s.n * sn + s.t * cs;
        let j = Vector4::new(c * slope * dn_dang, -c * slope, 1.0, val);
        let w = s.weight;
        cost += w * r * r;
        jtj += (w * j) * j.transpose();
        jtr += (w * r) * j;
    }
    (cost, jtj, jtr)
}

/// Levenberg–Marquardt over (angle, offset, B, C) from `x`: the parameters and the cost.
fn lm(band: &EdgeBand, data: &ProfileData<'_>, x: Vector4<f64>) -> (Vector4<f64>, f64) {
    minimize(&ProfileModel { data, len: band.len }, x)
}

/// The profile model as an [`EdgeModel`]; `len` the edge's length (px).
struct ProfileModel<'a> {
    data: &'a ProfileData<'a>,
    len: f64,
}

impl EdgeModel<4> for ProfileModel<'_> {
    fn normal_equations(&self, x: &Vector4<f64>) -> (f64, Matrix4<f64>, Vector4<f64>) {
        normal_equations(self.data, x)
    }

    /// Converged as the parametric fit is (see `fit::StepModel`).
    fn converged(&self, step: &Vector4<f64>) -> bool {
        step[0].abs() * self.len + step[1].abs() < 1e-3
    }
}

#[cfg(test)]
mod tests {
    use super::super::band::one_pixel_band;
    use super::super::lm::check_one_pixel_jacobian;
    use super::*;

    #[test]
    fn the_kernel_models_jacobian_matches_finite_differences() {
        // A 3×3 sharpening of amount 1 after the pixel, as a 5 × 5 kernel.
        let mut taps = [0.0; super::super::kernel2d::TAPS];
        taps[12] = 2.0;
        [7, 11, 13, 17].into_iter().for_each(|k| taps[k] = -0.25);
        let kernel = super::super::kernel2d::Kernel2d::from_taps(vec![taps]);
        // The same after a blur before the pixel and an aperture (the physical formation).
        let light = super::super::formation::Light { sigma_x_px: 0.5, sigma_y_px: 0.3, corr: 0.4, width_px: 0.8 };
        for kernel in [kernel.clone(), kernel.with_light(light)] {
            let profile = EdgeProfile::from_fn(|d| d.clamp(-0.5, 0.5) + 0.5).with_kernel(kernel);
            for (t, n, white) in [(9.3, -3.7, true), (6.0, -3.9, true), (14.0, -0.8, false), (2.5, 0.3, false)] {
                let band = one_pixel_band(t, n, white);
                let along = profile.kernel().expect("a kernel").along(&band.normal);
                let aw = [if white { 0.83 } else { 0.0 }];
                let values = [150.0];
                let data = ProfileData {
                    pixels: &band.pixels,
                    values: &values,
                    aw: &aw,
                    classes: &[1],
                    clips: &[0],
                    profile: &profile,
                    kernel: Some(&along),
                };
                let model = ProfileModel { data: &data, len: band.len };
                for x in [Vector4::<f64>::new(0.03, 0.2, 40.0, 150.0), Vector4::new(-0.05, -0.3, 35.0, 160.0)] {
                    let p = band.pixels[0];
                    let nn = p.n * x[0].cos() + p.t * x[0].sin() - x[1];
                    let val = along.value_slope(1, nn, false).0 + aw[0] * along.value_slope(1, -nn - p.gap, true).0;
                    assert!(val.abs() > 1e-3, "the model is not flat at {nn}");
                    let r = x[2] + x[3] * val - values[0];
                    check_one_pixel_jacobian(&model, &x, p.weight, r, 1e-4);
                }
            }
        }
    }

    #[test]
    fn the_profile_models_jacobian_matches_finite_differences() {
        // A sharpened edge's profile (it overshoots), tabulated.
        let esf = |d: f64, s: f64| 1.0 / (1.0 + (-d / s).exp());
        let profile = EdgeProfile::from_fn(|d| 2.0 * esf(d, 0.3) - esf(d, 0.6));
        for (t, n, white) in [(6.0, -0.4, true), (9.3, 0.7, true), (14.0, -1.2, false), (2.5, 0.3, false)] {
            let band = one_pixel_band(t, n, white);
            let aw = [if white { 0.83 } else { 0.0 }];
            let values = [250.0];
            let data =
                ProfileData { pixels: &band.pixels, values: &values, aw: &aw, classes: &[3], clips: &[0], profile: &profile, kernel: None };
            let model = ProfileModel { data: &data, len: band.len };
            for x in [Vector4::<f64>::new(0.03, 0.2, 40.0, 150.0), Vector4::new(-0.05, -0.3, 35.0, 160.0)] {
                let p = band.pixels[0];
                let nn = p.n * x[0].cos() + p.t * x[0].sin() - x[1];
                let val = profile.value(nn) + aw[0] * profile.value(-nn - p.gap);
                let r = x[2] + x[3] * val - values[0];
                check_one_pixel_jacobian(&model, &x, p.weight, r, 1e-4);
            }
        }
    }
}
