//! The camera's optics and the pixel's aperture: what happens to the light *before* the
//! pixels integrate it ([`Optics`], built from an [`OpticsSpec`]).

use rayon::prelude::*;

use crate::formation::{astigmatic_gaussian, defocus_disk, pixel_aperture, Kernel2};
use crate::pixels::gaussian_kernel;

/// An elliptical (astigmatic) Gaussian point-spread function.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Astigmatism {
    /// σ along the major axis, pixels.
    pub major_px: f64,
    /// σ along the minor axis, pixels.
    pub minor_px: f64,
    /// Angle of the major axis from the image's x axis towards its y axis (down), degrees.
    pub angle_deg: f64,
}

/// What the light passes through before the pixels integrate it, and how much of each pixel
/// integrates it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OpticsSpec {
    /// σ of a round Gaussian point-spread function, pixels (0 = none).
    pub gaussian_sigma_px: f64,
    /// Radius of a defocus disk (a uniform disk point-spread function), pixels (0 = none).
    pub defocus_radius_px: f64,
    /// An elliptical Gaussian point-spread function (none = round optics).
    pub astigmatism: Option<Astigmatism>,
    /// Fraction of each pixel's area that integrates the light: a centred square of side
    /// `√fill_factor` (1 = the whole pixel).
    pub fill_factor: f64,
}

impl OpticsSpec {
    /// Optics with a round Gaussian of `sigma_px` only, over whole pixels.
    pub fn gaussian(sigma_px: f64) -> OpticsSpec {
        OpticsSpec { gaussian_sigma_px: sigma_px, defocus_radius_px: 0.0, astigmatism: None, fill_factor: 1.0 }
    }

    /// Sub-boxes per pixel along each axis: `⌈1.2/σ⌉` for the narrowest Gaussian (see
    /// [`Optics`]), 4 for a defocus disk's sharp rim and for a fill factor below 1 (the
    /// aperture's edge then falls within a quarter pixel), at most 4.
    fn scale(&self) -> usize {
        let per_sigma = |s: f64| if s > 0.0 { (1.2 / s).ceil() as usize } else { 1 };
        let mut scale = per_sigma(self.gaussian_sigma_px);
        if let Some(a) = self.astigmatism {
            scale = scale.max(per_sigma(a.minor_px));
        }
        if self.defocus_radius_px > 0.0 || self.fill_factor < 1.0 {
            scale = 4;
        }
        scale.clamp(1, 4)
    }
}

/// The camera's optics: a point-spread function that acts on the light *before* the pixels
/// integrate it, as a lens does — a round Gaussian, a defocus disk, an elliptical Gaussian,
/// or their combination — and the pixel's aperture (its fill factor).
///
/// A sampled Gaussian applied to an image already integrated over pixels (what an image
/// editor's blur does) is not that: its effective point-spread function is the pixel box
/// times a comb of weights one pixel apart, whose edge profiles have kinks at the pixel
/// phase. A blurred-step edge fit then finds every straight edge off by up to ±0.024 px at
/// σ = 0.6 px depending on where it falls within its pixel, an error no lens and sensor
/// make, and a moving tag's position wanders with it.
///
/// Here the scene is integrated over `scale × scale` sub-boxes of every pixel; `scale`
/// consecutive sub-boxes sum to the exact pixel box, and those sums are taken at every
/// sub-box offset (the light integrated over a 1-px box, sampled every `1/scale` px). That is
/// convolved with the Gaussian sampled every `1/scale` px and taken at the pixel centres. A
/// kernel sampled every `1/scale` px has the periodic spectrum `Σₙ Ĝ(f + n·scale)`, wrong by
/// at most `Ĝ(scale/2) = exp(−π²σ²·scale²/2)` of the image's content there: `scale =
/// ⌈1.2/σ⌉` keeps that below `exp(−π²·1.44/2)` ≈ 8e-4 (capped at 4 sub-boxes: below
/// σ = 0.3 px it grows, 0.04 at σ = 0.2 px); an edge fit's phase error scales with it, from
/// 0.024 px at one sub-box and σ = 0.6 px to ~1e-4 px. With no blur the sub-box grid is the
/// pixel grid and the image is the exact pixel integral.
///
/// A defocus disk is taken by its area in each quarter-pixel sub-box (its rim resolved to a
/// quarter pixel), an elliptical Gaussian sampled like the round one; either makes the
/// point-spread function non-separable, and the pixels are then a 2-D sum over the sub-boxes.
/// A fill factor below 1 shrinks the pixel box to a centred square of side `√fill_factor`
/// (sub-boxes it covers in part weighted by the part covered).
#[derive(Debug, Clone)]
pub struct Optics {
    scale: usize,
    /// Taps on the sub-box grid along each axis: the pixel's aperture convolved with the
    /// sampled round Gaussian.
    kernel: Vec<f32>,
    /// The tap at offset 0: output sub-box `I` reads sub-boxes `I + k − origin`.
    origin: usize,
    /// The non-separable point-spread function convolved with `kernel` along both axes
    /// (`n × n` taps centred on `origin + radius`), when there is one.
    full: Option<Kernel2>,
}

