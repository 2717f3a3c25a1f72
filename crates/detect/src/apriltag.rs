//! Safe wrapper around the AprilTag C library (`apriltag-sys`, bundled source).
//!
//! One [`Detector`] holds one or several tag families at once (specimen and background tags
//! may reuse ids: every [`Detection`] carries its family). It owns the C detector and the
//! family tables and destroys them in the only safe order: the detector first (its
//! destructor frees the quick-decode tables that hang off each family), then the families.
//!
//! **Pixel convention.** The C library treats pixel `(i, j)` as the unit square
//! `[i, i+1) × [j, j+1)`, i.e. pixel centres at `+0.5` (see `value_for_pixel` and the
//! `delta = 0.5` offsets in `apriltag.c` / `apriltag_quad_thresh.c`). The product uses
//! OpenCV's convention, centres at integers, so every corner leaves this module as
//! `library − 0.5`. This is the only place where the conversion happens.
//!
//! **Corner order.** The library's `det->p[i]` are the homography images of the tag
//! coordinates `(-1, 1), (1, 1), (1, -1), (-1, -1)`, with tag `y` growing downwards along the
//! printed bit rows: bottom-left, bottom-right, top-right, top-left as printed. That is
//! SPEC's order, so the mapping is the identity (`LIBRARY_TO_SPEC`); the real-data tests
//! check it on upright renderings of the tag images.
//!
//! **Windows.** [`Detector::detect_window`] runs the library on a sub-rectangle of a frame
//! without copying it: the `image_u8_t` handed to C points into the frame at the window's
//! offset with `stride` = frame width. The window's origin is aligned down to the library's
//! 4-pixel threshold tiles so that, inside the window, the binarisation (and so the quads and
//! corners) is the same as on the full frame.
//!
//! **Refinement.** Corners are refined after the library (when the options ask for it)
//! through [`crate::refine`], which works on [`Detection`]s and knows nothing of this
//! module: the imports go one way, from this wrapper to refinement.
#![allow(unsafe_code)] // FFI module: every `unsafe` block carries its SAFETY comment.

use std::ptr::NonNull;
use std::sync::{Mutex, TryLockError};

use apriltag_sys as sys;
use nalgebra::Point2;

use super::family::FamilyTable;
use super::refine::{refine_corners_warm, refine_corners_with, EdgeMemory, RefineOptions, RefineStats};
use super::{Detection, Rect};
use tagdeflect_core::camera::{CameraIntrinsics, Lens};
use tagdeflect_core::frame::GrayImage;
use tagdeflect_core::tags::TagFamily;

// The detector's errors live below this module and `refine` (which reports bad options
// with them); re-exported here, where the detector's users find them.
pub use crate::error::DetectError;

/// Maps SPEC corner index → the library's `det->p` index (identity, see the module docs).
const LIBRARY_TO_SPEC: [usize; 4] = [0, 1, 2, 3];

/// Offset added to a library coordinate to get an OpenCV coordinate.
pub const LIBRARY_TO_OPENCV: f64 = -0.5;

/// Size of the library's thresholding tiles; windows are aligned to it.
const THRESHOLD_TILE: u32 = 4;

/// Options of a [`Detector`].
#[derive(Debug, Clone, PartialEq)]
pub struct DetectorOptions {
    /// Tag families searched at once (at least one, no duplicates).
    pub families: Vec<TagFamily>,
    /// Quad detection on an image decimated by this factor (1 = full resolution, the default).
    /// Larger values are a speed option only: corners are still refined on the full image,
    /// but small tags are lost.
    pub quad_decimate: f32,
    /// Gaussian blur (σ, pixels) before quad detection; 0 (the default) = none. When non-zero
    /// at full resolution the library blurs its input in place, so the frame is copied first.
    pub quad_sigma: f32,
    /// The library's own edge refinement of the quads (on by default).
    pub refine_edges: bool,
    /// Sharpening of the decoded bit samples (library default 0.25).
    pub decode_sharpening: f64,
    /// Worker threads of the library per search (1 = single-threaded: parallel searches
    /// then run on several workers, see [`Detector::with_workers`]).
    pub nthreads: u32,
    /// Bit errors the decoder corrects (library default 2; at most 3).
    pub max_bits_corrected: u8,
    /// Image regions (12 px around each 4 px tile) whose brightest and darkest pixels differ
    /// by less than this (grey levels) are not searched for tag edges (library default 5).
    /// Raising it towards the tags' own contrast skips low-contrast texture — the costliest
    /// part of a search on a textured specimen — at no risk to tags of that contrast.
    pub min_white_black_diff: u8,
    /// Sub-pixel corner refinement against the image (see [`super::refine`]); `None` = off.
    pub subpixel: Option<RefineOptions>,
    /// Width of the tags' black border in bits: 1 (the families as designed, the default)
    /// or 2 (Kalibr's AprilGrid: one more black ring, see `FamilyTable::with_border`). The
    /// refinement's [`RefineOptions::border_bits`] must be the same.
    pub border_bits: u32,
}

