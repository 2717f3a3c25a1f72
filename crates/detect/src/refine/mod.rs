//! Sub-pixel corner refinement: fits each edge of a tag's black square to the image.
//!
//! The AprilTag library's corners scatter by about 0.08 px; the measurement needs several
//! times better. For each of the four edges this module fits a blurred-step edge model to the
//! raw pixel values in a band along the edge (away from the corners), by Levenberg–Marquardt
//! over the line's angle and offset, the two grey levels and the blur width:
//!
//! ```text
//! I(n) = B + C · ( S(n) + white · S(−n − g) ),   S(x) = Φ(x / σ)
//! ```
//!
//! where `n` is the signed distance (pixels, outwards positive) of the pixel centre from the
//! edge line, and the second term models the data bits just inside the 1-bit black border
//! where they are white (`g` = local bit width; the bit colours are read from the image, so
//! no family table is needed). `white` is not a 0/1 flag but the blurred indicator of the
//! white bits along the edge (1 inside a run of white bits, fading over the blur at its ends
//! and reaching into the black bits beside it): a white bit is a square, and a blurred
//! square's corner is the product of its two edges' profiles. Modelled as 0/1, the white
//! bits' corners biased every edge inwards, the more the smaller the bits in pixels — on a
//! tilted calibration board, the far side more than the near one, which put fx low by 1.5–2σ
//! (docs/calibration.md). Adjacent edge lines are then intersected for the corners.
//!
//! Every pixel integrates light over its area. While the optics blur more than a pixel, a
//! Gaussian of fitted width absorbs that (the model above, at the pixel's centre); for edges
//! sharper than `fit::SHARP_PX` (0.55 px effective blur) `S` is averaged over the pixel's
//! width across the edge instead, where a Gaussian fitted to the ramp that a sharp edge makes
//! was biased by the edge's sub-pixel phase (`fit::pixel_step`; figures there).
//!
//! Pixels are used at their centres (OpenCV convention) with their own values — no
//! interpolation, which would smooth and bias. With a [`CameraIntrinsics`] the fit runs in
//! undistorted ("ideal") pixel coordinates, where the edges are straight, and the corners are
//! mapped back to distorted pixels. Tag coordinates (which bit a pixel belongs to) come from
//! the homography of the current corners, so the bands follow perspective exactly.
//!
//! Robustness: an edge whose fit fails (too few pixels, no contrast, implausible blur, large
//! residual) leaves its two corners as they were, and a corner that would move more than
//! [`RefineOptions::max_shift_px`] keeps the library's value; both are counted in the
//! [`RefineReport`].
//!
//! **Pixels kept between frames.** Selecting a band's pixels (which pixel lies where
//! relative to the edge and to which bit, through the lens map and the homography) costs
//! as much as fitting them. A tracked tag's fit leaves its selection in an [`EdgeMemory`];
//! the next frame's fit of the same tag reuses it while the corners it starts from are
//! within [`RefineOptions::band_reuse_px`] (0.1 px) of those the selection was made
//! around, reading only the new pixel values. The fit stays continuous in the corners
//! it starts from (tapered weights), so a selection made 0.1 px away changes the result by
//! a small fraction of that: the 3 × 1080p benches (clean and noisy, tags moving up to
//! 0.17 px per frame) give the same displacement RMS to 0.0001 mm with reuse and without,
//! while 0.25 px already worsens the net deflection RMS by 0.0002 mm. In a real test the
//! specimen moves a few µm per frame, so nearly every fit reuses its pixels.
//!
//! **Files.** `band` selects the pixels each edge is fitted on (which pixel lies where
//! relative to the edge and to which bit, and with what weight); `fit` fits the edge model
//! to their values; `profile` learns a camera's edge profile and `profile_fit` fits with
//! it; `kernel2d` is the image formation as a 2-D kernel after the pixel, and `formation`
//! the whole physical order (blur before the pixel, aperture, kernel after it), measurement
//! switches (`TAGDEFLECT_EDGE_MODEL`); this file holds the options, the reports, the memory
//! kept between frames and the passes that tie them together.
//!
//! **Layering.** Refinement builds on the detector's output, not on the detector: it takes
//! a [`Detection`] (the crate root's type, whoever found it), reports bad options as a
//! [`DetectError`] (defined in `crate::error`, below both) and imports nothing from
//! [`crate::apriltag`]. The imports go one way: the AprilTag wrapper, the confirmer and
//! the camera detector call this module.

