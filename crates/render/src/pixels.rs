//! The renderer: area integration of a traced scene over pixels, motion blur, sensor noise
//! and rounding (the optics before the pixels: [`crate::Optics`]).
//!
//! Each camera's undistorted ray through every pixel *corner* (OpenCV convention: pixel
//! centres at integers, so corners at half-integers) is computed once from the intrinsics.
//! Pixels inside one tag take `n × n` sub-samples in the tag's own frame; other mixed
//! pixels (paper edges, surface edges, silhouettes) take `n/2 × n/2` traced sub-samples.
//! A pixel whose four corners hit the same uniform region (one colour of one tag, one
//! surface) takes the mean of its corner values (exact for flat regions; tag cells are
//! larger than a pixel, so a pixel whose corners all see one colour lies wholly in it);
//! any other pixel is integrated with `n × n` sub-samples in an
//! n-rooks pattern (every sub-sample has its own row and column, so an edge parallel to the
//! pixel grid is resolved to `1/n²` of a pixel), whose rays are interpolated bilinearly
//! between the four corner rays (the distortion is smooth at the pixel scale).

use nalgebra::{Rotation3, Vector3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use rayon::prelude::*;

use tagdeflect_core::camera::CameraIntrinsics;
use tagdeflect_core::frame::{DeepPlane, GrayImage};

/// A rectangle of pixels `x0..x1`, `y0..y1` (exclusive ends).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PixelRect {
    /// First column.
    pub x0: usize,
    /// First row.
    pub y0: usize,
    /// One past the last column.
    pub x1: usize,
    /// One past the last row.
    pub y1: usize,
}

impl PixelRect {
    /// Width in pixels.
    pub fn width(&self) -> usize {
        self.x1 - self.x0
    }
    /// Height in pixels.
    pub fn height(&self) -> usize {
        self.y1 - self.y0
    }
    /// True when it holds no pixel.
    pub fn is_empty(&self) -> bool {
        self.x1 <= self.x0 || self.y1 <= self.y0
    }
    /// The same area counted in sub-boxes of `1/scale` pixel.
    pub fn scaled(&self, scale: usize) -> PixelRect {
        PixelRect { x0: self.x0 * scale, y0: self.y0 * scale, x1: self.x1 * scale, y1: self.y1 * scale }
    }
    /// Grown by `m` pixels on every side, clipped to `w × h`.
    pub fn grow(&self, m: usize, w: usize, h: usize) -> PixelRect {
        PixelRect { x0: self.x0.saturating_sub(m), y0: self.y0.saturating_sub(m), x1: (self.x1 + m).min(w), y1: (self.y1 + m).min(h) }
    }
}

/// Undistorted normalised rays through the pixel corners of one camera.
#[derive(Debug, Clone)]
pub struct CornerRays {
    /// Image width.
    pub w: usize,
    /// Image height.
    pub h: usize,
    /// `(w + 1) × (h + 1)` normalised coordinates `(x/z, y/z)` at pixel corners.
    rays: Vec<[f32; 2]>,
}

impl CornerRays {
    /// Undistorts every pixel corner of `k` (both cores) with the simulator's own lens
    /// model ([`crate::lens`]), not the product's.
    pub fn new(k: &CameraIntrinsics) -> Self {
        Self::sub_boxes(k, 1)
    }

    /// The rays through the corners of every pixel's `scale × scale` sub-boxes ([`Optics`]):
    /// `w`, `h` and the pixel indices of [`render_rect`] then count sub-boxes.
    pub fn sub_boxes(k: &CameraIntrinsics, scale: usize) -> Self {
        let (w, h) = (k.width as usize * scale, k.height as usize * scale);
        let lens = crate::lens::Lens::of(k);
        let step = 1.0 / scale as f64;
        let mut rays = vec![[0.0f32; 2]; (w + 1) * (h + 1)];
        rays.par_chunks_mut(w + 1).enumerate().for_each(|(j, row)| {
            for (i, r) in row.iter_mut().enumerate() {
                let (x, y) = lens.ray(i as f64 * step - 0.5, j as f64 * step - 0.5);
                *r = [x as f32, y as f32];
            }
        });
        Self { w, h, rays }
    }

    #[inline]
    fn at(&self, i: usize, j: usize) -> [f64; 2] {
        let r = self.rays[j * (self.w + 1) + i];
        [r[0] as f64, r[1] as f64]
    }
}