impl Default for DetectorOptions {
    fn default() -> Self {
        Self {
            families: vec![TagFamily::Tag36h11, TagFamily::Tag25h9],
            quad_decimate: 1.0,
            quad_sigma: 0.0,
            refine_edges: true,
            decode_sharpening: 0.25,
            nthreads: 1,
            max_bits_corrected: 2,
            min_white_black_diff: 5,
            subpixel: Some(RefineOptions::default()),
            border_bits: 1,
        }
    }
}

impl DetectorOptions {
    /// Default options for the given families.
    pub fn for_families(families: &[TagFamily]) -> Self {
        Self { families: families.to_vec(), ..Self::default() }
    }

    /// These options for tags with a black border of `border_bits` bits (detection and
    /// refinement).
    pub fn with_border_bits(mut self, border_bits: u32) -> Self {
        self.border_bits = border_bits;
        if let Some(r) = &mut self.subpixel {
            r.border_bits = border_bits;
        }
        self
    }

    /// Checks every option; the detector is built only from valid options. A library's
    /// options, not a config section: the error is typed ([`DetectError::BadOption`] names
    /// the option), and `[measure]`'s check turns it into a located config problem.
    pub fn validate(&self) -> Result<(), DetectError> {
        if self.families.is_empty() {
            return Err(DetectError::NoFamily);
        }
        for (i, f) in self.families.iter().enumerate() {
            if self.families[..i].contains(f) {
                return Err(DetectError::DuplicateFamily(*f));
            }
        }
        if !(self.quad_decimate >= 1.0 && self.quad_decimate <= 16.0) {
            return Err(DetectError::BadOption {
                name: "quad_decimate",
                value: self.quad_decimate.to_string(),
                expected: "expected 1.0 (full resolution) to 16.0",
            });
        }
        if !(self.quad_sigma.is_finite() && self.quad_sigma.abs() <= 10.0) {
            return Err(DetectError::BadOption {
                name: "quad_sigma",
                value: self.quad_sigma.to_string(),
                expected: "expected a finite value in [-10, 10] (0 = no blur)",
            });
        }
        if !(self.decode_sharpening.is_finite() && (0.0..=10.0).contains(&self.decode_sharpening)) {
            return Err(DetectError::BadOption {
                name: "decode_sharpening",
                value: self.decode_sharpening.to_string(),
                expected: "expected 0.0 to 10.0",
            });
        }
        if self.nthreads == 0 || self.nthreads > 256 {
            return Err(DetectError::BadOption { name: "nthreads", value: self.nthreads.to_string(), expected: "expected 1 to 256" });
        }
        if self.max_bits_corrected > 3 {
            return Err(DetectError::BadOption {
                name: "max_bits_corrected",
                value: self.max_bits_corrected.to_string(),
                expected: "expected 0 to 3",
            });
        }
        if !(1..=2).contains(&self.border_bits) {
            return Err(DetectError::BadOption {
                name: "border_bits",
                value: self.border_bits.to_string(),
                expected: "expected 1 (classic tags) or 2 (AprilGrid tags)",
            });
        }
        if let Some(r) = &self.subpixel {
            r.validate()?;
            if r.border_bits != self.border_bits {
                return Err(DetectError::BadOption {
                    name: "subpixel.border_bits",
                    value: r.border_bits.to_string(),
                    expected: "expected the detector's own border_bits (see DetectorOptions::with_border_bits)",
                });
            }
        }
        Ok(())
    }
}