impl Optics {
    /// The optics of a Gaussian point-spread function of `sigma_px` pixels (0 = none).
    pub fn new(sigma_px: f64) -> Optics {
        Optics::of(&OpticsSpec::gaussian(sigma_px))
    }

    /// The optics of `spec`.
    pub fn of(spec: &OpticsSpec) -> Optics {
        let scale = spec.scale();
        let g = gaussian_kernel(spec.gaussian_sigma_px * scale as f64);
        let r = g.len() / 2;
        let aperture = pixel_aperture(spec.fill_factor, scale);
        let mut kernel = vec![0.0f32; g.len() + scale - 1];
        for (j, gj) in g.iter().enumerate() {
            for (m, am) in aperture.iter().enumerate() {
                kernel[j + m] += gj * am;
            }
        }
        let mut psf: Option<Kernel2> = None;
        if spec.defocus_radius_px > 0.0 {
            psf = Some(defocus_disk(spec.defocus_radius_px, scale));
        }
        if let Some(a) = spec.astigmatism {
            let e = astigmatic_gaussian(a.major_px, a.minor_px, a.angle_deg, scale);
            psf = Some(match psf {
                Some(p) => p.convolve(&e),
                None => e,
            });
        }
        let full = psf.map(|p| Kernel2::outer(&kernel, &kernel).convolve(&p));
        Optics { scale, kernel, origin: r, full }
    }

    /// Sub-boxes per pixel along each axis.
    pub fn scale(&self) -> usize {
        self.scale
    }

    /// Sub-samples per axis of a sub-box for `per_pixel` per axis of a pixel: an n-rooks
    /// pattern of `n` per axis resolves an edge parallel to the grid to `1/n²` of its box, so
    /// `⌈per_pixel/√scale⌉` keeps the pixel's `1/per_pixel²` with `scale` sub-boxes across it.
    pub fn sub_box_samples(&self, per_pixel: usize) -> usize {
        let n = per_pixel as f64 / (self.scale as f64).sqrt();
        (n.ceil() as usize).max(1)
    }

    /// The taps along one axis and their origin (the 2-D ones when the point-spread function
    /// is not separable).
    fn extent(&self) -> (usize, usize) {
        match &self.full {
            Some(k) => (k.n, self.origin + (k.n - self.kernel.len()) / 2),
            None => (self.kernel.len(), self.origin),
        }
    }

    /// Pixels the point-spread function reaches on either side of a pixel.
    pub fn reach_px(&self) -> usize {
        let (len, origin) = self.extent();
        let far = origin.max(len - 1 - origin);
        far.div_ceil(self.scale)
    }

