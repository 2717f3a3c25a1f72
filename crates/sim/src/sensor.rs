//! The light a pixel collects (`exposure`) and its photon shot noise (`full_well_e`), applied
//! to the optics' image before the camera's processing after the pixel; the read noise
//! (`noise_sigma`) and the digitisation follow in [`crate::render::quantize_bits`].
//!
//! Why a camera model in electrons: a real sensor's gain from more bits shows only where its
//! own noise is below the 8-bit step — a dim, low-contrast scene (a dark lab, or an exposure
//! kept short against motion blur), on a sensor whose full well is large against its read
//! noise. There a pixel's noise is its photon shot noise, √(electrons), which is smaller in
//! grey levels the fewer electrons a grey level holds; docs/accuracy.md gives the scene used.

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use rayon::prelude::*;

/// Grey levels of 8 bits at the top of the sensor's range (its full well).
const FULL_SCALE_GREY: f64 = 255.0;

/// Scales `img` (grey levels of 8 bits, `w` pixels a row) by `exposure` and, when
/// `full_well_e` > 0, adds each pixel's photon shot noise (Gaussian, σ = √electrons, the
/// electrons being the level's share of the full well), seeded by `seed`.
pub(crate) fn expose(img: &mut [f32], w: usize, exposure: f64, full_well_e: f64, seed: u64) {
    if exposure == 1.0 && full_well_e <= 0.0 {
        return;
    }
    let e_per_grey = full_well_e / FULL_SCALE_GREY;
    img.par_chunks_mut(w.max(1)).enumerate().for_each(|(y, row)| {
        let mut rng = ChaCha8Rng::seed_from_u64(seed ^ (y as u64).wrapping_mul(0xd1b5_4a32_d192_ed03));
        for v in row.iter_mut() {
            let grey = (*v as f64 * exposure).max(0.0);
            let shot = if e_per_grey > 0.0 {
                let z: f64 = StandardNormal.sample(&mut rng);
                z * (grey * e_per_grey).sqrt() / e_per_grey
            } else {
                0.0
            };
            *v = (grey + shot) as f32;
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exposure_scales_and_shot_noise_grows_as_the_root_of_the_light() {
        let (w, h) = (200usize, 200usize);
        let spread = |level: f32, exposure: f64, full_well: f64| {
            let mut img = vec![level; w * h];
            expose(&mut img, w, exposure, full_well, 7);
            let mean = img.iter().map(|&v| v as f64).sum::<f64>() / img.len() as f64;
            let var = img.iter().map(|&v| (v as f64 - mean).powi(2)).sum::<f64>() / img.len() as f64;
            (mean, var.sqrt())
        };
        let (m, s) = spread(200.0, 0.1, 0.0);
        assert!((m - 20.0).abs() < 1e-4 && s < 1e-4, "{m} {s}");
        // 20 grey levels of a 25 500-electron well: 2000 e, σ 44.7 e = 0.447 grey levels.
        let (m, s) = spread(200.0, 0.1, 25_500.0);
        assert!((m - 20.0).abs() < 0.01 && (s - 0.447).abs() < 0.01, "{m} {s}");
        // Four times the light: twice the noise.
        let (_, s4) = spread(200.0, 0.4, 25_500.0);
        assert!((s4 / s - 2.0).abs() < 0.05, "{s4} / {s}");
        let mut same = vec![3.0f32; 10];
        expose(&mut same, 10, 1.0, 0.0, 1);
        assert_eq!(same, vec![3.0f32; 10], "the default scene is untouched");
    }
}
