//! Confirming a known tag at its predicted corners, without searching for it.
//!
//! Between frames a tag moves by a fraction of a pixel to a few pixels, and its corners
//! are predicted well by the last refined corners moved by the tag's image velocity (see
//! `detect::plan`). Instead of running the AprilTag library's quad search over a window
//! around the tag (whose cost grows with the texture inside the window), the tracked tag's
//! corners are fitted by the same sub-pixel edge refinement as every detection (see
//! [`super::refine`]), started from the prediction. The result is then **verified** by
//! reading the tag back: every cell of the black square and of the white ring is sampled
//! through the homography of the refined corners and compared with the tag's own bitmap.
//! A tag is accepted only when all four corners were refined (none kept, none moved more
//! than the refinement's `max_shift_px` from the prediction), the contrast is clear and
//! at most [`ConfirmOptions::max_wrong_cells`] cells disagree — otherwise the caller falls
//! back to a window search with the library. Accepted corners are therefore of exactly the
//! quality of refined library detections: the same fit on the same pixels, only started
//! from a different (and closer) guess.

use nalgebra::{Point2, Vector2};
use std::collections::HashMap;

use super::family::tag_bitmap;
use super::refine::{refine_corners_warm, EdgeMemory, RefineOptions};
use super::Detection;
use tagdeflect_core::camera::{apply_homography, Lens};
use tagdeflect_core::frame::GrayImage;
use tagdeflect_core::tags::{cell_homography, TagBitmap, TagFamily};

/// Acceptance limits of a confirmed tag.
#[derive(Debug, Clone, PartialEq)]
pub struct ConfirmOptions {
    /// Cells (black square and white ring) allowed to read the wrong colour (the library
    /// corrects up to 2 data bits by default).
    pub max_wrong_cells: u32,
    /// Smallest difference between the mean white and mean black cell, grey levels.
    pub min_contrast: f64,
    /// Refinement passes (at most the refinement's own). A second pass re-selects the
    /// pixels around the first pass's edges, which matters when the starting corners are
    /// a pixel off (library quads); predicted corners are within a few tenths of a pixel,
    /// and one pass gives the same measurement (3 × 1080p bench: displacement RMS
    /// 0.0082 mm with one pass or two) for two thirds of the cost.
    pub refine_passes: u32,
}

impl Default for ConfirmOptions {
    fn default() -> Self {
        Self { max_wrong_cells: 2, min_contrast: 10.0, refine_passes: 1 }
    }
}

/// Why a tag was not confirmed (the caller searches a window instead).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ConfirmMiss {
    /// Tags of this size cannot be refined (bits too narrow) or the id is unknown.
    Unsupported,
    /// A corner could not be refined or moved too far from the prediction.
    Refinement,
    /// The cells read back do not match the tag (wrong place, occluded, or too dim).
    Code,
}

/// Where a tracked tag is expected in a frame.
#[derive(Debug, Clone, PartialEq)]
pub struct Prediction {
    /// Its family.
    pub family: TagFamily,
    /// Its id.
    pub id: u32,
    /// Its predicted corners, pixels, SPEC order.
    pub corners: [Point2<f64>; 4],
    /// What its last fit in this camera left (warm start: about one iteration less per
    /// edge, and the pixels to fit while it has barely moved), or the default.
    pub memory: EdgeMemory,
}

/// A tag confirmed at its predicted place.
#[derive(Debug, Clone, PartialEq)]
pub struct ConfirmedTag {
    /// The tag with its refined corners (`decision_margin`: mean distance of its cells
    /// from the mid-grey threshold; `hamming`: cells read wrong).
    pub detection: Detection,
    /// Mean white cell minus mean black cell, grey levels.
    pub contrast: f64,
    /// What this fit leaves for the tag's next fit.
    pub memory: EdgeMemory,
}

/// Confirms known tags in frames. Immutable while confirming, so one confirmer serves every
/// camera and thread; the bitmaps of the tags given at construction are read once.
#[derive(Debug, Default)]
pub struct TagConfirmer {
    bitmaps: HashMap<(TagFamily, u32), TagBitmap>,
    options: ConfirmOptions,
}

impl TagConfirmer {
    /// A confirmer with the given acceptance limits, holding the bitmaps of `tags` (others
    /// are read from the family table when confirmed).
    pub fn new(options: ConfirmOptions, tags: impl IntoIterator<Item = (TagFamily, u32)>) -> Self {
        let bitmaps = tags.into_iter().filter_map(|(f, id)| tag_bitmap(f, id).ok().map(|b| ((f, id), b))).collect();
        Self { bitmaps, options }
    }

