//! A colour sensor's raw mosaic (V4L2 `RGGB`, `GRBG`, `GBRG`, `BA81`; GenICam `BayerRG8`,
//! `BayerGR8`, `BayerGB8`, `BayerBG8`) as a grey image at full resolution: every photosite
//! kept where it is, its channel's gain equalised — no demosaic, no interpolation.
//!
//! Why not demosaic: the tags are grey, so under any light every photosite sees the same
//! scene through its filter and differs from its neighbours only by its channel's gain. Once
//! the four sites of the 2 × 2 mosaic are brought to one gain, each pixel is a sample of the
//! scene where it lies, as a monochrome sensor's is. A demosaic (bilinear, as a camera's
//! firmware or a driver's conversion does) instead interpolates each channel from its own
//! sites, so each pixel's value becomes a different blur of its neighbours depending on its
//! place in the mosaic: the edge's profile changes with a two-pixel period, which no single
//! profile fits (up to ±0.08 px of bias with the edge's phase; docs/accuracy.md, "A colour
//! sensor").
//!
//! The gains are measured on each frame ([`site_gains`]): for every 2 × 2 cell bright enough
//! and unsaturated, each site's value over the mean of the cell's two green sites; the median
//! of those ratios per site, then the ratio of sums over the cells within 10 % of it (robust
//! to the cells on edges and to a minority of coloured surfaces), is that site's response to
//! grey, and its inverse its gain. Green stays
//! as it is (the reference). A scene mostly of one colour other than grey moves the medians
//! off grey's: this conversion is for grey targets in a mostly grey (concrete, steel, white
//! wall) scene.

use tagdeflect_core::frame::{DeepPlane, GrayImage};

/// The order of a 2 × 2 colour mosaic's filters, read along its first row then its second.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BayerPattern {
    /// Red, green / green, blue (V4L2 `RGGB`, GenICam `BayerRG8`).
    Rggb,
    /// Green, red / blue, green (V4L2 `GRBG`, GenICam `BayerGR8`).
    Grbg,
    /// Green, blue / red, green (V4L2 `GBRG`, GenICam `BayerGB8`).
    Gbrg,
    /// Blue, green / green, red (V4L2 `BA81`, GenICam `BayerBG8`).
    Bggr,
}

impl BayerPattern {
    /// Whether the photosites at even `x + y` (the cell's first and last) are the green ones.
    fn green_on_even(self) -> bool {
        matches!(self, BayerPattern::Grbg | BayerPattern::Gbrg)
    }

    /// The cell's two green sites (indices `x % 2 + 2 (y % 2)`).
    fn green_sites(self) -> [usize; 2] {
        if self.green_on_even() {
            [0, 3]
        } else {
            [1, 2]
        }
    }
}

/// The reference (the two green sites' mean) a cell needs to be used: dark cells' ratios are
/// mostly noise.
const MIN_REFERENCE: u8 = 32;
/// A cell with a site at or above this level is left out: a clipped site's ratio is wrong.
const SATURATED: u8 = 250;
/// Bins of the ratio histograms over `0..MAX_RATIO`.
const BINS: usize = 16_384;
/// The largest response to grey measured, relative to green.
const MAX_RATIO: f64 = 4.0;
/// Fewer usable cells than this: the gains stay 1 (a dark or blank frame).
const MIN_CELLS: u32 = 64;

/// A cell's ratio further than this from its site's median is left out of the gain (edges,
/// coloured surfaces).
const TRIM: f64 = 0.1;

/// The gain of each of the four sites of the 2 × 2 cell (index `x % 2 + 2 (y % 2)`) that
/// brings its response to a grey scene to the green sites' mean; all 1 when the frame has
/// too few usable cells. `data` is the `w × h` mosaic, row-major.
///
/// Two passes over the usable cells (bright enough, unclipped): the median of each site's
/// ratio to the cell's green mean (a histogram), then the ratio of the sums of the site's
/// values and of the green means over the cells within [`TRIM`] of that median — the median
/// alone sits on the lattice of 8-bit ratios, ~0.1 % off.
pub fn site_gains(data: &[u8], w: usize, h: usize, pattern: BayerPattern) -> [f64; 4] {
    let [g0, g1] = pattern.green_sites();
    let mut hist = vec![[0u32; 4]; BINS];
    let scale = BINS as f64 / MAX_RATIO;
    let cells = for_each_cell(data, w, h, [g0, g1], |v, reference| {
        for (site, &s) in v.iter().enumerate() {
            let bin = (f64::from(s) / reference * scale) as usize;
            hist[bin.min(BINS - 1)][site] += 1;
        }
    });
    if cells < MIN_CELLS {
        return [1.0; 4];
    }
    let medians: [f64; 4] = std::array::from_fn(|site| median_bin(&hist, site, cells) / scale);
    let (mut sums, mut refs) = ([0.0f64; 4], [0.0f64; 4]);
    for_each_cell(data, w, h, [g0, g1], |v, reference| {
        for (site, &s) in v.iter().enumerate() {
            let ratio = f64::from(s) / reference;
            if (ratio - medians[site]).abs() <= TRIM * medians[site] {
                sums[site] += f64::from(s);
                refs[site] += reference;
            }
        }
    });
    std::array::from_fn(|site| if sums[site] > 0.0 && refs[site] > 0.0 { refs[site] / sums[site] } else { 1.0 })
}