/// A detection exactly as the library reports it: library pixel convention (centres at
/// `+0.5`) and `det->p` corner order. For diagnostics and tests; the product uses
/// [`Detection`].
#[derive(Debug, Clone, PartialEq)]
pub struct RawDetection {
    /// Family of the tag.
    pub family: TagFamily,
    /// Tag id.
    pub id: u32,
    /// Bits corrected.
    pub hamming: u8,
    /// Decision margin.
    pub decision_margin: f32,
    /// Centre (library convention).
    pub centre: [f64; 2],
    /// `det->p` (library convention and order).
    pub p: [[f64; 2]; 4],
}

impl RawDetection {
    /// Converts to the product's convention: OpenCV pixels (`− 0.5`), SPEC corner order.
    pub fn to_detection(&self) -> Detection {
        let corners = LIBRARY_TO_SPEC.map(|i| Point2::new(self.p[i][0] + LIBRARY_TO_OPENCV, self.p[i][1] + LIBRARY_TO_OPENCV));
        Detection { family: self.family, id: self.id, corners, decision_margin: self.decision_margin, hamming: self.hamming }
    }
}

/// What may change from one search to the next on the same [`Detector`] (the other
/// options are fixed when it is built): passed with each call, so searches of different
/// purposes (a full frame, windows, unrefined sweep tiles) share the detector without
/// switching its options.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SearchOptions {
    /// Quad decimation of this search (at least 1).
    pub quad_decimate: f32,
    /// The contrast filter of this search (see [`DetectorOptions::min_white_black_diff`]).
    pub min_white_black_diff: u8,
    /// Refine the corners (with the detector's [`DetectorOptions::subpixel`] options).
    pub refine: bool,
}

impl SearchOptions {
    /// The search the detector's own options describe.
    pub fn of(options: &DetectorOptions) -> Self {
        Self {
            quad_decimate: options.quad_decimate,
            min_white_black_diff: options.min_white_black_diff,
            refine: options.subpixel.is_some(),
        }
    }
}

/// One C detector of a [`Detector`]: its own worker state and scratch, the families
/// (and their decoding tables) shared with the detector's other workers.
struct Worker {
    td: NonNull<sys::apriltag_detector_t>,
    /// Copy of the input when the library would blur it in place (`quad_sigma != 0`).
    scratch: Vec<u8>,
}

// SAFETY: a C detector is a plain heap object owned by this value alone; the library keeps
// no thread-local state, and the worker pool it spawns is joined inside each
// `apriltag_detector_detect` call.
unsafe impl Send for Worker {}

/// An AprilTag detector for one or several families.
///
/// It holds the families' tables once (tag36h11's decoding table is 37 MB) and one or
/// more C detectors ("workers", [`Detector::with_workers`]) that share them: the library
/// builds a family's decoding table only when the family has none yet, and only reads it
/// while detecting. [`Detector::search`] takes `&self`, so several threads search at once,
/// each on a free worker; the `&mut self` methods use the detector's own options.
pub struct Detector {
    /// The C detectors; destroyed in `Drop` before `families`.
    workers: Vec<Mutex<Worker>>,
    /// Families registered with every worker; dropped after them.
    families: Vec<FamilyTable>,
    options: DetectorOptions,
    intrinsics: Option<CameraIntrinsics>,
    stats: RefineStats,
}

// SAFETY: see `Worker`; `Detector` is also `Sync`: each C detector is used under its
// mutex only, and the family tables (with their decoding tables) are written only while
// the detector is built (`apriltag_detector_add_family_bits`) and read afterwards.
unsafe impl Send for Detector {}
// SAFETY: as above.
unsafe impl Sync for Detector {}

impl std::fmt::Debug for Detector {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Detector")
            .field("options", &self.options)
            .field("workers", &self.workers.len())
            .field("intrinsics", &self.intrinsics)
            .finish()
    }
}

impl Detector {
    /// Creates a detector with one worker; the options are validated first.
    pub fn new(options: DetectorOptions) -> Result<Self, DetectError> {
        Self::with_workers(options, 1)
    }

