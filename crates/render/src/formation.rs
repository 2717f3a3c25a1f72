//! Image formations: what a camera's image processor does to the integrated pixels before
//! they are stored — a discrete Gaussian kernel, a 3×3 sharpening kernel, the bilinear
//! demosaic of a colour (RGGB Bayer) sensor, JPEG compression — each on a grey image of
//! `f32` grey levels, row-major, `w × h`, before noise and rounding ([`crate::quantize`])
//! except JPEG, which takes the stored 8-bit image; the sensor's bit depth
//! ([`sensor_levels`]); and the point-spread functions and pixel aperture that act *before*
//! the pixel ([`defocus_disk`], [`astigmatic_gaussian`], [`pixel_aperture`]), on the
//! sub-box grid of [`crate::Optics`].

use tagdeflect_core::frame::GrayImage;

use super::pixels::{blur, gaussian_kernel};

/// Weights of the grey value computed from a demosaiced (R, G, B) pixel (ITU-R BT.601).
const GREY_WEIGHTS: [f32; 3] = [0.299, 0.587, 0.114];

/// The discrete Gaussian kernel of σ `sigma_px` pixels applied over the integrated pixels
/// (separable; the image edge is clamped).
pub fn blur_after_pixels(img: &[f32], w: usize, h: usize, sigma_px: f64) -> Vec<f32> {
    if sigma_px <= 0.0 {
        return img.to_vec();
    }
    blur(img, w, h, &gaussian_kernel(sigma_px))
}

/// The 3×3 unsharp kernel of `amount` (row-major): the identity plus `amount` times the
/// image minus its 4-neighbour mean; its weights sum to 1 (flat regions stay flat).
pub fn sharpen_kernel(amount: f64) -> [f32; 9] {
    let a = amount as f32;
    [0.0, -a / 4.0, 0.0, -a / 4.0, 1.0 + a, -a / 4.0, 0.0, -a / 4.0, 0.0]
}

/// `img` convolved with the 3×3 `kernel` (row-major; the image edge is clamped).
pub fn convolve3x3(img: &[f32], w: usize, h: usize, kernel: &[f32; 9]) -> Vec<f32> {
    let at = |x: isize, y: isize| img[y.clamp(0, h as isize - 1) as usize * w + x.clamp(0, w as isize - 1) as usize];
    let mut out = vec![0.0f32; w * h];
    for y in 0..h as isize {
        for x in 0..w as isize {
            let mut s = 0.0f32;
            for (k, wk) in kernel.iter().enumerate() {
                s += wk * at(x + (k % 3) as isize - 1, y + (k / 3) as isize - 1);
            }
            out[y as usize * w + x as usize] = s;
        }
    }
    out
}

/// Responses to grey of an RGGB sensor's four sites (index `x % 2 + 2 (y % 2)`: red, green
/// on the red rows, green on the blue rows, blue) under a warm light, before any white
/// balance: red and blue well below green, the two greens 2 % apart (a common imbalance).
pub const RAW_BAYER_RESPONSES: [f32; 4] = [0.62, 1.0, 0.98, 0.74];

/// A grey scene as an RGGB sensor's raw mosaic: every photosite sees the grey level through
/// its filter, scaled by its site's response ([`RAW_BAYER_RESPONSES`]); nothing interpolated.
pub fn bayer_mosaic(img: &[f32], w: usize, responses: &[f32; 4]) -> Vec<f32> {
    img.iter().enumerate().map(|(i, v)| v * responses[i % w % 2 + 2 * (i / w % 2)]).collect()
}

/// Colour channel (0 R, 1 G, 2 B) of an RGGB Bayer sensor's pixel `(x, y)`.
fn bayer_channel(x: usize, y: usize) -> usize {
    match (x % 2, y % 2) {
        (0, 0) => 0,
        (1, 1) => 2,
        _ => 1,
    }
}

