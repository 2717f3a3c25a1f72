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

use super::band::{reference_levels, BandPixel, EdgeBand};
use super::fit::{finish, Line};
use super::profile::EdgeProfile;
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
    let values: Vec<f64> = band.pixels.iter().map(|p| image.data[p.index] as f64).collect();
    let [bl, c, blur] = warm.unwrap_or([black_ref, contrast0, super::DEFAULT_BLUR_PX]);
    let aw: Vec<f64> = band.pixels.iter().map(|p| if p.white { along_white(profile, band, p.t, p.cell as usize) } else { 0.0 }).collect();
    let (x, cost) = lm(band, &values, &aw, profile, Vector4::new(0.0, 0.0, bl, c));
    let EdgeBand { a, dir, normal, bit_px, .. } = *band;
    finish(&Vector5::new(x[0], x[1], x[2], x[3], blur), &band.pixels, cost, contrast0, bit_px, a, dir, normal)
}

/// The weighted cost, JᵀWJ and JᵀWr of the model at `x` = (angle, offset, B, C).
fn normal_equations(
    pixels: &[BandPixel],
    values: &[f64],
    aw: &[f64],
    profile: &EdgeProfile,
    x: &Vector4<f64>,
) -> (f64, Matrix4<f64>, Vector4<f64>) {
    let (sn, cs) = x[0].sin_cos();
    let (off, bl, c) = (x[1], x[2], x[3]);
    let (mut cost, mut jtj, mut jtr) = (0.0, Matrix4::<f64>::zeros(), Vector4::<f64>::zeros());
    for ((s, &value), &wa) in pixels.iter().zip(values).zip(aw) {
        let n = s.n * cs + s.t * sn - off;
        let (mut val, mut slope) = profile.value_slope(n);
        if wa > 0.0 {
            let (v2, s2) = profile.value_slope(-n - s.gap);
            val += wa * v2;
            slope -= wa * s2;
        }
        let r = bl + c * val - value;
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
fn lm(band: &EdgeBand, values: &[f64], aw: &[f64], profile: &EdgeProfile, mut x: Vector4<f64>) -> (Vector4<f64>, f64) {
    let eq = |x: &Vector4<f64>| normal_equations(&band.pixels, values, aw, profile, x);
    let (mut current, mut jtj, mut jtr) = eq(&x);
    let mut lambda = 1e-6;
    for _ in 0..40 {
        let mut damped = jtj;
        for d in 0..4 {
            damped[(d, d)] += lambda * jtj[(d, d)].max(1e-9);
        }
        let Some(step) = damped.cholesky().map(|ch| ch.solve(&(-jtr))) else {
            lambda *= 10.0;
            if lambda > 1e8 {
                break;
            }
            continue;
        };
        let cand = x + step;
        // Converged as the parametric fit is (see `fit::FitData::lm`).
        if step[0].abs() * band.len + step[1].abs() < 1e-3 {
            x = cand;
            break;
        }
        let (cost, j2, r2) = eq(&cand);
        if cost.is_finite() && cost <= current {
            (x, current, jtj, jtr) = (cand, cost, j2, r2);
            lambda = (lambda * 0.1).max(1e-9);
        } else {
            lambda *= 10.0;
            if lambda > 1e8 {
                break;
            }
        }
    }
    (x, current)
}
