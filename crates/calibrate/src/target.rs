//! Calibration targets: the `--target` syntax, their board geometry and their detection.
//!
//! ```text
//! checkerboard:COLSxROWS:SQUARE_MM                       inner corners, e.g. checkerboard:9x6:25
//! tagboard:FAMILY:COLSxROWS:SIZE_MM:PITCH_MM[:FIRST_ID]  e.g. tagboard:tag36h11:6x4:30:40
//! aprilgrid:COLSxROWS:TAG_M:SPACING_RATIO                Kalibr's, e.g. aprilgrid:6x6:0.088:0.3
//! ```
//!
//! **Checkerboard.** `COLS` × `ROWS` inner corners (OpenCV's `patternSize`), squares of
//! `SQUARE_MM`. Corners are found and labelled by the `calib-targets-chessboard` crate
//! (ChESS X-junction detector + topological grid labelling that tolerates distortion and
//! partial views; MIT/Apache-2.0), then refined here to sub-pixel precision by the gradient
//! orthogonality condition (the method of OpenCV's `cornerSubPix`: at the true saddle every
//! image gradient in the window is orthogonal to the vector from the corner to its pixel),
//! in a window scaled to the local square size. Views that show only part of the board are
//! used: any consistent labelling of a square grid is the board up to a planar isometry,
//! which the view's pose absorbs.
//!
//! **Tag board.** A grid of `COLS` × `ROWS` AprilTags of one family (`tag36h11`,
//! `tag25h9`, `tag16h5`), black-square edge `SIZE_MM` (the same "size" as the config's
//! tags), centre-to-centre pitch `PITCH_MM`, ids row-major from the top-left tag as printed,
//! starting at `FIRST_ID` (default 0). Detected with the product's own detector and its
//! sub-pixel edge refinement (`tagdeflect_detect`), four corners per tag. Board frame: x to the
//! right, y up as printed, origin at the centre of the top-left tag (tag frames as in
//! [`tagdeflect_core::tags::tag_corners`]).
//!
//! **AprilGrid** (Kalibr's target, its `target.yaml` numbers): `COLS` × `ROWS` tag36h11 tags
//! of edge `TAG_M` metres (the black square with its 2-bit border, Kalibr's `tagSize`; `88mm`
//! is taken too), gaps of `SPACING_RATIO` × the tag edge (`tagSpacing`) with a black square
//! in every gap crossing. Ids and corners as Kalibr: tag `id` sits at column `id % COLS`,
//! row `id / COLS` counted from the bottom of the grid as printed (x right, y up, origin at
//! tag 0's bottom-left corner, pitch `TAG · (1 + SPACING)`); its corners are taken
//! bottom-left, bottom-right, top-right, top-left (corner ids `4 id + k` in yac's numbering;
//! Kalibr's grid-point index `2·COLS·(2 row + k / 2) + 2 col + …` names the same points).
//!
//! *How the 2-bit border is read (decision).* An AprilGrid tag is the tag36h11 code inside
//! two black rings instead of one: the same 8×8 black square grown by one cell all round.
//! The tags are found by the same AprilTag library and sub-pixel refinement as a tag board,
//! with two changes. (1) The family table given to the library describes that wider border
//! (black square 10 cells, every data bit one cell further in: `border_bits = 2` of
//! `tagdeflect_detect::DetectorOptions`), so the library's own decoder and code table read
//! the bits where the grid prints them — no decoder of our own, the library's Hamming
//! correction and rotation handling unchanged. (2) The black squares in the gap crossings
//! touch every tag at its four corners, which joins the tags into one black region in which
//! the library's quad finder sees no tag outline; the library therefore searches a copy of
//! the image in which black is shrunk by a 3 × 3 maximum filter (one pixel off every black
//! edge, which parts the touching corners and keeps the 3-pixel bits of a small tag
//! readable), and a copy with a 2 × 2 filter for tags so small that 3 × 3 erases their bits;
//! a tag found in both keeps the more confident decode. The corners are then refined on the
//! original image with the 10-cell square (behind a 2-bit border the edge model's inner side
//! is black all along), whose bands stay `margin` pixels away from the corners where the
//! corner squares touch. Decoding the 6 × 6 bits ourselves or locating tags from the corner
//! squares would have needed a second quad finder; the library's is already tested on every
//! lens and blur the product sees.