use nalgebra::{Point2, Vector2};

use crate::error::DetectError;
use crate::Detection;
use tagdeflect_core::camera::{CameraIntrinsics, Lens};
use tagdeflect_core::frame::GrayImage;
use tagdeflect_core::tags::cell_homography;

mod band;
mod excess;
mod fit;
mod formation;
mod kernel2d;
mod lm;
mod profile;
mod profile_classes;
mod profile_curve;
mod profile_fit;

use band::{select_band, EdgeBand, TagBands};
pub use excess::{widening, widening_switch, ModelExcess, FLAT_SLOPE, RHO2_TOLERANCE};
use fit::{fit_band, Line};
pub use profile::{ClassChoice, ClassUse, EdgeProfile, ProfileLearner};
use profile_fit::fit_band_profile;

/// The blur σ (pixels) an edge's fit starts from when no earlier fit of it is known.
pub(crate) const DEFAULT_BLUR_PX: f64 = 0.8;

/// Options of the sub-pixel refinement.
#[derive(Debug, Clone, PartialEq)]
pub struct RefineOptions {
    /// A corner that would move further than this (pixels) keeps its input value.
    pub max_shift_px: f64,
    /// How deep into the tag the band reaches, in bits (at most 2 − margin: beyond the
    /// first data bit lie unknown bits).
    pub inner_band_bits: f64,
    /// How far out of the tag the band reaches, in bits (at most the 1-bit white ring).
    pub outer_band_bits: f64,
    /// Distance (pixels) kept from the corners along each edge and from unknown neighbours.
    pub margin_px: f64,
    /// Tags whose bits are narrower than this (pixels) are not refined.
    pub min_bit_px: f64,
    /// The band never reaches further than this from the edge (pixels), inwards or outwards:
    /// enough for the blur, and it bounds the cost on large tags.
    pub max_band_px: f64,
    /// Edges longer than this (pixels) use every other pixel (checkerboard) to bound the cost.
    pub checker_above_px: f64,
    /// Refinement passes (each re-selects the pixels around the previous pass's edges).
    pub passes: u32,
    /// A tag's next fit reuses the pixels its last fit was selected on while its starting
    /// corners stay within this distance (pixels) of that selection's (0: always select
    /// anew); see [`refine_corners_warm`].
    pub band_reuse_px: f64,
    /// Width of the tags' black border in bits (1, or 2 for Kalibr's AprilGrid): the corners
    /// are those of a black square `width_at_border + 2 (border_bits − 1)` bits across.
    pub border_bits: u32,
}

impl Default for RefineOptions {
    fn default() -> Self {
        Self {
            max_shift_px: 1.5,
            inner_band_bits: 1.5,
            outer_band_bits: 0.8,
            margin_px: 2.0,
            min_bit_px: 2.0,
            max_band_px: 6.0,
            checker_above_px: 120.0,
            passes: 2,
            band_reuse_px: 0.1,
            border_bits: 1,
        }
    }
}