/// A grey scene seen through an RGGB colour sensor: the mosaic (every photosite sees the
/// grey level through its filter, the channels white-balanced to equal gains), each
/// channel interpolated bilinearly from its own photosites (the mean of the nearest ones),
/// then converted back to grey ([`GREY_WEIGHTS`]).
pub fn bayer_demosaic_bilinear(img: &[f32], w: usize, h: usize) -> Vec<f32> {
    let mut out = vec![0.0f32; w * h];
    for y in 0..h {
        for x in 0..w {
            let mut rgb = [0.0f32; 3];
            for (c, v) in rgb.iter_mut().enumerate() {
                *v = channel_at(img, w, h, x, y, c);
            }
            out[y * w + x] = GREY_WEIGHTS.iter().zip(rgb).map(|(g, v)| g * v).sum();
        }
    }
    out
}

/// Channel `c` at `(x, y)`: the photosite's own value when it has that filter, else the
/// mean of the photosites of that filter in its 3×3 neighbourhood (bilinear interpolation).
fn channel_at(img: &[f32], w: usize, h: usize, x: usize, y: usize, c: usize) -> f32 {
    if bayer_channel(x, y) == c {
        return img[y * w + x];
    }
    let (mut sum, mut n) = (0.0f32, 0u32);
    for yy in y.saturating_sub(1)..(y + 2).min(h) {
        for xx in x.saturating_sub(1)..(x + 2).min(w) {
            if bayer_channel(xx, yy) == c {
                sum += img[yy * w + xx];
                n += 1;
            }
        }
    }
    if n == 0 {
        img[y * w + x]
    } else {
        sum / n as f32
    }
}

/// A square kernel of `n × n` taps (`n` odd, centred), row-major: a point-spread function
/// on the sub-box grid of [`crate::Optics`].
#[derive(Debug, Clone, PartialEq)]
pub struct Kernel2 {
    /// Taps along each axis.
    pub n: usize,
    /// `n × n` weights, row-major.
    pub taps: Vec<f32>,
}

impl Kernel2 {
    /// The separable kernel `col[y] · row[x]`; both of length `n`.
    pub fn outer(col: &[f32], row: &[f32]) -> Kernel2 {
        debug_assert_eq!(col.len(), row.len());
        Kernel2 { n: row.len(), taps: col.iter().flat_map(|c| row.iter().map(move |r| c * r)).collect() }
    }

    /// The full convolution of the two kernels (`n + other.n − 1` taps along each axis).
    pub fn convolve(&self, other: &Kernel2) -> Kernel2 {
        let (a, b) = (self.n, other.n);
        let n = a + b - 1;
        let mut taps = vec![0.0f32; n * n];
        for (i, ta) in self.taps.iter().enumerate() {
            for (j, tb) in other.taps.iter().enumerate() {
                taps[(i / a + j / b) * n + i % a + j % b] += ta * tb;
            }
        }
        Kernel2 { n, taps }
    }

    /// The sum of the taps.
    pub fn sum(&self) -> f32 {
        self.taps.iter().sum()
    }

    /// The kernel with its taps scaled to sum to 1.
    fn normalised(mut self) -> Kernel2 {
        let s = self.sum();
        self.taps.iter_mut().for_each(|t| *t /= s);
        self
    }
}

/// The area of a disk of `radius_px` in each sub-box of `1/scale` px around its centre,
/// px² (`(2⌈radius·scale⌉ + 1)²` sub-boxes; each by 32 × 32 samples).
fn disk_areas_px2(radius_px: f64, scale: usize) -> Kernel2 {
    let rs = radius_px * scale as f64;
    let r = rs.ceil() as usize;
    let n = 2 * r + 1;
    let m = 32;
    let cell = 1.0 / (scale * scale * m * m) as f32;
    let mut taps = vec![0.0f32; n * n];
    for (k, t) in taps.iter_mut().enumerate() {
        let (cy, cx) = ((k / n) as f64 - r as f64, (k % n) as f64 - r as f64);
        let inside = (0..m * m)
            .filter(|q| {
                let dx = cx - 0.5 + ((q % m) as f64 + 0.5) / m as f64;
                let dy = cy - 0.5 + ((q / m) as f64 + 0.5) / m as f64;
                dx * dx + dy * dy <= rs * rs
            })
            .count();
        *t = inside as f32 * cell;
    }
    Kernel2 { n, taps }
}