use std::fmt::Write as _;

use nalgebra::{Point2, Vector3};

use super::solve::View;
use tagdeflect_core::camera::CameraIntrinsics;
use tagdeflect_core::frame::GrayImage;
use tagdeflect_core::tags::{tag_corners, TagFamily};
use tagdeflect_detect::{refine_corners_with, Detector, DetectorOptions};

/// A calibration target (parsed `--target`).
#[derive(Debug, Clone, PartialEq)]
pub enum TargetSpec {
    /// A checkerboard of `cols` × `rows` inner corners, `square_mm` squares.
    Checkerboard {
        /// Inner corners per row.
        cols: u32,
        /// Inner corners per column.
        rows: u32,
        /// Square edge, mm.
        square_mm: f64,
    },
    /// A grid of AprilTags.
    TagBoard {
        /// Tag family.
        family: TagFamily,
        /// Tags per row.
        cols: u32,
        /// Tag rows.
        rows: u32,
        /// Black-square edge, mm.
        size_mm: f64,
        /// Centre-to-centre pitch, mm.
        pitch_mm: f64,
        /// Id of the top-left tag; ids run row-major.
        first_id: u32,
    },
    /// Kalibr's AprilGrid (tag36h11, 2-bit borders, black squares in the gap crossings).
    AprilGrid {
        /// Tags per row.
        cols: u32,
        /// Tag rows.
        rows: u32,
        /// Tag edge (black square with its 2-bit border), mm.
        tag_mm: f64,
        /// Gap between tags over the tag edge (Kalibr's `tagSpacing`).
        spacing: f64,
    },
}

/// A bad `--target`.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("--target {spec:?}: {message}")]
pub struct TargetError {
    /// The text given.
    pub spec: String,
    /// What is wrong.
    pub message: String,
}

fn parse_dims(s: &str) -> Option<(u32, u32)> {
    let (a, b) = s.split_once(['x', 'X'])?;
    let (a, b) = (a.trim().parse().ok()?, b.trim().parse().ok()?);
    (a > 0 && b > 0).then_some((a, b))
}

fn parse_mm(s: &str) -> Option<f64> {
    let t = s.trim().trim_end_matches("mm");
    let v: f64 = t.parse().ok()?;
    (v.is_finite() && v > 0.0).then_some(v)
}

impl std::str::FromStr for TargetSpec {
    type Err = TargetError;