impl RefineOptions {
    /// Checks the options' ranges.
    pub(crate) fn validate(&self) -> Result<(), DetectError> {
        let bad = |name, value: f64, expected| Err(DetectError::BadOption { name, value: value.to_string(), expected });
        if !(self.max_shift_px > 0.0 && self.max_shift_px.is_finite()) {
            return bad("subpixel.max_shift_px", self.max_shift_px, "expected a positive number of pixels");
        }
        if !(self.inner_band_bits > 0.2 && self.inner_band_bits <= 2.0) {
            return bad("subpixel.inner_band_bits", self.inner_band_bits, "expected 0.2 to 2.0 bits");
        }
        if !(self.outer_band_bits > 0.2 && self.outer_band_bits <= 1.0) {
            return bad("subpixel.outer_band_bits", self.outer_band_bits, "expected 0.2 to 1.0 bits");
        }
        if !(self.margin_px >= 0.0 && self.margin_px <= 20.0) {
            return bad("subpixel.margin_px", self.margin_px, "expected 0 to 20 pixels");
        }
        if !(self.min_bit_px >= 1.0 && self.min_bit_px.is_finite()) {
            return bad("subpixel.min_bit_px", self.min_bit_px, "expected at least 1 pixel");
        }
        if !(self.max_band_px >= 2.0 && self.max_band_px <= 100.0) {
            return bad("subpixel.max_band_px", self.max_band_px, "expected 2 to 100 pixels");
        }
        if self.checker_above_px.is_nan() || self.checker_above_px < 0.0 {
            return bad("subpixel.checker_above_px", self.checker_above_px, "expected a length in pixels (0 = always)");
        }
        if !(self.band_reuse_px >= 0.0 && self.band_reuse_px <= 2.0) {
            return bad("subpixel.band_reuse_px", self.band_reuse_px, "expected 0 to 2 pixels");
        }
        if !(1..=2).contains(&self.border_bits) {
            return bad("subpixel.border_bits", self.border_bits as f64, "expected 1 or 2 bits");
        }
        if self.passes == 0 || self.passes > 10 {
            return bad("subpixel.passes", self.passes as f64, "expected 1 to 10");
        }
        Ok(())
    }
}

/// What happened to one detection's corners.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct RefineReport {
    /// Corners replaced by refined values.
    pub refined: u8,
    /// Corners that kept their input value (fit failed, or moved too far).
    pub kept: u8,
    /// Of `kept`: corners kept because an adjacent edge fit failed or was implausible.
    pub failed_fit: u8,
    /// Of `kept`: corners kept because the refined corner moved more than `max_shift_px`.
    pub too_far: u8,
}

/// Refinement counts over many detections.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct RefineStats {
    /// Detections processed.
    pub tags: u64,
    /// Corners refined.
    pub corners_refined: u64,
    /// Corners that kept the library's value.
    pub corners_kept: u64,
    /// Of `corners_kept`: because an edge fit failed.
    pub failed_fit: u64,
    /// Of `corners_kept`: because the refined corner moved too far.
    pub too_far: u64,
}

impl RefineStats {
    /// Adds one detection's report.
    pub(crate) fn add(&mut self, r: &RefineReport) {
        self.tags += 1;
        self.corners_refined += r.refined as u64;
        self.corners_kept += r.kept as u64;
        self.failed_fit += r.failed_fit as u64;
        self.too_far += r.too_far as u64;
    }
}

/// Refines a detection's corners with the default options (see the module docs).
pub fn refine_corners(image: &GrayImage, det: &mut Detection, intrinsics: Option<&CameraIntrinsics>) -> RefineReport {
    refine_corners_with(image, det, intrinsics, &RefineOptions::default())
}

/// Refines a detection's corners in place; corners whose refinement fails or moves too far
/// keep their value. `intrinsics` (optional) straightens lens distortion during the fit.
pub fn refine_corners_with(
    image: &GrayImage,
    det: &mut Detection,
    intrinsics: Option<&CameraIntrinsics>,
    opts: &RefineOptions,
) -> RefineReport {
    refine_corners_warm(image, det, Lens::new(intrinsics), opts, &mut EdgeMemory::default())
}

/// Each edge's fitted black level, contrast and blur width (`None`: not fitted), edges in
/// SPEC order from the bottom edge; the warm start of the next fit of the same tag.
pub type EdgeLevels = [Option<[f64; 3]>; 4];