/// What a traced ray hits: a region label (equal labels = one uniformly shaded region),
/// the grey level there, and, on a tag, the point in the tag's frame (mm; else zeros).
pub type Hit = (u32, f32, [f64; 2]);

/// Labels of tag pixels: bits 8.. name the tag (non-zero), bit 0 its colour. A pixel whose
/// four corners lie on one tag is integrated in the tag's own frame, the sub-samples
/// interpolated bilinearly between the corners' tag coordinates (the pixel-to-plane map is
/// smooth at the pixel scale), then shaded by `flat(label, x, y)` without tracing.
pub type Flat<'a> = Option<&'a (dyn Fn(u32, f64, f64) -> f32 + Sync)>;

#[inline]
fn tag_key(label: u32) -> Option<u32> {
    (label & 0xff00 != 0 && label & 0xff <= 1).then_some(label & !0xff)
}

/// Which uniform pixels to copy from a buffer instead: (label predicate, full-image buffer).
pub type Keep<'a> = Option<(&'a (dyn Fn(u32) -> bool + Sync), &'a [f32])>;

/// Renders pixels of `rect` into `out` (row-major, `rect.width()` wide) by area
/// integration. `corner` is traced at the pixel corners; a pixel whose four corner labels
/// agree is uniform: it takes `keep`'s buffer value when `keep`'s predicate accepts the
/// label (`keep` = (predicate, full-image buffer)), else the mean of its corner values.
/// Any other pixel is integrated with `n × n` sub-samples of `sample(direction, x, y)`
/// (`x`, `y`: the pixel). `rot_cw` maps camera to world directions.
#[allow(clippy::too_many_arguments)]
pub fn render_rect<C, S>(
    rays: &CornerRays,
    rot_cw: &Rotation3<f64>,
    rect: PixelRect,
    n: usize,
    corner: &C,
    sample: &S,
    keep: Keep<'_>,
    flat: Flat<'_>,
    out: &mut [f32],
) where
    C: Fn(&Vector3<f64>) -> Hit + Sync,
    S: Fn(&Vector3<f64>, usize, usize) -> f32 + Sync,
{
    if rect.is_empty() {
        return;
    }
    let (rw, rh) = (rect.width(), rect.height());
    let m = rot_cw.matrix();
    let dir = |xn: f64, yn: f64| -> Vector3<f64> { m * Vector3::new(xn, yn, 1.0) };
    // Labels and values at the corners of the rect's pixels.
    let mut hits: Vec<Hit> = vec![(0, 0.0, [0.0; 2]); (rw + 1) * (rh + 1)];
    hits.par_chunks_mut(rw + 1).enumerate().for_each(|(j, row)| {
        for (i, l) in row.iter_mut().enumerate() {
            let r = rays.at(rect.x0 + i, rect.y0 + j);
            *l = corner(&dir(r[0], r[1]));
        }
    });
    let inv = 1.0 / (n * n) as f32;
    out[..rw * rh].par_chunks_mut(rw).enumerate().for_each(|(j, row)| {
        let y = rect.y0 + j;
        for (i, px) in row.iter_mut().enumerate() {
            let x = rect.x0 + i;
            let h00 = hits[j * (rw + 1) + i];
            let h10 = hits[j * (rw + 1) + i + 1];
            let h01 = hits[(j + 1) * (rw + 1) + i];
            let h11 = hits[(j + 1) * (rw + 1) + i + 1];
            if h00.0 == h10.0 && h00.0 == h01.0 && h00.0 == h11.0 {
                match keep {
                    Some((pred, buf)) if pred(h00.0) => *px = buf[y * rays.w + x],
                    _ => *px = 0.25 * (h00.1 + h10.1 + h01.1 + h11.1),
                }
                continue;
            }
            let nf = n as f64;
            if let (Some(f), Some(key)) = (flat, tag_key(h00.0)) {
                if [h10.0, h01.0, h11.0].iter().all(|&l| tag_key(l) == Some(key)) {
                    let (a0, a1, a2, a3) = (h00.2, h10.2, h01.2, h11.2);
                    let mut sum = 0.0f32;
                    for a in 0..n {
                        for b in 0..n {
                            let (wa, wb, wc, wd) = rook_weights(a, b, nf);
                            let u = wa * a0[0] + wb * a1[0] + wc * a2[0] + wd * a3[0];
                            let v = wa * a0[1] + wb * a1[1] + wc * a2[1] + wd * a3[1];
                            sum += f(key, u, v);
                        }
                    }
                    *px = sum * inv;
                    continue;
                }
            }
            // Other edges (paper, surfaces, silhouettes) are not what tags are measured on:
            // half the sub-samples per axis there.
            let n = (n / 2).max(2);
            let nf = n as f64;
            let inv = 1.0 / (n * n) as f32;
            let r00 = rays.at(x, y);
            let r10 = rays.at(x + 1, y);
            let r01 = rays.at(x, y + 1);
            let r11 = rays.at(x + 1, y + 1);
            let mut sum = 0.0f32;
            for a in 0..n {
                for b in 0..n {
                    let (wa, wb, wc, wd) = rook_weights(a, b, nf);
                    let d =
                        dir(wa * r00[0] + wb * r10[0] + wc * r01[0] + wd * r11[0], wa * r00[1] + wb * r10[1] + wc * r01[1] + wd * r11[1]);
                    sum += sample(&d, x, y);
                }
            }
            *px = sum * inv;
        }
    });
}