    fn from_str(spec: &str) -> Result<Self, TargetError> {
        let err = |m: &str| TargetError { spec: spec.to_string(), message: m.to_string() };
        let parts: Vec<&str> = spec.split(':').collect();
        match parts[0] {
            "checkerboard" | "chessboard" => {
                if parts.len() != 3 {
                    return Err(err("expected checkerboard:COLSxROWS:SQUARE_MM (inner corners, e.g. checkerboard:9x6:25)"));
                }
                let (cols, rows) =
                    parse_dims(parts[1]).ok_or_else(|| err("COLSxROWS must be two positive numbers of inner corners, e.g. 9x6"))?;
                if cols < 2 || rows < 2 {
                    return Err(err("a checkerboard needs at least 2x2 inner corners"));
                }
                let square_mm = parse_mm(parts[2]).ok_or_else(|| err("SQUARE_MM must be a positive length in mm"))?;
                Ok(TargetSpec::Checkerboard { cols, rows, square_mm })
            }
            "tagboard" => {
                if !(5..=6).contains(&parts.len()) {
                    return Err(err("expected tagboard:FAMILY:COLSxROWS:SIZE_MM:PITCH_MM[:FIRST_ID], e.g. tagboard:tag36h11:6x4:30:40"));
                }
                let family: TagFamily = parts[1].parse().map_err(|e| err(&format!("{e}")))?;
                let (cols, rows) = parse_dims(parts[2]).ok_or_else(|| err("COLSxROWS must be two positive numbers of tags, e.g. 6x4"))?;
                let size_mm = parse_mm(parts[3]).ok_or_else(|| err("SIZE_MM (black-square edge) must be a positive length in mm"))?;
                let pitch_mm = parse_mm(parts[4]).ok_or_else(|| err("PITCH_MM must be a positive length in mm"))?;
                if pitch_mm <= size_mm {
                    return Err(err("PITCH_MM must be larger than SIZE_MM (tags may not touch)"));
                }
                let first_id: u32 = match parts.get(5) {
                    Some(s) => s.trim().parse().map_err(|_| err("FIRST_ID must be a tag id"))?,
                    None => 0,
                };
                let last = first_id as u64 + cols as u64 * rows as u64;
                if last > family.code_count() as u64 {
                    return Err(err(&format!("ids {first_id}..{} exceed the {} codes of {family}", last - 1, family.code_count())));
                }
                Ok(TargetSpec::TagBoard { family, cols, rows, size_mm, pitch_mm, first_id })
            }
            "aprilgrid" => {
                if parts.len() != 4 {
                    return Err(err("expected aprilgrid:COLSxROWS:TAG_M:SPACING_RATIO (Kalibr's tagCols x tagRows, tagSize in metres, \
                         tagSpacing), e.g. aprilgrid:6x6:0.088:0.3"));
                }
                let (cols, rows) = parse_dims(parts[1]).ok_or_else(|| err("COLSxROWS must be two positive numbers of tags, e.g. 6x6"))?;
                let t = parts[2].trim();
                let tag_mm = if let Some(mm) = t.strip_suffix("mm") {
                    mm.trim().parse::<f64>().ok()
                } else {
                    t.trim_end_matches('m').trim().parse::<f64>().ok().map(|m| 1000.0 * m)
                }
                .filter(|v| v.is_finite() && *v > 0.0)
                .ok_or_else(|| err("TAG_M must be the tag edge in metres (Kalibr's tagSize, e.g. 0.088) or in mm with a unit (88mm)"))?;
                let spacing: f64 = parts[3]
                    .trim()
                    .parse()
                    .ok()
                    .filter(|v: &f64| v.is_finite() && (0.05..=2.0).contains(v))
                    .ok_or_else(|| err("SPACING_RATIO must be the gap over the tag edge (Kalibr's tagSpacing, 0.05 to 2, e.g. 0.3)"))?;
                if cols as u64 * rows as u64 > TagFamily::Tag36h11.code_count() as u64 {
                    return Err(err(&format!("{cols}x{rows} tags exceed the {} codes of tag36h11", TagFamily::Tag36h11.code_count())));
                }
                Ok(TargetSpec::AprilGrid { cols, rows, tag_mm, spacing })
            }
            _ => Err(err(
                "unknown target: expected checkerboard:COLSxROWS:SQUARE_MM, tagboard:FAMILY:COLSxROWS:SIZE_MM:PITCH_MM[:FIRST_ID] \
                 or aprilgrid:COLSxROWS:TAG_M:SPACING_RATIO",
            )),
        }
    }
}

impl TargetSpec {
    /// Every board point (mm, z = 0), for renderers and tests: checkerboard corners row-major
    /// (`x = col · square`, `y = row · square`); tag-board corners tag by tag in SPEC order.
    pub fn board_points(&self) -> Vec<Vector3<f64>> {
        match *self {
            TargetSpec::Checkerboard { cols, rows, square_mm } => {
                (0..rows).flat_map(|r| (0..cols).map(move |c| Vector3::new(c as f64 * square_mm, r as f64 * square_mm, 0.0))).collect()
            }
            TargetSpec::TagBoard { cols, rows, size_mm, pitch_mm, .. } => (0..rows)
                .flat_map(|r| (0..cols).map(move |c| (r, c)))
                .flat_map(|(r, c)| tag_corners(size_mm).map(|p| p + tag_centre(c, r, pitch_mm)))
                .collect(),
            TargetSpec::AprilGrid { cols, rows, tag_mm, spacing } => {
                (0..cols * rows).flat_map(|id| aprilgrid_corners(id, cols, tag_mm, spacing)).collect()
            }
        }
    }

