//! Image formations after the pixel: what a camera's image processor does to the integrated
//! pixels before they are stored — a discrete Gaussian kernel, a 3×3 sharpening kernel, the
//! bilinear demosaic of a colour (RGGB Bayer) sensor. Each works on a grey image of `f32`
//! grey levels, row-major, `w × h`, before noise and rounding ([`crate::quantize`]).

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
}