    /// Creates a detector whose [`search`](Self::search) runs up to `workers` searches at
    /// once (each on the library's `nthreads` threads; the families' tables are shared).
    pub fn with_workers(options: DetectorOptions, workers: usize) -> Result<Self, DetectError> {
        options.validate()?;
        let mut families = Vec::with_capacity(options.families.len());
        for &f in &options.families {
            families.push(FamilyTable::with_border(f, options.border_bits).ok_or(DetectError::Create("a tag family table"))?);
        }
        let mut det = Self { workers: Vec::new(), families, options, intrinsics: None, stats: RefineStats::default() };
        for _ in 0..workers.max(1) {
            // SAFETY: no preconditions; returns a heap object or null.
            let td = NonNull::new(unsafe { sys::apriltag_detector_create() }).ok_or(DetectError::Create("the detector"))?;
            let worker = Worker { td, scratch: Vec::new() };
            for fam in &det.families {
                // SAFETY: both pointers are valid; the family outlives the worker (Drop
                // order). The first worker builds the family's decoding table, the others
                // find it built and share it.
                unsafe { sys::apriltag_detector_add_family_bits(td.as_ptr(), fam.as_ptr(), det.options.max_bits_corrected as i32) };
            }
            det.workers.push(Mutex::new(worker));
        }
        Ok(det)
    }

    /// Writes the options of one search into a worker's C detector.
    fn apply_options(td: NonNull<sys::apriltag_detector_t>, options: &DetectorOptions, search: &SearchOptions) {
        // SAFETY: `td` is valid and held under its worker's mutex; plain field writes.
        unsafe {
            let td = &mut *td.as_ptr();
            td.quad_decimate = search.quad_decimate.max(1.0);
            td.quad_sigma = options.quad_sigma;
            td.refine_edges = options.refine_edges;
            td.decode_sharpening = options.decode_sharpening;
            td.nthreads = options.nthreads as i32;
            td.debug = false;
            td.qtp.min_white_black_diff = search.min_white_black_diff as i32;
        }
    }

    /// The options in force.
    pub fn options(&self) -> &DetectorOptions {
        &self.options
    }

    /// Number of C detectors (searches that can run at once).
    pub fn workers(&self) -> usize {
        self.workers.len()
    }

    /// Changes the options used by the `&mut self` methods; the families cannot change
    /// (they are fixed when the detector is built).
    pub fn set_options(&mut self, options: DetectorOptions) -> Result<(), DetectError> {
        options.validate()?;
        if options.families != self.options.families
            || options.max_bits_corrected != self.options.max_bits_corrected
            || options.border_bits != self.options.border_bits
        {
            return Err(DetectError::BadOption {
                name: "families",
                value: format!("{:?}", options.families),
                expected: "the detector's own families, max_bits_corrected and border_bits (build a new detector for others)",
            });
        }
        self.options = options;
        Ok(())
    }

    /// The camera's intrinsics, used by sub-pixel refinement to straighten distorted edges
    /// (for the `&mut self` methods; [`search`](Self::search) takes them per call).
    pub fn set_intrinsics(&mut self, intrinsics: Option<CameraIntrinsics>) {
        self.intrinsics = intrinsics;
    }

    /// Refinement counts accumulated since creation (or the last [`take_refine_stats`](Self::take_refine_stats)).
    pub fn refine_stats(&self) -> RefineStats {
        self.stats
    }

    /// Returns the refinement counts and resets them.
    pub fn take_refine_stats(&mut self) -> RefineStats {
        std::mem::take(&mut self.stats)
    }

    /// Detects tags in the whole image: OpenCV pixels, SPEC corner order, refined when enabled.
    pub fn detect(&mut self, image: &GrayImage) -> Vec<Detection> {
        let full = Rect { x: 0, y: 0, width: image.width, height: image.height };
        self.detect_window(image, full)
    }