/// A normalised Gaussian kernel of standard deviation `sigma` (radius 3 sigma).
pub fn gaussian_kernel(sigma: f64) -> Vec<f32> {
    if sigma <= 0.0 {
        return vec![1.0];
    }
    let r = (3.0 * sigma).ceil() as i64;
    let k: Vec<f64> = (-r..=r).map(|i| (-(i * i) as f64 / (2.0 * sigma * sigma)).exp()).collect();
    let s: f64 = k.iter().sum();
    k.iter().map(|v| (v / s) as f32).collect()
}

/// Separable convolution of a `w × h` image with `kernel` (odd length), edges clamped.
pub fn blur(img: &[f32], w: usize, h: usize, kernel: &[f32]) -> Vec<f32> {
    if kernel.len() <= 1 || w == 0 || h == 0 {
        return img.to_vec();
    }
    let r = (kernel.len() / 2) as isize;
    let mut tmp = vec![0.0f32; w * h];
    tmp.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        let src = &img[y * w..(y + 1) * w];
        for (x, o) in row.iter_mut().enumerate() {
            let mut s = 0.0;
            for (k, kv) in kernel.iter().enumerate() {
                let xx = (x as isize + k as isize - r).clamp(0, w as isize - 1) as usize;
                s += kv * src[xx];
            }
            *o = s;
        }
    });
    let mut out = vec![0.0f32; w * h];
    out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        for (k, kv) in kernel.iter().enumerate() {
            let yy = (y as isize + k as isize - r).clamp(0, h as isize - 1) as usize;
            let src = &tmp[yy * w..(yy + 1) * w];
            for (o, s) in row.iter_mut().zip(src) {
                *o += kv * s;
            }
        }
    });
    out
}

/// Motion blur (camera shake): the mean of the image shifted along a straight streak of
/// `length` pixels at angle `angle`, centred on zero shift (the centroid does not move).
pub fn motion_blur(img: &[f32], w: usize, h: usize, length: f64, angle: f64) -> Vec<f32> {
    let steps = (length.ceil() as usize * 2).max(2) + 1;
    let (dx, dy) = (angle.cos() * length, angle.sin() * length);
    let offsets: Vec<(f64, f64)> = (0..steps)
        .map(|k| {
            let f = k as f64 / (steps - 1) as f64 - 0.5;
            (f * dx, f * dy)
        })
        .collect();
    let sample = |x: f64, y: f64| -> f32 {
        let x = x.clamp(0.0, (w - 1) as f64);
        let y = y.clamp(0.0, (h - 1) as f64);
        let (x0, y0) = (x.floor() as usize, y.floor() as usize);
        let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
        let (fx, fy) = ((x - x0 as f64) as f32, (y - y0 as f64) as f32);
        let a = img[y0 * w + x0] * (1.0 - fx) + img[y0 * w + x1] * fx;
        let b = img[y1 * w + x0] * (1.0 - fx) + img[y1 * w + x1] * fx;
        a * (1.0 - fy) + b * fy
    };
    let mut out = vec![0.0f32; w * h];
    let inv = 1.0 / steps as f32;
    out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        for (x, o) in row.iter_mut().enumerate() {
            let s: f32 = offsets.iter().map(|&(ox, oy)| sample(x as f64 + ox, y as f64 + oy)).sum();
            *o = s * inv;
        }
    });
    out
}