/// [`refine_corners_with`] through `lens` (e.g. one with the camera's [`IdealPixelMap`](tagdeflect_core::camera::IdealPixelMap)),
/// started from `memory` (the same tag's fit in the previous frame, or the default): the
/// edges' levels are the LM's warm start (fewer iterations), and when the corners to start
/// from are within [`RefineOptions::band_reuse_px`] of those the remembered pixels were
/// selected around, the first pass fits those pixels again instead of selecting them anew.
/// `memory` is replaced by this fit's.
pub fn refine_corners_warm(
    image: &GrayImage,
    det: &mut Detection,
    lens: Lens<'_>,
    opts: &RefineOptions,
    memory: &mut EdgeMemory,
) -> RefineReport {
    let keep_all = RefineReport { refined: 0, kept: 4, failed_fit: 4, too_far: 0 };
    if image.width < 4 || image.height < 4 || image.data.len() < image.width as usize * image.height as usize {
        return keep_all;
    }
    if det.corners.iter().any(|c| !(c.x.is_finite() && c.y.is_finite())) {
        return keep_all;
    }
    let nb = (det.family.width_at_border() + 2 * (opts.border_bits.clamp(1, 2) - 1)) as f64;
    let original = det.corners;
    // Corners in ideal coordinates.
    let mut ideal: [Vector2<f64>; 4] = original.map(|c| lens.pixel_to_ideal(&c.coords, None));
    let mut ok_edges = [false; 4];
    memory.reused = false;
    for pass in 0..opts.passes {
        let reuse = pass == 0 && memory.bands.as_ref().is_some_and(|b| b.serve(image, nb, &ideal, opts.band_reuse_px));
        let mut fresh: [Option<EdgeBand>; 4] = [None, None, None, None];
        if !reuse {
            let Some(h) = cell_homography(&ideal, nb) else {
                return keep_all;
            };
            let Some(hinv) = h.try_inverse() else {
                return keep_all;
            };
            for (e, band) in fresh.iter_mut().enumerate() {
                *band = select_band(image, &lens, &ideal, &h, &hinv, nb, e, opts);
            }
        }
        let mut lines: [Option<Line>; 4] = [None; 4];
        for (e, line) in lines.iter_mut().enumerate() {
            let band = match (&memory.bands, reuse) {
                (Some(b), true) => Some(&b.edges[e]),
                _ => fresh[e].as_ref(),
            };
            *line = band.and_then(|b| fit_edge(image, b, memory.levels[e], memory.profile.as_deref()));
        }
        memory.lines = lines;
        memory.levels = lines.map(|l| l.map(|l| l.levels));
        memory.reused |= reuse;
        if !reuse {
            // Remembered only when every edge has its band.
            memory.bands = match fresh {
                [Some(e0), Some(e1), Some(e2), Some(e3)] => Some(std::sync::Arc::new(TagBands {
                    corners: ideal,
                    image_size: (image.width, image.height),
                    nb,
                    edges: [e0, e1, e2, e3],
                })),
                _ => None,
            };
        }
        ok_edges = lines.map(|l| l.is_some());
        let mut next = ideal;
        for (i, c) in next.iter_mut().enumerate() {
            // Corner i lies between edge i−1 (ending at it) and edge i (starting at it).
            if let (Some(a), Some(b)) = (lines[(i + 3) % 4], lines[i]) {
                if let Some(p) = a.intersect(&b) {
                    *c = p;
                }
            }
        }
        ideal = next;
    }
    let mut report = RefineReport::default();
    for i in 0..4 {
        let edges_ok = ok_edges[(i + 3) % 4] && ok_edges[i];
        let p = lens.ideal_to_pixel(&ideal[i]);
        let shift = (p - original[i].coords).norm();
        if !(edges_ok && p.x.is_finite() && p.y.is_finite()) {
            report.kept += 1;
            report.failed_fit += 1;
        } else if shift > opts.max_shift_px {
            report.kept += 1;
            report.too_far += 1;
        } else {
            det.corners[i] = Point2::from(p);
            report.refined += 1;
        }
    }
    report
}