    /// Detects tags inside `rect` of `image` (clamped to the image; its origin is aligned down
    /// to 4 pixels), without copying the frame. Corners are in full-frame OpenCV pixels and
    /// identical in quality to [`detect`](Self::detect)'s (same library run, same refinement
    /// on the full image). An empty window gives no detections.
    pub fn detect_window(&mut self, image: &GrayImage, rect: Rect) -> Vec<Detection> {
        let raws = self.raw(image, Some(rect), &SearchOptions { refine: false, ..SearchOptions::of(&self.options) });
        let mut out: Vec<Detection> = raws.iter().map(RawDetection::to_detection).collect();
        if let Some(opts) = self.options.subpixel.clone() {
            for d in &mut out {
                let r = refine_corners_with(image, d, self.intrinsics.as_ref(), &opts);
                self.stats.add(&r);
            }
        }
        out
    }

    /// Detects tags in `rect` of `image` (the whole image for `None`) with the options of
    /// this search, on a free worker (thread-safe); corners refined when `search.refine`
    /// and the detector has refinement options, straightened through `lens` (the camera's,
    /// e.g. with its [`IdealPixelMap`](tagdeflect_core::camera::IdealPixelMap); `Lens::new(None)`: none).
    pub fn search(&self, image: &GrayImage, rect: Option<Rect>, search: &SearchOptions, lens: Lens<'_>) -> Vec<Detection> {
        let raws = self.raw(image, rect, search);
        let mut out: Vec<Detection> = raws.iter().map(RawDetection::to_detection).collect();
        if let (true, Some(opts)) = (search.refine, &self.options.subpixel) {
            for d in &mut out {
                refine_corners_warm(image, d, lens, opts, &mut EdgeMemory::default());
            }
        }
        out
    }

    /// Runs the library alone on `image` or on a window of it and returns its detections in
    /// the library's convention and order (no conversion, no sub-pixel refinement), with
    /// window coordinates already offset to the full frame.
    pub fn detect_raw(&mut self, image: &GrayImage, rect: Option<Rect>) -> Vec<RawDetection> {
        self.raw(image, rect, &SearchOptions::of(&self.options))
    }

    /// A free worker, or (all busy) the one of this thread's index.
    fn worker(&self) -> std::sync::MutexGuard<'_, Worker> {
        for w in &self.workers {
            match w.try_lock() {
                Ok(g) => return g,
                Err(TryLockError::Poisoned(p)) => return p.into_inner(),
                Err(TryLockError::WouldBlock) => {}
            }
        }
        let i = rayon::current_thread_index().unwrap_or(0) % self.workers.len();
        self.workers[i].lock().unwrap_or_else(|p| p.into_inner())
    }

    fn raw(&self, image: &GrayImage, rect: Option<Rect>, search: &SearchOptions) -> Vec<RawDetection> {
        let full = Rect { x: 0, y: 0, width: image.width, height: image.height };
        let Some(win) = rect.unwrap_or(full).aligned(THRESHOLD_TILE).clamp_to(image.width, image.height) else {
            return Vec::new();
        };
        let expected_len = image.width as usize * image.height as usize;
        // The library asserts on sizes ≥ 32768 and needs at least a few pixels to work with.
        if image.data.len() < expected_len || win.width < 8 || win.height < 8 || win.width >= 32768 || win.height >= 32768 {
            return Vec::new();
        }
        let mut worker = self.worker();
        let worker = &mut *worker;
        Self::apply_options(worker.td, &self.options, search);
        let stride = image.width as usize;
        let offset = win.y as usize * stride + win.x as usize;
        let in_place_blur = self.options.quad_sigma != 0.0 && search.quad_decimate <= 1.0;
        let (buf, stride_used): (*mut u8, usize) = if in_place_blur {
            // The library would blur its input in place: give it a private copy of the window.
            let (w, h) = (win.width as usize, win.height as usize);
            worker.scratch.clear();
            worker.scratch.reserve(w * h);
            for row in 0..h {
                let start = offset + row * stride;
                worker.scratch.extend_from_slice(&image.data[start..start + w]);
            }
            (worker.scratch.as_mut_ptr(), w)
        } else {
            // SAFETY (of the later read-only use): `offset` is inside `data`, and every row of
            // the window lies inside `data` because the window is clamped to the image. The
            // library only reads its input when it does not blur it (checked above).
            (image.data[offset..].as_ptr() as *mut u8, stride)
        };
        let mut im = sys::image_u8_t { width: win.width as i32, height: win.height as i32, stride: stride_used as i32, buf };
        // SAFETY: `td` is valid and ours under the mutex; `im` describes `height` rows of
        // `width` bytes at `stride` inside a live buffer that outlives the call; the result
        // is an owned zarray.
        let zarr = unsafe { sys::apriltag_detector_detect(worker.td.as_ptr(), &mut im) };
        let Some(zarr) = NonNull::new(zarr) else {
            return Vec::new();
        };
        let mut out = Vec::new();
        // SAFETY: `zarr` is a zarray of `apriltag_detection_t*` returned by the library; we
        // read `size` elements of `el_sz` bytes and free the array and detections once.
        unsafe {
            let z = zarr.as_ref();
            let n = z.size.max(0) as usize;
            if z.el_sz == std::mem::size_of::<*mut sys::apriltag_detection_t>() && !z.data.is_null() {
                let dets = z.data as *const *mut sys::apriltag_detection_t;
                for i in 0..n {
                    let dp = *dets.add(i);
                    if dp.is_null() {
                        continue;
                    }
                    let d = &*dp;
                    let Some(fam) = self.families.iter().find(|f| f.as_ptr() == d.family) else {
                        continue;
                    };
                    if d.id < 0 || d.hamming < 0 {
                        continue;
                    }
                    let (ox, oy) = (win.x as f64, win.y as f64);
                    out.push(RawDetection {
                        family: fam.family(),
                        id: d.id as u32,
                        hamming: d.hamming.min(255) as u8,
                        decision_margin: d.decision_margin,
                        centre: [d.c[0] + ox, d.c[1] + oy],
                        p: d.p.map(|q| [q[0] + ox, q[1] + oy]),
                    });
                }
            }
            sys::apriltag_detections_destroy(zarr.as_ptr());
        }
        out.sort_by(|a, b| (a.family.name(), a.id).cmp(&(b.family.name(), b.id)));
        out
    }
}