/// Adds Gaussian noise of `sigma` grey levels (seeded per row) and rounds to 8 bits.
pub fn quantize(img: &[f32], w: usize, h: usize, sigma: f64, seed: u64) -> GrayImage {
    quantize_bits(img, w, h, sigma, seed, 8)
}

/// Adds Gaussian noise of `sigma` grey levels (seeded per row) and digitises to a sensor of
/// `bits` bits ([`crate::formation::sensor_levels`]): at 8 bits the image is the rounded
/// levels; deeper, the sensor's values (`level · 2^(bits − 8)`) are kept as the image's
/// full-depth plane ([`tagdeflect_core::frame::DeepPlane`]) and the 8-bit plane is rounded
/// from them.
pub fn quantize_bits(img: &[f32], w: usize, h: usize, sigma: f64, seed: u64, bits: u32) -> GrayImage {
    let per_grey = (1u32 << bits.saturating_sub(8)) as f32;
    let max = ((1u32 << bits.max(8)) - 1) as f32;
    let mut values = vec![0u16; w * h];
    values.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        let mut rng = ChaCha8Rng::seed_from_u64(seed ^ (y as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15));
        let src = &img[y * w..(y + 1) * w];
        for (o, &v) in row.iter_mut().zip(src) {
            let noise = if sigma > 0.0 {
                let z: f64 = StandardNormal.sample(&mut rng);
                (z * sigma) as f32
            } else {
                0.0
            };
            *o = ((v + noise) * per_grey).round().clamp(0.0, max) as u16;
        }
    });
    if bits <= 8 {
        return GrayImage::from_8bit(w as u32, h as u32, values.into_iter().map(|v| v as u8).collect());
    }
    let mut out = GrayImage::new(w as u32, h as u32);
    out.deep = Some(DeepPlane { bits: bits as u8, data: values });
    out.fill_8bit_from_deep();
    out
}