/// Calls `f` with the four sites' values and the green mean of every usable 2 × 2 cell
/// (greens' mean ≥ [`MIN_REFERENCE`], no site ≥ [`SATURATED`]); returns how many.
fn for_each_cell(data: &[u8], w: usize, h: usize, greens: [usize; 2], mut f: impl FnMut(&[u8; 4], f64)) -> u32 {
    let mut cells = 0u32;
    for y in (0..h.saturating_sub(1)).step_by(2) {
        let (top, bottom) = (&data[y * w..y * w + w], &data[(y + 1) * w..(y + 1) * w + w]);
        for x in (0..w.saturating_sub(1)).step_by(2) {
            let v = [top[x], top[x + 1], bottom[x], bottom[x + 1]];
            let reference = (f64::from(v[greens[0]]) + f64::from(v[greens[1]])) / 2.0;
            if reference < f64::from(MIN_REFERENCE) || v.iter().any(|&s| s >= SATURATED) {
                continue;
            }
            cells += 1;
            f(&v, reference);
        }
    }
    cells
}

/// The median of site `site`'s histogram (in bins, interpolated within the median's bin).
fn median_bin(hist: &[[u32; 4]], site: usize, total: u32) -> f64 {
    let half = f64::from(total) / 2.0;
    let mut below = 0.0;
    for (bin, counts) in hist.iter().enumerate() {
        let n = f64::from(counts[site]);
        if below + n >= half {
            return bin as f64 + (half - below) / n.max(1.0);
        }
        below += n;
    }
    BINS as f64
}

/// Bits of an equalised frame's full-depth plane: four below the 8-bit level, so a gain near 1
/// is not lost to rounding (rounded to 8 bits, `round(g · v)` is `v` for every dark level
/// when `g` is within `0.5 / v` of 1: a staircase that put the two green sites 0.5 grey levels
/// apart on the tags' black).
pub const EQUALISED_BITS: u8 = 12;

/// Equalises the 8-bit mosaic `img` in place: each site times its gain ([`site_gains`]),
/// kept at [`EQUALISED_BITS`] (the full-depth plane the edge fit reads) beside the 8-bit plane
/// rounded from it. Unchanged when every gain is 1.
pub fn equalise(img: &mut GrayImage, pattern: BayerPattern) {
    let (w, h) = (img.width as usize, img.height as usize);
    let gains = site_gains(&img.data, w, h, pattern);
    if gains == [1.0; 4] {
        return;
    }
    let scale = f64::from(1u32 << (EQUALISED_BITS - 8));
    let max = f64::from((1u32 << EQUALISED_BITS) - 1);
    let data = img
        .data
        .iter()
        .enumerate()
        .map(|(i, &v)| (f64::from(v) * gains[i % w % 2 + 2 * (i / w % 2)] * scale).round().clamp(0.0, max) as u16)
        .collect();
    img.deep = Some(DeepPlane { bits: EQUALISED_BITS, data });
    img.fill_8bit_from_deep();
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A grey scene (a vertical step from 40 to 200 at x = 13.3, plus a ramp) seen through
    /// `responses` per site, rounded to 8 bits.
    fn mosaic(w: usize, h: usize, responses: [f64; 4]) -> (Vec<f64>, Vec<u8>) {
        let grey: Vec<f64> = (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as f64, (i / w) as f64);
                let step = (x + 0.5 - 13.3).clamp(0.0, 1.0);
                40.0 + 160.0 * step + 0.3 * y
            })
            .collect();
        let raw = grey.iter().enumerate().map(|(i, g)| (g * responses[i % w % 2 + 2 * (i / w % 2)]).round() as u8).collect();
        (grey, raw)
    }

    #[test]
    fn a_grey_scene_through_unequal_channels_comes_back_grey() {
        let (w, h) = (40, 30);
        // A warm light on an RGGB sensor: red 0.62, the greens 1.0 and 0.97, blue 0.74 of green.
        let responses = [0.62, 1.0, 0.97, 0.74];
        let (grey, raw) = mosaic(w, h, responses);
        let gains = site_gains(&raw, w, h, BayerPattern::Rggb);
        // Relative to the two greens' mean (0.985).
        for (site, (g, r)) in gains.iter().zip(responses).enumerate() {
            let want = 0.985 / r;
            assert!((g - want).abs() < 0.01 * want, "site {site}: gain {g}, want {want}");
        }
        let mut img = GrayImage::from_8bit(w as u32, h as u32, raw);
        equalise(&mut img, BayerPattern::Rggb);
        assert_eq!(img.deep.as_ref().map(|d| d.bits), Some(EQUALISED_BITS));
        for (i, g) in grey.iter().enumerate() {
            // Within the mosaic's rounding (times the gain, up to 1.6) of the scene at green's gain.
            let v = f64::from(img.level(i));
            assert!((v - 0.985 * g).abs() <= 0.85 + 0.002 * g, "pixel {i}: {v} vs {}", 0.985 * g);
        }
    }

    #[test]
    fn the_green_sites_follow_the_pattern() {
        let (w, h) = (40, 30);
        // GRBG: green at the cell's first and last sites.
        let responses = [1.0, 0.55, 0.8, 1.0];
        let (_, raw) = mosaic(w, h, responses);
        let gains = site_gains(&raw, w, h, BayerPattern::Grbg);
        assert!((gains[0] - 1.0).abs() < 0.01 && (gains[3] - 1.0).abs() < 0.01, "{gains:?}");
        assert!((gains[1] - 1.0 / 0.55).abs() < 0.02 && (gains[2] - 1.0 / 0.8).abs() < 0.02, "{gains:?}");
    }

    #[test]
    fn a_dark_frame_keeps_its_levels() {
        let mut raw = vec![10u8; 16 * 12];
        raw[5] = 3;
        assert_eq!(site_gains(&raw, 16, 12, BayerPattern::Rggb), [1.0; 4]);
        let mut img = GrayImage::from_8bit(16, 12, raw.clone());
        equalise(&mut img, BayerPattern::Rggb);
        assert_eq!(img.data, raw);
        assert!(img.deep.is_none());
    }
}
