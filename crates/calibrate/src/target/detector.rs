//! Finding a target in an image: the tag boards' and AprilGrids' tags through the product's
//! AprilTag detector (the AprilGrid's black-shrunk copies, module docs of
//! [`crate::target`]), the checkerboard's corners through [`super::checkerboard`]; what was
//! seen of the board, and why nothing usable was found.

use nalgebra::Point2;

use super::checkerboard::detect_checkerboard;
use super::{aprilgrid_corners, tag_centre, TargetSpec};
use crate::solve::View;
use tagdeflect_core::camera::CameraIntrinsics;
use tagdeflect_core::frame::GrayImage;
use tagdeflect_core::tags::{tag_corners, TagFamily};
use tagdeflect_detect::{refine_corners_with, Detector, DetectorOptions};

/// Detects targets in images; holds the AprilTag detector between images.
pub struct TargetDetector {
    spec: TargetSpec,
    tags: Option<Detector>,
    intrinsics: Option<CameraIntrinsics>,
    refine: bool,
}

impl TargetDetector {
    /// A detector for `spec`.
    pub fn new(spec: TargetSpec) -> Result<Self, tagdeflect_detect::DetectError> {
        let tags = match &spec {
            TargetSpec::TagBoard { family, .. } => Some(Detector::new(DetectorOptions::for_families(&[*family]))?),
            TargetSpec::AprilGrid { .. } => Some(Detector::new(DetectorOptions::for_families(&[TagFamily::Tag36h11]).with_border_bits(2))?),
            TargetSpec::Checkerboard { .. } => None,
        };
        Ok(Self { spec, tags, intrinsics: None, refine: true })
    }

    /// The camera's intrinsics (e.g. a first calibration's) for the tags' sub-pixel
    /// refinement: their edges are then fitted as straight lines in undistorted pixels
    /// instead of in the distorted image, where a lens bends them (see
    /// [`crate::run`]). Checkerboard corners are point features: unchanged.
    pub fn set_intrinsics(&mut self, intrinsics: Option<CameraIntrinsics>) {
        self.intrinsics = intrinsics;
        if let Some(d) = &mut self.tags {
            d.set_intrinsics(self.intrinsics);
        }
    }

    /// Turns the tags' sub-pixel refinement off (`false`) or on (the default): off, the
    /// tags' corners are the AprilTag library's quads (an AprilGrid's with their edges put
    /// back, module docs); checkerboards are unchanged. Only for measuring what the refinement gains
    /// (the real-image test of `tests/it/aprilgrid.rs`); calibration always refines.
    pub fn set_refinement(&mut self, enabled: bool) {
        self.refine = enabled;
    }

    /// The tags of an AprilGrid: the library on the two black-shrunk copies, each tag's
    /// more confident decode, refined on `image` (module docs).
    fn aprilgrid_tags(&mut self, image: &GrayImage) -> Vec<tagdeflect_detect::Detection> {
        let det = self.tags.as_mut().expect("tag detector for an AprilGrid");
        let mut best: Vec<tagdeflect_detect::Detection> = Vec::new();
        for size in [3, 2] {
            let shrunk = shrink_black(image, size);
            for raw in det.detect_raw(&shrunk, None) {
                let mut d = raw.to_detection();
                // The filter moved the black square's edges: put them back before refining.
                let (grow, shift) = if size >= 3 { (1.0, 0.0) } else { (0.5, 0.5) };
                d.corners = grow_quad(&d.corners, grow).map(|c| c + nalgebra::Vector2::new(shift, shift));
                match best.iter_mut().find(|b| b.id == d.id) {
                    Some(b) if b.decision_margin >= d.decision_margin => {}
                    Some(b) => *b = d,
                    None => best.push(d),
                }
            }
        }
        let opts = det.options().subpixel.clone().unwrap_or_default();
        if self.refine {
            for d in &mut best {
                refine_corners_with(image, d, self.intrinsics.as_ref(), &opts);
            }
        }
        best.sort_by_key(|d| d.id);
        best
    }

    /// Finds the target in `image`: board points and their sub-pixel pixels. `Err` says
    /// why nothing usable was found.
    pub fn detect(&mut self, image: &GrayImage, name: &str) -> Result<View, TargetNotFound> {
        self.detect_seen(image, name).map(|(v, _)| v)
    }