    /// The pixel image (`wf/scale × hf/scale`) of a `wf × hf` image of sub-box integrals
    /// (each the scene's mean over its sub-box), edges clamped.
    pub fn apply(&self, fine: &[f32], wf: usize, hf: usize) -> Vec<f32> {
        let s = self.scale;
        let (w, h) = (wf / s, hf / s);
        if w == 0 || h == 0 {
            return Vec::new();
        }
        if let Some(k) = &self.full {
            return self.apply_2d(k, fine, wf, hf);
        }
        let at = |i: usize, k: usize, n: usize| (i as isize + k as isize - self.origin as isize).clamp(0, n as isize - 1) as usize;
        // Along rows, at the pixel centres' columns.
        let mut tmp = vec![0.0f32; w * hf];
        tmp.par_chunks_mut(w).enumerate().for_each(|(yf, row)| {
            let src = &fine[yf * wf..(yf + 1) * wf];
            for (x, o) in row.iter_mut().enumerate() {
                *o = self.kernel.iter().enumerate().map(|(k, kv)| kv * src[at(x * s, k, wf)]).sum();
            }
        });
        // Along columns, at the pixel centres' rows.
        let mut out = vec![0.0f32; w * h];
        out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
            for (k, kv) in self.kernel.iter().enumerate() {
                let src = &tmp[at(y * s, k, hf) * w..(at(y * s, k, hf) + 1) * w];
                for (o, v) in row.iter_mut().zip(src) {
                    *o += kv * v;
                }
            }
        });
        out
    }

    /// [`Optics::apply`] with the non-separable `k` (`n × n` taps): each pixel the sum of
    /// its taps over the sub-boxes around it (a contiguous row of taps against a contiguous
    /// row of sub-boxes away from the image edge; clamped at it).
    fn apply_2d(&self, k: &Kernel2, fine: &[f32], wf: usize, hf: usize) -> Vec<f32> {
        let s = self.scale;
        let (w, h) = (wf / s, hf / s);
        let n = k.n;
        let o = self.extent().1 as isize;
        let mut out = vec![0.0f32; w * h];
        out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
            for ky in 0..n {
                let taps = &k.taps[ky * n..(ky + 1) * n];
                if taps.iter().all(|&t| t == 0.0) {
                    continue;
                }
                let fy = (y as isize * s as isize + ky as isize - o).clamp(0, hf as isize - 1) as usize;
                let src = &fine[fy * wf..(fy + 1) * wf];
                for (x, px) in row.iter_mut().enumerate() {
                    let x0 = x as isize * s as isize - o;
                    *px += if x0 >= 0 && x0 as usize + n <= wf {
                        taps.iter().zip(&src[x0 as usize..x0 as usize + n]).map(|(t, v)| t * v).sum::<f32>()
                    } else {
                        taps.iter().enumerate().map(|(kx, t)| t * src[(x0 + kx as isize).clamp(0, wf as isize - 1) as usize]).sum::<f32>()
                    };
                }
            }
        });
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A `w × h` image of a step between columns `at - 1` and `at`, with a bright square.
    fn scene(w: usize, h: usize, at: usize) -> Vec<f32> {
        (0..w * h).map(|i| if i % w >= at || (i / w > h / 3 && i / w < h / 2 && i % w < at / 2) { 200.0 } else { 20.0 }).collect()
    }

    #[test]
    fn a_round_ellipse_is_the_round_gaussian() {
        // The non-separable path with a round ellipse gives what the separable one gives:
        // the taps line up with the pixels (no shift) and reach as far.
        let round = Optics::new(0.6);
        let spec =
            OpticsSpec { astigmatism: Some(Astigmatism { major_px: 0.6, minor_px: 0.6, angle_deg: 40.0 }), ..OpticsSpec::gaussian(0.0) };
        let ellipse = Optics::of(&spec);
        assert_eq!(round.scale(), ellipse.scale());
        let s = round.scale();
        let (wf, hf) = (40 * s, 30 * s);
        let fine = scene(wf, hf, 17 * s + 1);
        let (a, b) = (round.apply(&fine, wf, hf), ellipse.apply(&fine, wf, hf));
        let worst = a.iter().zip(&b).map(|(x, y)| (x - y).abs()).fold(0.0f32, f32::max);
        assert!(worst < 0.5, "largest difference {worst} grey levels");
        assert!(ellipse.reach_px() >= round.reach_px());
    }

    #[test]
    fn a_defocus_disk_spreads_a_step_over_its_diameter() {
        // A vertical step at x = 16.5 px seen through a disk of radius 1.5 px: pixels more
        // than radius + ½ px from it are untouched, the two beside it meet half-way.
        let optics = Optics::of(&OpticsSpec { defocus_radius_px: 1.5, ..OpticsSpec::gaussian(0.0) });
        let s = optics.scale();
        let (wf, hf) = (32 * s, 12 * s);
        let fine: Vec<f32> = (0..wf * hf).map(|i| if i % wf >= 17 * s { 100.0 } else { 0.0 }).collect();
        let img = optics.apply(&fine, wf, hf);
        let row = &img[6 * 32..7 * 32];
        assert_eq!((row[14], row[19]), (0.0, 100.0), "{row:?}");
        assert!((row[16] + row[17] - 100.0).abs() < 1e-3 && row[15] > 0.5 && row[18] < 99.5, "{row:?}");
        assert!((2..=3).contains(&optics.reach_px()));
    }
}