/// An edge's fit: with the camera's learned profile when there is one and it fits, else
/// with the parametric model (the fallback, and the model the profile is first learned from).
fn fit_edge(image: &GrayImage, band: &EdgeBand, warm: Option<[f64; 3]>, profile: Option<&EdgeProfile>) -> Option<Line> {
    profile.and_then(|p| fit_band_profile(image, band, warm, p)).or_else(|| fit_band(image, band, warm))
}

/// What a tag's fit in one frame leaves for the same tag's fit in the next frame of the
/// same camera: each edge's levels (the LM's warm start) and the pixels it used; and the
/// camera's learned edge profile its fits use (see [`EdgeMemory::with_profile`]).
#[derive(Debug, Clone, Default)]
pub struct EdgeMemory {
    /// Each edge's fitted levels.
    pub levels: EdgeLevels,
    bands: Option<std::sync::Arc<TagBands>>,
    /// The last pass's fitted lines (on `bands`): the samples of a [`ProfileLearner`].
    lines: [Option<Line>; 4],
    reused: bool,
    profile: Option<std::sync::Arc<EdgeProfile>>,
}

impl PartialEq for EdgeMemory {
    /// Equal levels and the very same remembered pixels.
    fn eq(&self, other: &Self) -> bool {
        let same_bands = match (&self.bands, &other.bands) {
            (Some(a), Some(b)) => std::sync::Arc::ptr_eq(a, b),
            (None, None) => true,
            _ => false,
        };
        let same_profile = match (&self.profile, &other.profile) {
            (Some(a), Some(b)) => std::sync::Arc::ptr_eq(a, b) || a == b,
            (None, None) => true,
            _ => false,
        };
        self.levels == other.levels && self.reused == other.reused && same_bands && same_profile
    }
}

impl EdgeMemory {
    /// This memory with the camera's learned edge profile: the tag's next fits use it
    /// instead of the parametric model (`None`: the parametric model).
    pub fn with_profile(mut self, profile: Option<std::sync::Arc<EdgeProfile>>) -> Self {
        self.profile = profile;
        self
    }

    /// The profile this memory's fits use.
    pub fn profile(&self) -> Option<&std::sync::Arc<EdgeProfile>> {
        self.profile.as_ref()
    }

    /// The largest of the four edges' RMS residuals of the last fit (grey levels), when every
    /// edge was fitted.
    pub fn worst_edge_rms(&self) -> Option<f64> {
        self.lines.iter().try_fold(0.0f64, |m, l| l.map(|l| m.max(l.rms)))
    }

    /// Whether the fit that left this memory reused the pixels selected in an earlier frame.
    pub fn reused_bands(&self) -> bool {
        self.reused
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tagdeflect_core::tags::TagFamily;

    #[test]
    fn options_validate() {
        assert!(RefineOptions::default().validate().is_ok());
        assert!(RefineOptions { passes: 0, ..Default::default() }.validate().is_err());
        assert!(RefineOptions { max_shift_px: f64::NAN, ..Default::default() }.validate().is_err());
    }

    #[test]
    fn flat_image_keeps_corners() {
        let img = GrayImage { width: 100, height: 100, data: vec![128; 10_000], deep: None };
        let mut det = Detection {
            family: TagFamily::Tag36h11,
            id: 0,
            corners: [Point2::new(20.0, 80.0), Point2::new(80.0, 80.0), Point2::new(80.0, 20.0), Point2::new(20.0, 20.0)],
            decision_margin: 50.0,
            hamming: 0,
        };
        let before = det.corners;
        let r = refine_corners(&img, &mut det, None);
        assert_eq!(r, RefineReport { refined: 0, kept: 4, failed_fit: 4, too_far: 0 });
        assert_eq!(det.corners, before);
    }
}