    /// [`detect`](Self::detect), plus what the detector saw of the board beyond the points
    /// used (for [`crate::guard::check_board`]).
    pub fn detect_seen(&mut self, image: &GrayImage, name: &str) -> Result<(View, BoardSeen), TargetNotFound> {
        match self.spec.clone() {
            TargetSpec::Checkerboard { cols, rows, square_mm } => detect_checkerboard(image, name, cols, rows, square_mm),
            TargetSpec::TagBoard { cols, rows, size_mm, pitch_mm, first_id, .. } => {
                let det = self.tags.as_mut().expect("tag detector for a tag board");
                let mut object = Vec::new();
                let mut pixels = Vec::new();
                let mut found = 0;
                let mut seen = BoardSeen::default();
                let dets =
                    if self.refine { det.detect(image) } else { det.detect_raw(image, None).iter().map(|r| r.to_detection()).collect() };
                for d in dets {
                    if d.id < first_id || d.id >= first_id + cols * rows {
                        seen.outside_ids.push(d.id);
                        continue;
                    }
                    seen.ids.push(d.id);
                    let k = d.id - first_id;
                    let (c, r) = (k % cols, k / cols);
                    let centre = tag_centre(c, r, pitch_mm);
                    found += 1;
                    for (corner, px) in tag_corners(size_mm).iter().zip(d.corners) {
                        object.push(corner + centre);
                        pixels.push(px);
                    }
                }
                if found < 2 {
                    seen.outside_ids.sort_unstable();
                    return Err(TargetNotFound::TooFewBoardTags {
                        found,
                        outside: seen.outside_ids,
                        first_id,
                        last_id: first_id + cols * rows - 1,
                    });
                }
                seen.outside_ids.sort_unstable();
                seen.ids.sort_unstable();
                Ok((View { name: name.to_string(), object, image: pixels }, seen))
            }
            TargetSpec::AprilGrid { cols, rows, tag_mm, spacing } => {
                let mut object = Vec::new();
                let mut pixels = Vec::new();
                let mut seen = BoardSeen::default();
                for d in self.aprilgrid_tags(image) {
                    if d.id >= cols * rows {
                        seen.outside_ids.push(d.id);
                        continue;
                    }
                    seen.ids.push(d.id);
                    for (corner, px) in aprilgrid_corners(d.id, cols, tag_mm, spacing).iter().zip(d.corners) {
                        object.push(*corner);
                        pixels.push(px);
                    }
                }
                if seen.ids.len() < 2 {
                    return Err(TargetNotFound::TooFewGridTags {
                        found: seen.ids.len(),
                        outside: seen.outside_ids,
                        last_id: cols * rows - 1,
                    });
                }
                Ok((View { name: name.to_string(), object, image: pixels }, seen))
            }
        }
    }

    /// The AprilGrid tags found in `image` (ids of the family, whether on the grid or not),
    /// corners refined, SPEC order; empty for other targets. For tests and diagnostics.
    pub fn aprilgrid_detections(&mut self, image: &GrayImage) -> Vec<tagdeflect_detect::Detection> {
        if matches!(self.spec, TargetSpec::AprilGrid { .. }) {
            self.aprilgrid_tags(image)
        } else {
            Vec::new()
        }
    }
}

/// Why the target was not found in an image (a view's `reason` in the report).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TargetNotFound {
    /// Fewer than two tags of a tag board (`last_id` its last id), with the family's tags
    /// seen outside the board's ids.
    #[error("{found} board tags found (need at least 2){}", outside_board(.outside, *.first_id, *.last_id))]
    TooFewBoardTags {
        /// Board tags found.
        found: usize,
        /// Ids of the family seen outside the board's, sorted.
        outside: Vec<u32>,
        /// The board's first id.
        first_id: u32,
        /// The board's last id.
        last_id: u32,
    },
    /// Fewer than two tags of an AprilGrid, with the tag36h11 tags seen outside its ids.
    #[error("{found} AprilGrid tags found (need at least 2){}", outside_grid(.outside, *.last_id))]
    TooFewGridTags {
        /// Grid tags found.
        found: usize,
        /// Ids seen outside the grid's.
        outside: Vec<u32>,
        /// The grid's last id.
        last_id: u32,
    },
    /// The checkerboard detector refused its parameters.
    #[error("chessboard detector: {0}")]
    ChessboardDetector(calib_targets_chessboard::ChessboardParamsError),
    /// No checkerboard among the X-junctions found.
    #[error("no checkerboard found ({junctions} X-junctions)")]
    NoCheckerboard {
        /// X-junctions found.
        junctions: usize,
    },
    /// Too few checkerboard corners labelled.
    #[error("only {found} checkerboard corners labelled (need {need})")]
    TooFewCorners {
        /// Corners labelled (after trimming to the board).
        found: usize,
        /// Corners needed.
        need: usize,
    },
}