    /// A short text for reports (`checkerboard 9x6, 25 mm squares`).
    pub fn describe(&self) -> String {
        match self {
            TargetSpec::Checkerboard { cols, rows, square_mm } => {
                format!("checkerboard {cols}x{rows} inner corners, {square_mm} mm squares")
            }
            TargetSpec::TagBoard { family, cols, rows, size_mm, pitch_mm, first_id } => {
                format!("{family} board {cols}x{rows}, {size_mm} mm tags at {pitch_mm} mm pitch, ids from {first_id}")
            }
            TargetSpec::AprilGrid { cols, rows, tag_mm, spacing } => {
                format!("AprilGrid {cols}x{rows}, {tag_mm} mm tags, spacing {spacing}")
            }
        }
    }

    /// True for targets made of tags (corners from straight edges, refined per tag).
    pub fn has_tags(&self) -> bool {
        !matches!(self, TargetSpec::Checkerboard { .. })
    }

    /// The centre (mm, board frame) of the tag that `corner`, one of
    /// [`board_points`](Self::board_points), belongs to: the point the corner's diagonal runs
    /// from, along which the refinement's systematic corner bias lies ([`CornerBiasPrior`]).
    /// `None` for checkerboards.
    pub fn tag_centre_of(&self, corner: &Vector3<f64>) -> Option<Vector3<f64>> {
        match *self {
            TargetSpec::Checkerboard { .. } => None,
            // Corners lie half a tag from their centre, and a tag is smaller than the pitch:
            // the nearest centre is the tag's.
            TargetSpec::TagBoard { pitch_mm, .. } => {
                let (c, r) = ((corner.x / pitch_mm).round(), (-corner.y / pitch_mm).round());
                Some(Vector3::new(c * pitch_mm, -r * pitch_mm, 0.0))
            }
            TargetSpec::AprilGrid { tag_mm, spacing, .. } => {
                let pitch = tag_mm * (1.0 + spacing);
                let half = 0.5 * tag_mm;
                let (c, r) = (((corner.x - half) / pitch).round(), ((corner.y - half) / pitch).round());
                Some(Vector3::new(c * pitch + half, r * pitch + half, 0.0))
            }
        }
    }

    /// The black square of the tag that `corner` belongs to: its four corners (mm, board
    /// frame, SPEC order) and how many bits it spans (a tag board's family's
    /// `width_at_border`; 10 for an AprilGrid's 2-bit border). `None` for checkerboards.
    pub fn tag_square_of(&self, corner: &Vector3<f64>) -> Option<([Vector3<f64>; 4], u32)> {
        let centre = self.tag_centre_of(corner)?;
        let (edge_mm, bits) = match *self {
            TargetSpec::Checkerboard { .. } => return None,
            TargetSpec::TagBoard { family, size_mm, .. } => (size_mm, family.width_at_border()),
            TargetSpec::AprilGrid { tag_mm, .. } => (tag_mm, 10),
        };
        Some((tag_corners(edge_mm).map(|c| c + centre), bits))
    }

    /// The prior of the sub-pixel refinement's systematic corner bias on this target
    /// ([`CornerBiasPrior`]); `None` for checkerboards (saddle points have no such bias).
    pub fn corner_bias_prior(&self) -> Option<CornerBiasPrior> {
        match self {
            TargetSpec::Checkerboard { .. } => None,
            TargetSpec::TagBoard { .. } => Some(TAG_BOARD_CORNER_BIAS),
            TargetSpec::AprilGrid { .. } => Some(APRILGRID_CORNER_BIAS),
        }
    }
}

/// Bit size (pixels) at which [`CornerBiasPrior::uniform_px`] holds.
pub const CORNER_BIAS_REFERENCE_BIT_PX: f64 = 4.0;

