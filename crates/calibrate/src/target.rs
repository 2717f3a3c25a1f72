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

mod checkerboard;
mod detector;
mod parse;

use nalgebra::Vector3;

use tagdeflect_core::tags::{tag_corners, TagFamily};

pub use detector::{BoardSeen, TargetDetector, TargetNotFound};
pub use parse::TargetError;

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
/// truth (`tests/it/calibrate_rendered.rs::rendered_tag_corner_bias`, docs/calibration.md), whose size
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

/// Centre of tag (`col`, `row`) of a tag board (x right, y up; row 0 at the top).
pub(crate) fn tag_centre(col: u32, row: u32, pitch_mm: f64) -> Vector3<f64> {
    Vector3::new(col as f64 * pitch_mm, -(row as f64) * pitch_mm, 0.0)
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
}