/// A defocus disk of `radius_px` (the light of a point spread uniformly over a disk: a
/// lens focused off the target plane) on the sub-box grid of `1/scale` px: each tap the
/// disk's area in its sub-box, normalised to sum to 1.
pub fn defocus_disk(radius_px: f64, scale: usize) -> Kernel2 {
    disk_areas_px2(radius_px, scale).normalised()
}

/// An elliptical (astigmatic) Gaussian of σ `major_px` along the axis at `angle_deg` from
/// the image's x axis towards its y axis, σ `minor_px` across it, sampled on the sub-box
/// grid of `1/scale` px out to 3.5 σ of the major axis, normalised to sum to 1.
pub fn astigmatic_gaussian(major_px: f64, minor_px: f64, angle_deg: f64, scale: usize) -> Kernel2 {
    let r = (3.5 * major_px * scale as f64).ceil() as usize;
    let n = 2 * r + 1;
    let (sin, cos) = angle_deg.to_radians().sin_cos();
    let taps = (0..n * n)
        .map(|k| {
            let x = ((k % n) as f64 - r as f64) / scale as f64;
            let y = ((k / n) as f64 - r as f64) / scale as f64;
            let (u, v) = (x * cos + y * sin, -x * sin + y * cos);
            (-0.5 * (u * u / (major_px * major_px) + v * v / (minor_px * minor_px))).exp() as f32
        })
        .collect();
    Kernel2 { n, taps }.normalised()
}

/// The weights of a pixel's `scale` sub-boxes along one axis when only a centred square of
/// `fill_factor` of its area integrates the light (side `√fill_factor`): each sub-box's
/// share of the square's side, summing to 1 (`1/scale` each at a fill factor of 1).
pub fn pixel_aperture(fill_factor: f64, scale: usize) -> Vec<f32> {
    let half = 0.5 * fill_factor.clamp(1e-6, 1.0).sqrt();
    (0..scale)
        .map(|m| {
            let (a, b) = (m as f64 / scale as f64 - 0.5, (m + 1) as f64 / scale as f64 - 0.5);
            ((b.min(half) - a.max(-half)).max(0.0) / (2.0 * half)) as f32
        })
        .collect()
}

/// A grey level (8-bit units, before rounding) as a sensor of `bits` bits digitises it: to
/// the nearest of its `2^bits` levels, `2^(bits − 8)` per 8-bit grey level, within the
/// sensor's range.
pub fn sensor_levels(v: f32, bits: u32) -> f32 {
    let per_grey = (1u32 << bits.saturating_sub(8)) as f32;
    ((v * per_grey).round() / per_grey).clamp(0.0, 255.0 + 1.0 - 1.0 / per_grey)
}

