//! The AprilTag library's family tables (codes and bit layout) behind a safe owner.
//!
//! [`FamilyTable`] owns one `apriltag_family_t` created by the library's own constructor
//! (`tag36h11_create()` etc.) and destroys it on drop. The detector passes
//! [`FamilyTable::as_ptr`] to `apriltag_detector_add_family`; it must destroy the detector
//! *before* dropping the table (the detector keeps a pointer to it and writes into its
//! `impl` field). Everything else (tag bitmaps for rendering) reads the table through the
//! safe accessors or a [`FamilyLayout`] copy.
#![allow(unsafe_code)] // FFI module: every `unsafe` block carries its SAFETY comment.

use apriltag_sys as sys;

use crate::tags::TagFamily;

/// The layout and codes of a family, copied out of the library's table (plain data).
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

/// Owner of one family table created by the AprilTag library.
#[derive(Debug)]
pub struct FamilyTable {
    family: TagFamily,
    ptr: *mut sys::apriltag_family_t,
}

// SAFETY: the table is heap memory owned by this value alone; nothing in it is tied to the
// creating thread, so it may move between threads. It is not `Sync`: the detector writes
// into the table's `impl` field when the family is added.
unsafe impl Send for FamilyTable {}

impl FamilyTable {
    /// Creates the library's table for `family`. `None` only if the library's allocation failed.
    pub fn new(family: TagFamily) -> Option<Self> {
        // SAFETY: the constructors take no input and return a freshly allocated table (or null).
        let ptr = unsafe {
            match family {
                TagFamily::Tag36h11 => sys::tag36h11_create(),
                TagFamily::Tag25h9 => sys::tag25h9_create(),
                TagFamily::Tag16h5 => sys::tag16h5_create(),
            }
        };
        if ptr.is_null() {
            None
        } else {
            Some(Self { family, ptr })
        }
    }

    /// The family this table describes.
    pub fn family(&self) -> TagFamily {
        self.family
    }

    /// The raw table for `apriltag_detector_add_family`. The pointer stays valid while `self`
    /// lives; a detector using it must be destroyed before `self` is dropped.
    pub fn as_ptr(&self) -> *mut sys::apriltag_family_t {
        self.ptr
    }

    fn raw(&self) -> &sys::apriltag_family_t {
        // SAFETY: `ptr` is non-null and points to a table owned by `self` until drop.
        unsafe { &*self.ptr }
    }

    /// Number of codes (valid ids are `0..ncodes()`).
    pub fn ncodes(&self) -> u32 {
        self.raw().ncodes
    }

    /// Number of data bits.
    pub fn nbits(&self) -> u32 {
        self.raw().nbits
    }

    /// Code of tag `id`, `None` when the id is out of range.
    pub fn code(&self, id: u32) -> Option<u64> {
        let raw = self.raw();
        if id >= raw.ncodes || raw.codes.is_null() {
            return None;
        }
        // SAFETY: `codes` holds `ncodes` entries and `id < ncodes`.
        Some(unsafe { *raw.codes.add(id as usize) })
    }

    /// Width of the black square in cells.
    pub fn width_at_border(&self) -> u32 {
        self.raw().width_at_border.max(0) as u32
    }

    /// Width of the printed tag in cells (white ring included).
    pub fn total_width(&self) -> u32 {
        self.raw().total_width.max(0) as u32
    }

    /// True for families whose border is reversed (white inside black).
    pub fn reversed_border(&self) -> bool {
        self.raw().reversed_border
    }

    /// Data-bit positions `(x, y)` in cells from the top-left of the black square.
    pub fn bit_positions(&self) -> Vec<(u32, u32)> {
        let raw = self.raw();
        if raw.bit_x.is_null() || raw.bit_y.is_null() {
            return Vec::new();
        }
        (0..raw.nbits as usize)
            // SAFETY: `bit_x` and `bit_y` hold `nbits` entries each.
            .map(|i| unsafe { (*raw.bit_x.add(i), *raw.bit_y.add(i)) })
            .collect()
    }

    /// A plain copy of the codes and layout.
    pub fn layout(&self) -> FamilyLayout {
        let bits = self.bit_positions();
        FamilyLayout {
            family: self.family,
            codes: (0..self.ncodes()).filter_map(|i| self.code(i)).collect(),
            bit_x: bits.iter().map(|b| b.0).collect(),
            bit_y: bits.iter().map(|b| b.1).collect(),
            width_at_border: self.width_at_border(),
            total_width: self.total_width(),
            reversed_border: self.reversed_border(),
            min_hamming: self.raw().h,
        }
    }
}

impl Drop for FamilyTable {
    fn drop(&mut self) {
        // SAFETY: `ptr` came from the matching constructor and is destroyed exactly once.
        unsafe {
            match self.family {
                TagFamily::Tag36h11 => sys::tag36h11_destroy(self.ptr),
                TagFamily::Tag25h9 => sys::tag25h9_destroy(self.ptr),
                TagFamily::Tag16h5 => sys::tag16h5_destroy(self.ptr),
            }
        }
    }
}

/// The layout of `family`, read from the library once per process and cached.
pub fn family_layout(family: TagFamily) -> &'static FamilyLayout {
    use std::sync::OnceLock;
    static LAYOUTS: [OnceLock<FamilyLayout>; 3] = [OnceLock::new(), OnceLock::new(), OnceLock::new()];
    let idx = match family {
        TagFamily::Tag36h11 => 0,
        TagFamily::Tag25h9 => 1,
        TagFamily::Tag16h5 => 2,
    };
    LAYOUTS[idx].get_or_init(|| match FamilyTable::new(family) {
        Some(t) => t.layout(),
        // The library only returns null when calloc fails; an empty layout makes every
        // bitmap request fail cleanly instead of panicking.
        None => FamilyLayout {
            family,
            codes: Vec::new(),
            bit_x: Vec::new(),
            bit_y: Vec::new(),
            width_at_border: 0,
            total_width: 0,
            reversed_border: false,
            min_hamming: 0,
        },
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tables_match_the_family_names() {
        for f in TagFamily::ALL {
            let t = FamilyTable::new(f).expect("family table");
            assert_eq!(t.ncodes(), f.code_count(), "{f}");
            assert_eq!(t.code(t.ncodes()), None);
            assert_eq!(t.bit_positions().len() as u32, t.nbits());
            assert_eq!(t.total_width(), t.width_at_border() + 2, "{f}: classic layout has a one-cell white ring");
        }
        let t = FamilyTable::new(TagFamily::Tag36h11).unwrap();
        assert_eq!(t.nbits(), 36);
        assert_eq!((t.width_at_border(), t.total_width()), (8, 10));
        assert_eq!(t.code(0), Some(0x0000_000d_7e00_984b));
    }
}