impl Drop for Worker {
    fn drop(&mut self) {
        // SAFETY: each C detector is destroyed exactly once, BEFORE the families it
        // references (`Detector` drops its workers first). The first one destroyed frees
        // the shared decoding tables and clears the families' pointers to them, so the
        // others find nothing left to free.
        unsafe { sys::apriltag_detector_destroy(self.td.as_ptr()) };
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn options_are_validated() {
        assert!(matches!(Detector::new(DetectorOptions { families: vec![], ..Default::default() }), Err(DetectError::NoFamily)));
        let dup = DetectorOptions { families: vec![TagFamily::Tag25h9, TagFamily::Tag25h9], ..Default::default() };
        assert!(matches!(Detector::new(dup), Err(DetectError::DuplicateFamily(TagFamily::Tag25h9))));
        let bad = DetectorOptions { quad_decimate: 0.5, ..Default::default() };
        let e = Detector::new(bad).unwrap_err().to_string();
        assert!(e.contains("quad_decimate"), "{e}");
        let bad = DetectorOptions { nthreads: 0, ..Default::default() };
        assert!(Detector::new(bad).is_err());
    }

    #[test]
    fn create_and_drop_many_detectors() {
        // Exercises the destruction order (detector before families) repeatedly.
        for _ in 0..20 {
            let mut d = Detector::new(DetectorOptions::for_families(&TagFamily::ALL)).unwrap();
            let img = GrayImage::new(64, 48);
            assert!(d.detect(&img).is_empty());
        }
    }

    #[test]
    fn degenerate_inputs_give_no_detections() {
        let mut d = Detector::new(DetectorOptions::default()).unwrap();
        let img = GrayImage::new(0, 0);
        assert!(d.detect(&img).is_empty());
        let img = GrayImage::new(5, 5);
        assert!(d.detect(&img).is_empty());
        let img = GrayImage::new(100, 100);
        assert!(d.detect_window(&img, Rect { x: 200, y: 0, width: 50, height: 50 }).is_empty());
        let broken = GrayImage { width: 100, height: 100, data: vec![0; 10], deep: None };
        assert!(d.detect(&broken).is_empty());
    }

    #[test]
    fn detector_is_send() {
        fn is_send<T: Send>() {}
        is_send::<Detector>();
    }
}