/// `; tags [..] of the family seen, outside the board's ids F..L`, or nothing.
fn outside_board(outside: &[u32], first_id: u32, last_id: u32) -> String {
    if outside.is_empty() {
        return String::new();
    }
    format!("; tags {outside:?} of the family seen, outside the board's ids {first_id}..{last_id}")
}

/// `; tag36h11 tags [..] seen, outside the grid's ids 0..L`, or nothing.
fn outside_grid(outside: &[u32], last_id: u32) -> String {
    if outside.is_empty() {
        return String::new();
    }
    format!("; tag36h11 tags {outside:?} seen, outside the grid's ids 0..{last_id}")
}

/// What the detector saw of the board in one view, beyond the points it used: the evidence
/// that the `--target` given is not the board in the images.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct BoardSeen {
    /// Checkerboard: the dense grid of inner corners the view shows (outer lines with less
    /// than half of a full line's corners trimmed), in the declared orientation (cols, rows).
    pub grid: Option<(u32, u32)>,
    /// Checkerboard: the whole grid the detector labelled (same orientation).
    pub labelled: Option<(u32, u32)>,
    /// Tag board: the board ids found.
    pub ids: Vec<u32>,
    /// Tag board: ids of the family found outside the board's range.
    pub outside_ids: Vec<u32>,
}

/// The quad `corners` with every edge moved `by` pixels outwards (its corners the
/// intersections of the moved edges); unchanged when an edge is degenerate.
fn grow_quad(corners: &[Point2<f64>; 4], by: f64) -> [Point2<f64>; 4] {
    use nalgebra::Vector2;
    let centre = corners.iter().fold(Vector2::zeros(), |a, p| a + p.coords) / 4.0;
    // Edge i from corner i to i+1: a point on it (moved) and its direction.
    let mut lines = [(Vector2::zeros(), Vector2::zeros()); 4];
    for i in 0..4 {
        let (a, b) = (corners[i].coords, corners[(i + 1) % 4].coords);
        let d = b - a;
        let len = d.norm();
        if len.is_nan() || len <= 1e-9 {
            return *corners;
        }
        let d = d / len;
        let mut n = Vector2::new(-d.y, d.x);
        if n.dot(&(a - centre)) < 0.0 {
            n = -n;
        }
        lines[i] = (a + by * n, d);
    }
    let mut out = *corners;
    for (i, c) in out.iter_mut().enumerate() {
        // Corner i lies on edge i−1 and edge i.
        let ((p, u), (q, v)) = (lines[(i + 3) % 4], lines[i]);
        let den = u.x * v.y - u.y * v.x;
        if den.abs() < 1e-9 {
            return *corners;
        }
        let t = ((q - p).x * v.y - (q - p).y * v.x) / den;
        *c = Point2::from(p + t * u);
    }
    out
}

/// `image` with black shrunk by a `size` × `size` maximum filter (`size` 2 or 3; the 2 × 2
/// window reaches right and down), for the AprilGrid's quad search (see the module docs).
fn shrink_black(image: &GrayImage, size: u32) -> GrayImage {
    let (w, h) = (image.width as usize, image.height as usize);
    let (lo, hi) = if size >= 3 { (1usize, 1usize) } else { (0, 1) };
    let px = |x: usize, y: usize| image.data[y * w + x];
    // Rows first, then columns (the maximum is separable).
    let mut rows = vec![0u8; w * h];
    for y in 0..h {
        for x in 0..w {
            let (a, b) = (x.saturating_sub(lo), (x + hi).min(w - 1));
            rows[y * w + x] = (a..=b).map(|i| px(i, y)).max().unwrap_or(0);
        }
    }
    let mut out = vec![0u8; w * h];
    for y in 0..h {
        let (a, b) = (y.saturating_sub(lo), (y + hi).min(h - 1));
        for x in 0..w {
            out[y * w + x] = (a..=b).map(|j| rows[j * w + x]).max().unwrap_or(0);
        }
    }
    GrayImage { width: image.width, height: image.height, data: out, deep: None }
}