/// Bilinear weights of the four pixel-corner rays for sub-sample (`a`, `b`) of an `nf`×`nf`
/// n-rooks pattern (every sub-sample in its own row and column of the pixel).
#[inline]
fn rook_weights(a: usize, b: usize, nf: f64) -> (f64, f64, f64, f64) {
    let fx = (a as f64 + (b as f64 + 0.5) / nf) / nf;
    let fy = (b as f64 + (a as f64 + 0.5) / nf) / nf;
    ((1.0 - fx) * (1.0 - fy), fx * (1.0 - fy), (1.0 - fx) * fy, fx * fy)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Optics;

    #[test]
    fn kernel_is_normalised_and_blur_keeps_the_mean() {
        let k = gaussian_kernel(1.2);
        assert!((k.iter().sum::<f32>() - 1.0).abs() < 1e-6);
        let (w, h) = (40, 30);
        let img: Vec<f32> = (0..w * h).map(|i| if (i % w) < 20 { 10.0 } else { 200.0 }).collect();
        let b = blur(&img, w, h, &k);
        // A vertical step stays centred between columns 19 and 20.
        let row = &b[15 * w..16 * w];
        assert!(((row[19] + row[20]) / 2.0 - 105.0).abs() < 1e-3);
        let m = motion_blur(&img, w, h, 4.0, 0.0);
        assert!(((m[15 * w + 19] + m[15 * w + 20]) / 2.0 - 105.0).abs() < 1e-3);
    }

    /// The standard normal CDF by Simpson's rule on the density (independent of the
    /// product's tables).
    fn normal_cdf(z: f64) -> f64 {
        let (a, n) = (-9.0, 4000);
        if z <= a {
            return 0.0;
        }
        let h = (z - a) / n as f64;
        let pdf = |x: f64| (-0.5 * x * x).exp() / (2.0 * std::f64::consts::PI).sqrt();
        let mut acc = pdf(a) + pdf(z);
        for k in 1..n {
            acc += if k % 2 == 1 { 4.0 } else { 2.0 } * pdf(a + k as f64 * h);
        }
        acc * h / 3.0
    }

    #[test]
    fn the_optics_blur_the_light_before_the_pixels_integrate_it() {
        // A vertical edge, dark left of x = 7.37 px, seen through a Gaussian PSF and then
        // integrated over each pixel: pixel x reads ∫ Φ((x + u − 7.37)/σ) du, u ∈ ±½.
        let k = CameraIntrinsics { width: 16, height: 8, fx: 1000.0, fy: 1000.0, cx: 7.0, cy: 3.5, dist: [0.0; 5] };
        let edge = 0.37;
        let trace = |d: &Vector3<f64>| -> Hit {
            if d.x / d.z * 1000.0 < edge {
                (1, 0.0, [0.0; 2])
            } else {
                (2, 100.0, [0.0; 2])
            }
        };
        for sigma in [0.3, 0.6, 1.0] {
            let optics = Optics::new(sigma);
            let s = optics.scale();
            let rays = CornerRays::sub_boxes(&k, s);
            let rect = PixelRect { x0: 0, y0: 0, x1: rays.w, y1: rays.h };
            let mut fine = vec![0.0; rays.w * rays.h];
            // Without a flat tag shading every mixed box takes (n/2)² samples: 8 × 8.
            let n = 16;
            render_rect(&rays, &Rotation3::identity(), rect, n, &trace, &|d: &Vector3<f64>, _, _| trace(d).1, None, None, &mut fine);
            let img = optics.apply(&fine, rays.w, rays.h);
            assert_eq!(img.len(), 16 * 8);
            let mut worst = 0.0f64;
            for x in 3..12 {
                let m = 200;
                let expected: f64 =
                    (0..m).map(|i| normal_cdf((x as f64 - 7.0 - edge + (i as f64 + 0.5) / m as f64 - 0.5) / sigma)).sum::<f64>() * 100.0
                        / m as f64;
                worst = worst.max((img[3 * 16 + x] as f64 - expected).abs());
            }
            // The sub-samples resolve the edge to 1/64 of a box: 100/128 grey levels at most.
            assert!(worst < 0.8, "sigma {sigma}: off by {worst} grey levels");
        }
        // The same PSF applied after the pixels (a sampled kernel on the pixel image) misses
        // the profile by several grey levels near the edge: what the optics are not.
        let rays = CornerRays::new(&k);
        let mut px = vec![0.0; 16 * 8];
        let rect = PixelRect { x0: 0, y0: 0, x1: 16, y1: 8 };
        render_rect(&rays, &Rotation3::identity(), rect, 16, &trace, &|d: &Vector3<f64>, _, _| trace(d).1, None, None, &mut px);
        let post = blur(&px, 16, 8, &gaussian_kernel(0.6));
        let physical = Optics::new(0.6);
        let rays2 = CornerRays::sub_boxes(&k, physical.scale());
        let mut fine = vec![0.0; rays2.w * rays2.h];
        let rect2 = PixelRect { x0: 0, y0: 0, x1: rays2.w, y1: rays2.h };
        render_rect(&rays2, &Rotation3::identity(), rect2, 16, &trace, &|d: &Vector3<f64>, _, _| trace(d).1, None, None, &mut fine);
        let img = physical.apply(&fine, rays2.w, rays2.h);
        let gap = (5..10).map(|x| (post[3 * 16 + x] - img[3 * 16 + x]).abs()).fold(0.0f32, f32::max);
        assert!(gap > 2.0, "{gap}");
    }

    #[test]
    fn area_integration_resolves_a_straight_edge() {
        // A camera looking down +z at a plane z = 1000 with an edge at world x = 0.37 px.
        let k = CameraIntrinsics { width: 16, height: 8, fx: 1000.0, fy: 1000.0, cx: 7.0, cy: 3.5, dist: [0.0; 5] };
        let rays = CornerRays::new(&k);
        let edge = 0.37; // pixels right of the principal point
        let trace = |d: &Vector3<f64>| -> Hit {
            let x = d.x / d.z * 1000.0; // pixels from cx
            if x < edge {
                (1, 0.0, [0.0; 2])
            } else {
                (2, 100.0, [0.0; 2])
            }
        };
        let rect = PixelRect { x0: 0, y0: 0, x1: 16, y1: 8 };
        let mut out = vec![0.0; 16 * 8];
        render_rect(&rays, &Rotation3::identity(), rect, 8, &trace, &|d: &Vector3<f64>, _, _| trace(d).1, None, None, &mut out);
        // Pixel 7 spans cx-0.5..cx+0.5: covered by the bright side from 0.37 to 0.5 → 13 %.
        let v = out[3 * 16 + 7];
        assert!((v - 13.0).abs() < 100.0 / 64.0, "{v}");
        assert_eq!(out[3 * 16 + 6], 0.0);
        assert_eq!(out[3 * 16 + 8], 100.0);
    }
}
