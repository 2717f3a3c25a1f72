//! Tag families and tag geometry: the families' facts (one table), corner order, tag-frame
//! corners, bitmaps from a family's layout, the cell homography.
//!
//! Corner order everywhere (SPEC): bottom-left, bottom-right, top-right, top-left of the
//! black square as the tag is printed upright. The tag frame has its origin at the centre
//! of the black square, x to the right, y up (as printed) and z out of the printed face
//! towards the viewer, so the corners are `(∓s/2, ∓s/2, 0)` in that order.

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};
use std::fmt;
use std::str::FromStr;

/// A supported AprilTag family.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(try_from = "String", into = "String")]
pub enum TagFamily {
    /// 36-bit, minimum Hamming distance 11 (587 codes).
    Tag36h11,
    /// 25-bit, minimum Hamming distance 9 (35 codes).
    Tag25h9,
    /// 16-bit, minimum Hamming distance 5 (30 codes).
    Tag16h5,
}

/// What the product needs to know of a family, one row per family (the AprilTag library's
/// own tables hold the codes and bit layout: see `detect::family`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FamilyFacts {
    /// The family's name as the AprilTag library spells it.
    pub name: &'static str,
    /// Number of codes (valid ids are `0..code_count`).
    pub code_count: u32,
    /// Width of the black square in cells (the library's `width_at_border`).
    pub width_at_border: u32,
    /// Width of the printed tag in cells, white ring included (`total_width`).
    pub total_width: u32,
}

/// The facts of every family, in the order of [`TagFamily::ALL`].
const FAMILY_FACTS: [FamilyFacts; 3] = [
    FamilyFacts { name: "tag36h11", code_count: 587, width_at_border: 8, total_width: 10 },
    FamilyFacts { name: "tag25h9", code_count: 35, width_at_border: 7, total_width: 9 },
    FamilyFacts { name: "tag16h5", code_count: 30, width_at_border: 6, total_width: 8 },
];

impl TagFamily {
    /// All supported families.
    pub const ALL: [TagFamily; 3] = [TagFamily::Tag36h11, TagFamily::Tag25h9, TagFamily::Tag16h5];

    /// Position of the family in [`TagFamily::ALL`] (an index into per-family tables).
    pub fn index(self) -> usize {
        self as usize
    }

    /// The family's row of facts.
    pub fn facts(self) -> &'static FamilyFacts {
        &FAMILY_FACTS[self.index()]
    }

    /// The family's name as the AprilTag library spells it.
    pub fn name(self) -> &'static str {
        self.facts().name
    }

    /// Number of codes (valid ids are `0..code_count()`).
    pub fn code_count(self) -> u32 {
        self.facts().code_count
    }

    /// Width of the black square in bits (cells).
    pub fn width_at_border(self) -> u32 {
        self.facts().width_at_border
    }
}

impl fmt::Display for TagFamily {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// A family name that is not one of the supported families.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown tag family \"{0}\": expected one of tag36h11, tag25h9, tag16h5")]
pub struct UnknownTagFamily(pub String);

impl FromStr for TagFamily {
    type Err = UnknownTagFamily;
    fn from_str(s: &str) -> Result<Self, UnknownTagFamily> {
        TagFamily::ALL.into_iter().find(|f| f.name() == s).ok_or_else(|| UnknownTagFamily(s.to_string()))
    }
}

impl TryFrom<String> for TagFamily {
    type Error = UnknownTagFamily;
    fn try_from(s: String) -> Result<Self, UnknownTagFamily> {
        s.parse()
    }
}

impl From<TagFamily> for String {
    fn from(f: TagFamily) -> String {
        f.name().to_string()
    }
}

/// The four corners of a black square of edge `size` in the tag frame, in SPEC order.
pub fn tag_corners(size: f64) -> [Vector3<f64>; 4] {
    let h = size / 2.0;
    [Vector3::new(-h, -h, 0.0), Vector3::new(h, -h, 0.0), Vector3::new(h, h, 0.0), Vector3::new(-h, h, 0.0)]
}

/// Error of a tag-bitmap request.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum TagError {
    /// The id is not a code of the family.
    #[error("tag id {id} does not exist in family {family} (valid ids are 0..{count})")]
    UnknownId {
        /// The family asked for.
        family: TagFamily,
        /// The id asked for.
        id: u32,
        /// Number of codes of the family.
        count: u32,
    },
}

/// A tag as printed, one entry per cell, taken from the AprilTag library's own family table
/// (the same layout as its `apriltag_to_image`).
///
/// Row 0 is the top row as printed upright, column 0 the left column. The printed tag is
/// `total_width` cells wide: a white ring of one cell, then the black square of
/// `width_at_border` cells (its border and the data bits). The black square's edge is the
/// `size_mm` of the config, so one cell is `size_mm / width_at_border`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TagBitmap {
    /// The family.
    pub family: TagFamily,
    /// The tag id.
    pub id: u32,
    /// Width of the printed tag in cells (white ring included).
    pub total_width: u32,
    /// Width of the black square in cells.
    pub width_at_border: u32,
    /// `total_width²` cells, row-major from the top-left; `true` = white.
    pub white: Vec<bool>,
}