    /// Fits the predicted tag at its predicted corners and verifies it; see the module docs.
    pub fn confirm(
        &self,
        image: &GrayImage,
        prediction: &Prediction,
        lens: Lens<'_>,
        refine: &RefineOptions,
    ) -> Result<ConfirmedTag, ConfirmMiss> {
        let Prediction { family, id, corners: predicted, ref memory } = *prediction;
        let mut memory = memory.clone();
        let predicted = &predicted;
        let read;
        let bitmap = match self.bitmaps.get(&(family, id)) {
            Some(b) => b,
            None => {
                read = tag_bitmap(family, id).map_err(|_| ConfirmMiss::Unsupported)?;
                &read
            }
        };
        let mut det = Detection { family, id, corners: *predicted, decision_margin: 0.0, hamming: 0 };
        let refine = &RefineOptions { passes: self.options.refine_passes.min(refine.passes).max(1), ..refine.clone() };
        let report = refine_corners_warm(image, &mut det, lens, refine, &mut memory);
        if report.refined != 4 {
            return Err(if report.failed_fit == 4 && edge_bits_px(predicted, family) < refine.min_bit_px {
                ConfirmMiss::Unsupported
            } else {
                ConfirmMiss::Refinement
            });
        }
        let read = read_cells(image, &det.corners, bitmap, lens).ok_or(ConfirmMiss::Code)?;
        if read.contrast < self.options.min_contrast || read.wrong > self.options.max_wrong_cells {
            return Err(ConfirmMiss::Code);
        }
        det.decision_margin = read.margin as f32;
        det.hamming = read.wrong.min(u8::MAX as u32) as u8;
        Ok(ConfirmedTag { detection: det, contrast: read.contrast, memory })
    }
}

/// Mean length of the four edges, in bits of the family.
fn edge_bits_px(c: &[Point2<f64>; 4], family: TagFamily) -> f64 {
    let len: f64 = (0..4).map(|i| (c[(i + 1) % 4] - c[i]).norm()).sum::<f64>() / 4.0;
    len / family.width_at_border() as f64
}

/// What reading a tag's cells back gave.
#[derive(Debug, Clone, Copy, PartialEq)]
struct CellRead {
    /// Mean white cell minus mean black cell, grey levels.
    contrast: f64,
    /// Cells on the wrong side of the mid-grey threshold.
    wrong: u32,
    /// Mean distance of the cells from the threshold, grey levels.
    margin: f64,
}

/// Samples every cell of the printed tag (black square and white ring) at its centre and
/// four points around it, through the homography of `corners`.
fn read_cells(image: &GrayImage, corners: &[Point2<f64>; 4], bitmap: &TagBitmap, lens: Lens<'_>) -> Option<CellRead> {
    let nb = bitmap.width_at_border as f64;
    let ideal = corners.map(|c| lens.pixel_to_ideal(&c.coords, None));
    let h = cell_homography(&ideal, nb)?;
    let tw = bitmap.total_width;
    // Offset of the black square inside the printed tag, cells.
    let ring = ((tw - bitmap.width_at_border) / 2) as f64;
    let (w, hgt) = (image.width as f64, image.height as f64);
    let mut values = [0.0f64; 16 * 16];
    if (tw * tw) as usize > values.len() {
        return None;
    }
    let (mut white_sum, mut white_n, mut black_sum, mut black_n) = (0.0, 0.0, 0.0, 0.0);
    for row in 0..tw {
        for col in 0..tw {
            let (cx, cy) = (col as f64 + 0.5 - ring, row as f64 + 0.5 - ring);
            let mut v = 0.0;
            for (dx, dy) in [(0.0, 0.0), (-0.25, -0.25), (0.25, -0.25), (-0.25, 0.25), (0.25, 0.25)] {
                let u = apply_homography(&h, &Vector2::new(cx + dx, cy + dy))?;
                let p = lens.ideal_to_pixel(&u);
                if !(p.x >= 0.0 && p.y >= 0.0 && p.x <= w - 1.0 && p.y <= hgt - 1.0) {
                    return None;
                }
                v += image.sample(p.x, p.y);
            }
            v /= 5.0;
            values[(row * tw + col) as usize] = v;
            if bitmap.is_white(col, row) {
                white_sum += v;
                white_n += 1.0;
            } else {
                black_sum += v;
                black_n += 1.0;
            }
        }
    }
    if white_n == 0.0 || black_n == 0.0 {
        return None;
    }
    let (white, black) = (white_sum / white_n, black_sum / black_n);
    let threshold = 0.5 * (white + black);
    let (mut wrong, mut margin) = (0, 0.0);
    for row in 0..tw {
        for col in 0..tw {
            let v = values[(row * tw + col) as usize];
            let d = if bitmap.is_white(col, row) { v - threshold } else { threshold - v };
            if d <= 0.0 {
                wrong += 1;
            }
            margin += d;
        }
    }
    Some(CellRead { contrast: white - black, wrong, margin: margin / (tw * tw) as f64 })
}