/// The prior of a tag target's systematic corner bias: every corner of a view set sits
/// `δ_i = a + c · (R / b_i − 1)` pixels out along its tag's diagonal (from the tag's
/// centre through the corner, outwards positive), `b_i` its tag's bit size in pixels and
/// `R` = [`CORNER_BIAS_REFERENCE_BIT_PX`], with `a` and `c` unknown, independent, zero-mean,
/// of 1-σ `uniform_px` and `size_px`. The size term is there because the sub-pixel edge
/// refinement's bias changes as the bits shrink in pixels, and on a tilted board that is
/// what moves fx: the far side's tags shrink more than the near side's, which looks like
/// another perspective. The σ are what the refinement leaves on rendered views with known
/// truth (`tests/it/calibrate.rs::rendered_tag_corner_bias`, docs/calibration.md), whose size
/// and sign on a real camera (blur, print, lens) are not known;
/// [`crate::calibrate_target_views`] adds their effect on the intrinsics to the covariance.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CornerBiasPrior {
    /// 1-σ of the bias at bits of [`CORNER_BIAS_REFERENCE_BIT_PX`], pixels.
    pub uniform_px: f64,
    /// 1-σ of how much more the bias is at bits half that size, pixels.
    pub size_px: f64,
}

/// [`CornerBiasPrior`] of a tag board (1-bit border, data bits just inside), measured
/// 2026-12-03 on `tagboard:tag36h11:6x4:32:44` rendered through the strongly distorted test
/// camera (24 views, bits 2.6–5.3 px): the RMS over optical blurs 0.5, 0.7 and 1.0 px of the
/// fitted `a` (−0.0064, −0.0044, −0.0065 px) and `c` (−0.017, −0.022, −0.056 px).
pub const TAG_BOARD_CORNER_BIAS: CornerBiasPrior = CornerBiasPrior { uniform_px: 0.006, size_px: 0.036 };

/// [`CornerBiasPrior`] of Kalibr's AprilGrid (2-bit border), measured as
/// [`TAG_BOARD_CORNER_BIAS`] on `aprilgrid:6x6:0.03:0.3` (bits 1.9–4.1 px): `a` −0.024, −0.023,
/// −0.010 px, `c` +0.011, +0.003, −0.054 px.
pub const APRILGRID_CORNER_BIAS: CornerBiasPrior = CornerBiasPrior { uniform_px: 0.02, size_px: 0.032 };

/// The four corners of AprilGrid tag `id` (mm, z = 0), Kalibr's order: bottom-left,
/// bottom-right, top-right, top-left, in the grid frame (x right, y up, origin at tag 0's
/// bottom-left corner; row `id / cols` from the bottom).
pub fn aprilgrid_corners(id: u32, cols: u32, tag_mm: f64, spacing: f64) -> [Vector3<f64>; 4] {
    let pitch = tag_mm * (1.0 + spacing);
    let (x, y) = ((id % cols) as f64 * pitch, (id / cols) as f64 * pitch);
    [Vector3::new(x, y, 0.0), Vector3::new(x + tag_mm, y, 0.0), Vector3::new(x + tag_mm, y + tag_mm, 0.0), Vector3::new(x, y + tag_mm, 0.0)]
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
    GrayImage { width: image.width, height: image.height, data: out }
}