/// The 8-bit image as a camera that compresses its frames stores it: encoded as a
/// baseline JPEG of `quality` (1–100, the `image` crate's encoder), then decoded.
pub fn jpeg_round_trip(img: &GrayImage, quality: u8) -> image::ImageResult<GrayImage> {
    let mut bytes = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut bytes, quality).encode(
        &img.data,
        img.width,
        img.height,
        image::ExtendedColorType::L8,
    )?;
    let decoded = image::load_from_memory_with_format(&bytes, image::ImageFormat::Jpeg)?.into_luma8();
    Ok(GrayImage { width: decoded.width(), height: decoded.height(), data: decoded.into_raw(), deep: None })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_sharpen_kernel_sums_to_one_and_keeps_flat_regions() {
        for amount in [0.0, 0.5, 1.0, 2.0] {
            let k = sharpen_kernel(amount);
            assert!((k.iter().sum::<f32>() - 1.0).abs() < 1e-6, "{k:?}");
        }
        let flat = vec![100.0f32; 20 * 10];
        let out = convolve3x3(&flat, 20, 10, &sharpen_kernel(1.0));
        assert!(out.iter().all(|v| (v - 100.0).abs() < 1e-3));
    }

    #[test]
    fn sharpening_overshoots_a_step() {
        let (w, h) = (12, 4);
        let img: Vec<f32> = (0..w * h).map(|i| if i % w < 6 { 20.0 } else { 200.0 }).collect();
        let out = convolve3x3(&img, w, h, &sharpen_kernel(1.0));
        assert!(out[w + 5] < 20.0 && out[w + 6] > 200.0, "{:?}", &out[w..2 * w]);
        assert_eq!(out[w], 20.0);
    }

    #[test]
    fn the_gaussian_after_the_pixels_keeps_the_mean() {
        let (w, h) = (16, 16);
        let mut img = vec![10.0f32; w * h];
        img[8 * w + 8] = 1010.0;
        let out = blur_after_pixels(&img, w, h, 1.0);
        let (a, b): (f32, f32) = (img.iter().sum(), out.iter().sum());
        assert!((a - b).abs() < 1e-2 * a, "{a} vs {b}");
        assert!(out[8 * w + 8] < 300.0 && out[8 * w + 9] > 10.0);
        assert_eq!(blur_after_pixels(&img, w, h, 0.0), img);
    }

    #[test]
    fn demosaic_of_a_flat_grey_is_flat() {
        let (w, h) = (9, 7);
        let out = bayer_demosaic_bilinear(&vec![77.0f32; w * h], w, h);
        assert!(out.iter().all(|v| (v - 77.0).abs() < 1e-3), "{out:?}");
    }

    #[test]
    fn demosaic_softens_a_step() {
        let (w, h) = (10, 6);
        let img: Vec<f32> = (0..w * h).map(|i| if i % w < 5 { 0.0 } else { 100.0 }).collect();
        let out = bayer_demosaic_bilinear(&img, w, h);
        // Away from the step the image is unchanged; beside it the interpolated channels mix.
        assert!((out[2 * w + 1]).abs() < 1e-3 && (out[2 * w + 8] - 100.0).abs() < 1e-3);
        assert!(out[2 * w + 4] > 1.0 && out[2 * w + 5] < 99.0, "{:?}", &out[2 * w..3 * w]);
    }

    #[test]
    fn the_defocus_disk_has_the_disks_area_and_sums_to_one() {
        for (radius, scale) in [(1.5, 4), (0.8, 4), (2.0, 3)] {
            let areas = disk_areas_px2(radius, scale);
            let want = std::f64::consts::PI * radius * radius;
            assert!((areas.sum() as f64 - want).abs() < 0.005 * want, "r {radius}: {} px² vs {want}", areas.sum());
            let k = defocus_disk(radius, scale);
            assert!((k.sum() - 1.0).abs() < 1e-5);
            // Round: the same weight a quarter turn away, nothing beyond the rim.
            let (n, c) = (k.n, k.n / 2);
            for y in 0..n {
                for x in 0..n {
                    assert!((k.taps[y * n + x] - k.taps[x * n + (n - 1 - y)]).abs() < 1e-6);
                    let d = ((x as f64 - c as f64).hypot(y as f64 - c as f64) - 0.75) / scale as f64;
                    if d > radius {
                        assert_eq!(k.taps[y * n + x], 0.0);
                    }
                }
            }
        }
    }

    #[test]
    fn the_ellipse_has_the_second_moments_given() {
        let (major, minor, angle, scale) = (1.0, 0.4, 30.0f64, 3);
        let k = astigmatic_gaussian(major, minor, angle, scale);
        assert!((k.sum() - 1.0).abs() < 1e-5);
        let (n, r) = (k.n, (k.n / 2) as f64);
        let (sin, cos) = angle.to_radians().sin_cos();
        let (mut uu, mut vv, mut uv, mut mx) = (0.0, 0.0, 0.0, 0.0);
        for (i, t) in k.taps.iter().enumerate() {
            let (x, y) = (((i % n) as f64 - r) / scale as f64, ((i / n) as f64 - r) / scale as f64);
            let (u, v) = (x * cos + y * sin, -x * sin + y * cos);
            let t = *t as f64;
            (uu, vv, uv, mx) = (uu + t * u * u, vv + t * v * v, uv + t * u * v, mx + t * x);
        }
        assert!((uu.sqrt() - major).abs() < 0.01 * major, "σ major {}", uu.sqrt());
        assert!((vv.sqrt() - minor).abs() < 0.01 * minor, "σ minor {}", vv.sqrt());
        assert!(uv.abs() < 1e-4 && mx.abs() < 1e-6, "{uv} {mx}");
    }

    #[test]
    fn the_pixel_aperture_covers_the_fill_factor() {
        let full = pixel_aperture(1.0, 4);
        assert!(full.iter().all(|w| (w - 0.25).abs() < 1e-6));
        let half = pixel_aperture(0.5, 4);
        assert!((half.iter().sum::<f32>() - 1.0).abs() < 1e-6);
        // Side √0.5 ≈ 0.707 px: the inner quarters whole, the outer ones 0.104 px each.
        let side = 0.5f32.sqrt();
        assert!((half[0] - (side / 2.0 - 0.25) / side).abs() < 1e-5 && (half[1] - 0.25 / side).abs() < 1e-5, "{half:?}");
        assert_eq!(half[0], half[3]);
    }

    #[test]
    fn a_flat_grey_stays_flat_through_every_optics_and_the_jpeg() {
        use crate::{Optics, OpticsSpec};
        let specs = [
            OpticsSpec { defocus_radius_px: 1.5, ..OpticsSpec::gaussian(0.0) },
            OpticsSpec {
                astigmatism: Some(crate::Astigmatism { major_px: 1.0, minor_px: 0.4, angle_deg: 30.0 }),
                ..OpticsSpec::gaussian(0.0)
            },
            OpticsSpec { fill_factor: 0.5, ..OpticsSpec::gaussian(0.7) },
        ];
        for spec in specs {
            let optics = Optics::of(&spec);
            let s = optics.scale();
            let (w, h) = (24 * s, 16 * s);
            let out = optics.apply(&vec![83.0f32; w * h], w, h);
            assert_eq!(out.len(), 24 * 16);
            assert!(out.iter().all(|v| (v - 83.0).abs() < 1e-3), "{spec:?}");
        }
        for bits in [8, 10, 12] {
            assert_eq!(sensor_levels(83.0, bits), 83.0);
        }
        let flat = GrayImage { width: 64, height: 48, data: vec![131; 64 * 48], deep: None };
        let back = jpeg_round_trip(&flat, 90).unwrap();
        assert_eq!((back.width, back.height), (64, 48));
        assert!(back.data.iter().all(|&v| v.abs_diff(131) <= 1), "{:?}", &back.data[..8]);
    }

    #[test]
    fn a_deeper_sensor_keeps_finer_levels() {
        assert_eq!(sensor_levels(10.3, 8), 10.0);
        assert_eq!(sensor_levels(10.3, 10), 10.25);
        assert_eq!(sensor_levels(10.3, 12), 10.3125);
        assert_eq!(sensor_levels(300.0, 12), 255.9375);
        assert_eq!(sensor_levels(-4.0, 10), 0.0);
    }

    #[test]
    fn jpeg_keeps_a_step_close_and_costs_detail() {
        let (w, h) = (32u32, 16u32);
        let data: Vec<u8> = (0..w * h).map(|i| if i % w < 13 { 40 } else { 200 }).collect();
        let img = GrayImage { width: w, height: h, data, deep: None };
        let back = jpeg_round_trip(&img, 90).unwrap();
        let err = img.data.iter().zip(&back.data).map(|(a, b)| a.abs_diff(*b)).max().unwrap();
        assert!(err > 0 && err < 40, "largest change {err}");
        let low = jpeg_round_trip(&img, 20).unwrap();
        let sq = |b: &GrayImage| img.data.iter().zip(&b.data).map(|(a, b)| (*a as f64 - *b as f64).powi(2)).sum::<f64>();
        assert!(sq(&low) > sq(&back));
    }
}