impl TagBitmap {
    /// True when the cell at `col`, `row` (from the top-left, as printed) is white.
    /// Cells outside the printed tag are reported white (paper).
    pub fn is_white(&self, col: u32, row: u32) -> bool {
        if col >= self.total_width || row >= self.total_width {
            return true;
        }
        self.white[(row * self.total_width + col) as usize]
    }

    /// Edge of one cell, mm, for a black square of edge `size_mm`.
    pub fn cell_mm(&self, size_mm: f64) -> f64 {
        size_mm / self.width_at_border as f64
    }

    /// Edge of the whole printed tag (white ring included), mm.
    pub fn printed_mm(&self, size_mm: f64) -> f64 {
        self.cell_mm(size_mm) * self.total_width as f64
    }

    /// The cell under a point of the tag frame (x right, y up, mm, origin at the centre of
    /// the black square of edge `size_mm`): `(col, row)` from the top-left, `None` outside
    /// the printed tag.
    pub fn cell_at(&self, x_mm: f64, y_mm: f64, size_mm: f64) -> Option<(u32, u32)> {
        let c = self.cell_mm(size_mm);
        let half = 0.5 * c * self.total_width as f64;
        let col = (x_mm + half) / c;
        let row = (half - y_mm) / c;
        let n = self.total_width as f64;
        // Truncation is the floor here: both are checked non-negative first.
        if col >= 0.0 && row >= 0.0 && col < n && row < n {
            Some((col as u32, row as u32))
        } else {
            None
        }
    }
}

/// The layout and codes of a family, copied out of the AprilTag library's table (plain
/// data; `detect::family::family_layout` reads it).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FamilyLayout {
    /// The family.
    pub family: TagFamily,
    /// One code per id; bit `nbits - 1 - i` is data bit `i`.
    pub codes: Vec<u64>,
    /// Data-bit x positions (cells, from the left edge of the black square).
    pub bit_x: Vec<u32>,
    /// Data-bit y positions (cells, from the top edge of the black square).
    pub bit_y: Vec<u32>,
    /// Width of the black square in cells.
    pub width_at_border: u32,
    /// Width of the whole printed tag in cells (white ring included).
    pub total_width: u32,
    /// True for families whose border is white inside black (not the classic families).
    pub reversed_border: bool,
    /// Minimum Hamming distance between codes.
    pub min_hamming: u32,
}

impl TagBitmap {
    /// The bitmap of tag `id` of the family whose table is `layout`.
    pub fn from_layout(layout: &FamilyLayout, id: u32) -> Result<TagBitmap, TagError> {
        let family = layout.family;
        let code = *layout.codes.get(id as usize).ok_or(TagError::UnknownId { family, id, count: layout.codes.len() as u32 })?;
        let tw = layout.total_width;
        let wab = layout.width_at_border;
        let mut white = vec![false; (tw * tw) as usize];
        // The white ring (classic layout: just outside the black square; reversed: the border itself).
        let ring = wab + if layout.reversed_border { 0 } else { 2 };
        let ring_start = (tw - ring.min(tw)) / 2;
        let ring_end = ring_start + ring - 1;
        for r in 0..tw {
            for c in 0..tw {
                let on_ring = (r == ring_start || r == ring_end || c == ring_start || c == ring_end)
                    && (ring_start..=ring_end).contains(&r)
                    && (ring_start..=ring_end).contains(&c);
                if on_ring {
                    white[(r * tw + c) as usize] = true;
                }
            }
        }
        let border_start = (tw - wab) / 2;
        let nbits = layout.bit_x.len() as u32;
        for i in 0..nbits {
            if code & (1u64 << (nbits - i - 1)) != 0 {
                let (x, y) = (layout.bit_x[i as usize] + border_start, layout.bit_y[i as usize] + border_start);
                if x < tw && y < tw {
                    white[(y * tw + x) as usize] = true;
                }
            }
        }
        Ok(TagBitmap { family, id, total_width: tw, width_at_border: wab, white })
    }
}

/// Homography from tag cell coordinates (x right, y down as printed, origin at the black
/// square's top-left, `width_at_border` cells across) to image coordinates, from the black
/// square's corners there in SPEC order.
pub fn cell_homography(corners: &[nalgebra::Vector2<f64>; 4], width_at_border: f64) -> Option<nalgebra::Matrix3<f64>> {
    use nalgebra::Vector2;
    let nb = width_at_border;
    let tag = [Vector2::new(0.0, nb), Vector2::new(nb, nb), Vector2::new(nb, 0.0), Vector2::new(0.0, 0.0)];
    crate::camera::homography(&tag, corners)
}