/// Centre of tag (`col`, `row`) of a tag board (x right, y up; row 0 at the top).
pub(crate) fn tag_centre(col: u32, row: u32, pitch_mm: f64) -> Vector3<f64> {
    Vector3::new(col as f64 * pitch_mm, -(row as f64) * pitch_mm, 0.0)
}

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
    pub fn detect(&mut self, image: &GrayImage, name: &str) -> Result<View, String> {
        self.detect_seen(image, name).map(|(v, _)| v)
    }

    /// [`detect`](Self::detect), plus what the detector saw of the board beyond the points
    /// used (for [`crate::guard::check_board`]).
    pub fn detect_seen(&mut self, image: &GrayImage, name: &str) -> Result<(View, BoardSeen), String> {
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
                    let mut m = format!("{found} board tags found (need at least 2)");
                    if !seen.outside_ids.is_empty() {
                        seen.outside_ids.sort_unstable();
                        let _ = write!(
                            m,
                            "; tags {:?} of the family seen, outside the board's ids {first_id}..{}",
                            seen.outside_ids,
                            first_id + cols * rows - 1
                        );
                    }
                    return Err(m);
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
                    let mut m = format!("{} AprilGrid tags found (need at least 2)", seen.ids.len());
                    if !seen.outside_ids.is_empty() {
                        let _ = write!(m, "; tag36h11 tags {:?} seen, outside the grid's ids 0..{}", seen.outside_ids, cols * rows - 1);
                    }
                    return Err(m);
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

/// Checkerboard corners: ChESS + grid labelling (`calib-targets-chessboard`), trimmed to
/// the board's size, refined by [`refine_saddle`].
fn detect_checkerboard(image: &GrayImage, name: &str, cols: u32, rows: u32, square_mm: f64) -> Result<(View, BoardSeen), String> {
    use calib_targets_chessboard as ct;
    let view = ct::GrayImageView { width: image.width as usize, height: image.height as usize, data: &image.data };
    let corners = ct::detect_corners(&view, &ct::default_chess_config());
    let detector = ct::ChessboardDetector::new(ct::ChessboardParams::default()).map_err(|e| format!("chessboard detector: {e}"))?;
    let det = detector.detect(&corners).ok_or_else(|| format!("no checkerboard found ({} X-junctions)", corners.len()))?;
    let mut pts: Vec<(i32, i32, Point2<f64>)> =
        det.corners.iter().map(|c| (c.grid.u, c.grid.v, Point2::new(c.position.x as f64, c.position.y as f64))).collect();
    // The labelling may be the board transposed (cols along v): pick the orientation whose
    // extent fits, trimming sparse outer lines when the grid is larger than the board.
    let extent = |p: &[(i32, i32, Point2<f64>)]| {
        let (umin, umax) = p.iter().fold((i32::MAX, i32::MIN), |a, q| (a.0.min(q.0), a.1.max(q.0)));
        let (vmin, vmax) = p.iter().fold((i32::MAX, i32::MIN), |a, q| (a.0.min(q.1), a.1.max(q.1)));
        (umin, umax, vmin, vmax)
    };
    let on = |p: &(i32, i32, Point2<f64>), (is_u, k): (bool, i32)| if is_u { p.0 == k } else { p.1 == k };
    let labelled = {
        let (umin, umax, vmin, vmax) = extent(&pts);
        ((umax - umin + 1) as u32, (vmax - vmin + 1) as u32)
    };
    // The dense grid: outer lines holding less than half of a full line's corners trimmed
    // (stray X-junctions next to the board; a line cut by the image's edge) — what the view
    // shows of the board whatever the target declares.
    let dense = {
        let mut q = pts.clone();
        loop {
            let (umin, umax, vmin, vmax) = extent(&q);
            let (eu, ev) = (umax - umin + 1, vmax - vmin + 1);
            let lines = [((true, umin), ev), ((true, umax), ev), ((false, vmin), eu), ((false, vmax), eu)];
            let (line, frac) = lines
                .iter()
                .map(|&(l, len)| (l, q.iter().filter(|p| on(p, l)).count() as f64 / len as f64))
                .min_by(|a, b| a.1.total_cmp(&b.1))
                .expect("four lines");
            if frac >= 0.5 || eu <= 2 || ev <= 2 {
                break (eu, ev);
            }
            q.retain(|p| !on(p, line));
        }
    };
    let (cu, cv) = {
        let (eu, ev) = dense;
        // Transposed when that fits better.
        if (eu > ev) == (cols >= rows) {
            (cols as i32, rows as i32)
        } else {
            (rows as i32, cols as i32)
        }
    };
    // Outer lines: (is a u line, index). Drop the sparsest until the grid fits the board.
    loop {
        let (umin, umax, vmin, vmax) = extent(&pts);
        if umax - umin < cu && vmax - vmin < cv {
            break;
        }
        let mut lines: Vec<(bool, i32)> = Vec::new();
        if umax - umin >= cu {
            lines.extend([(true, umin), (true, umax)]);
        }
        if vmax - vmin >= cv {
            lines.extend([(false, vmin), (false, vmax)]);
        }
        let drop = lines.into_iter().min_by_key(|&l| pts.iter().filter(|p| on(p, l)).count()).expect("a line to drop");
        pts.retain(|p| !on(p, drop));
    }
    let min_points = ((cols * rows) as usize / 3).max(6);
    if pts.len() < min_points {
        return Err(format!("only {} checkerboard corners labelled (need {min_points})", pts.len()));
    }
    let (umin, _, vmin, _) = extent(&pts);
    let spacing = det.cell_size.map(|c| c as f64).unwrap_or(20.0);
    let half = (0.4 * spacing).round().clamp(2.0, 11.0) as i32;
    let mut object = Vec::with_capacity(pts.len());
    let mut pixels = Vec::with_capacity(pts.len());
    for (u, v, p) in pts {
        object.push(Vector3::new((u - umin) as f64 * square_mm, (v - vmin) as f64 * square_mm, 0.0));
        pixels.push(refine_saddle(image, p, half).unwrap_or(p));
    }
    // In the declared orientation: (cols, rows) when cols ≥ rows matched u, else swapped.
    let orient = |(a, b): (u32, u32)| if cu as u32 == cols { (a, b) } else { (b, a) };
    let seen = BoardSeen { grid: Some(orient((dense.0 as u32, dense.1 as u32))), labelled: Some(orient(labelled)), ..BoardSeen::default() };
    Ok((View { name: name.to_string(), object, image: pixels }, seen))
}

/// Sub-pixel position of a checkerboard saddle near `start` (OpenCV pixels) from the gradient
/// orthogonality condition in a `(2 half + 1)²` window with Gaussian weights, iterated until
/// it moves less than 0.001 px. `None` when the window leaves the image, the structure
/// tensor is singular, or the corner wanders further than `half` from `start`.
fn refine_saddle(image: &GrayImage, start: Point2<f64>, half: i32) -> Option<Point2<f64>> {
    let (w, h) = (image.width as f64, image.height as f64);
    let hf = half as f64;
    let mut q = start;
    for _ in 0..40 {
        if q.x - hf - 1.0 < 0.0 || q.y - hf - 1.0 < 0.0 || q.x + hf + 1.0 > w - 1.0 || q.y + hf + 1.0 > h - 1.0 {
            return None;
        }
        let (mut a, mut b, mut c, mut bb1, mut bb2) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for j in -half..=half {
            for i in -half..=half {
                let (dx, dy) = (i as f64, j as f64);
                let (x, y) = (q.x + dx, q.y + dy);
                let gx = image.sample(x + 1.0, y) - image.sample(x - 1.0, y);
                let gy = image.sample(x, y + 1.0) - image.sample(x, y - 1.0);
                let m = (-(dx * dx + dy * dy) / (hf * hf)).exp();
                let (gxx, gxy, gyy) = (m * gx * gx, m * gx * gy, m * gy * gy);
                a += gxx;
                b += gxy;
                c += gyy;
                bb1 += gxx * dx + gxy * dy;
                bb2 += gxy * dx + gyy * dy;
            }
        }
        let det = a * c - b * b;
        if det.is_nan() || det.abs() <= 1e-9 * (a * c).abs().max(1e-300) {
            return None;
        }
        let step = nalgebra::Vector2::new(c * bb1 - b * bb2, a * bb2 - b * bb1) / det;
        q += step;
        if (q - start).norm() > hf {
            return None;
        }
        if step.norm() < 1e-3 {
            break;
        }
    }
    Some(q)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_targets_and_names_the_fault() {
        assert_eq!("checkerboard:9x6:25".parse::<TargetSpec>().unwrap(), TargetSpec::Checkerboard { cols: 9, rows: 6, square_mm: 25.0 });
        assert_eq!(
            "tagboard:tag36h11:6x4:30mm:40:10".parse::<TargetSpec>().unwrap(),
            TargetSpec::TagBoard { family: TagFamily::Tag36h11, cols: 6, rows: 4, size_mm: 30.0, pitch_mm: 40.0, first_id: 10 }
        );
        let e = "checkerboard:9:25".parse::<TargetSpec>().unwrap_err();
        assert!(e.to_string().contains("COLSxROWS"), "{e}");
        let e = "tagboard:tag25h9:10x10:30:40".parse::<TargetSpec>().unwrap_err();
        assert!(e.to_string().contains("exceed"), "{e}");
        let grid = TargetSpec::AprilGrid { cols: 6, rows: 6, tag_mm: 88.0, spacing: 0.3 };
        assert_eq!("aprilgrid:6x6:88mm:0.3".parse::<TargetSpec>().unwrap(), grid);
        let TargetSpec::AprilGrid { tag_mm, .. } = "aprilgrid:6x6:0.088:0.3".parse::<TargetSpec>().unwrap() else { panic!() };
        assert!((tag_mm - 88.0).abs() < 1e-9);
        assert!("aprilgrid:6x6:0.088".parse::<TargetSpec>().unwrap_err().to_string().contains("SPACING_RATIO"));
        assert!("aprilgrid:6x6:0.088:3".parse::<TargetSpec>().unwrap_err().to_string().contains("tagSpacing"));
        assert!("aprilgrid:30x30:0.088:0.3".parse::<TargetSpec>().unwrap_err().to_string().contains("exceed"));
        // Kalibr's grid: tag 7 of a 6-wide grid is column 1 of row 1; pitch 88 · 1.3 mm.
        let c = aprilgrid_corners(7, 6, 88.0, 0.3);
        assert!((c[0] - Vector3::new(114.4, 114.4, 0.0)).norm() < 1e-9 && (c[2] - Vector3::new(202.4, 202.4, 0.0)).norm() < 1e-9);
        assert_eq!(grid.board_points().len(), 144);
        assert!("tagboard:tag36h11:6x4:40:30".parse::<TargetSpec>().is_err());
    }

    #[test]
    fn every_tag_corner_knows_its_tag_centre() {
        for text in ["tagboard:tag36h11:6x4:32:44", "tagboard:tag25h9:3x2:30:31:5", "aprilgrid:6x6:0.03:0.3", "aprilgrid:4x3:88mm:0.05"] {
            let spec: TargetSpec = text.parse().unwrap();
            // Board points come tag by tag, four corners each.
            for tag in spec.board_points().chunks(4) {
                let mid = tag.iter().fold(Vector3::zeros(), |a, p| a + p) / 4.0;
                for p in tag {
                    assert!((spec.tag_centre_of(p).unwrap() - mid).norm() < 1e-9, "{text}: {p} → {:?}, not {mid}", spec.tag_centre_of(p));
                    // Its black square is the tag's four corners, in the board's order.
                    let (square, bits) = spec.tag_square_of(p).unwrap();
                    assert!(square.iter().zip(tag).all(|(a, b)| (a - b).norm() < 1e-9), "{text}: {square:?} vs {tag:?}");
                    assert_eq!(
                        bits,
                        if text.starts_with("aprilgrid") {
                            10
                        } else if text.contains("25h9") {
                            7
                        } else {
                            8
                        }
                    );
                }
            }
        }
        let board: TargetSpec = "checkerboard:9x6:25".parse().unwrap();
        assert_eq!(board.tag_centre_of(&Vector3::zeros()), None);
        assert!(board.tag_square_of(&Vector3::zeros()).is_none() && board.corner_bias_prior().is_none());
    }

    #[test]
    fn saddle_refinement_finds_a_rendered_corner() {
        // An anti-aliased saddle at (20.3, 17.8) with a lens's blur (σ 0.8 px).
        use tagdeflect_render::{blur, gaussian_kernel};
        let (w, h) = (41u32, 37u32);
        let (x0, y0) = (20.3, 17.8);
        let mut area = vec![0.0f32; (w * h) as usize];
        for y in 0..h {
            for x in 0..w {
                // Exact area fractions of the pixel right of and below the corner.
                let fx = (x as f64 + 0.5 - x0).clamp(0.0, 1.0);
                let fy = (y as f64 + 0.5 - y0).clamp(0.0, 1.0);
                let bright = fx * fy + (1.0 - fx) * (1.0 - fy);
                area[(y * w + x) as usize] = (30.0 + 190.0 * bright) as f32;
            }
        }
        let blurred = blur(&area, w as usize, h as usize, &gaussian_kernel(0.8));
        let img = GrayImage { width: w, height: h, data: blurred.iter().map(|v| v.round() as u8).collect() };
        // From where the ChESS detector leaves a corner (within half a pixel).
        for start in [Point2::new(20.0, 18.0), Point2::new(20.6, 17.4)] {
            let q = refine_saddle(&img, start, 6).unwrap();
            assert!((q.x - x0).abs() < 0.05 && (q.y - y0).abs() < 0.05, "{start} → {q}");
        }
    }
}
