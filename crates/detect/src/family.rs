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

use tagdeflect_core::tags::{TagBitmap, TagError, TagFamily};

pub use tagdeflect_core::tags::FamilyLayout;

/// The library's constructor and destructor of each family's table, in the order of
/// [`TagFamily::ALL`] (the family's other facts are in `tags`).
const CONSTRUCTORS: [(unsafe extern "C" fn() -> *mut sys::apriltag_family_t, unsafe extern "C" fn(*mut sys::apriltag_family_t)); 3] = [
    (sys::tag36h11_create, sys::tag36h11_destroy),
    (sys::tag25h9_create, sys::tag25h9_destroy),
    (sys::tag16h5_create, sys::tag16h5_destroy),
];

/// Owner of one family table created by the AprilTag library.
#[derive(Debug)]
pub(crate) struct FamilyTable {
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
        let ptr = unsafe { (CONSTRUCTORS[family.index()].0)() };
        if ptr.is_null() {
            None
        } else {
            Some(Self { family, ptr })
        }
    }

    /// Creates the library's table for `family` printed with a black border of
    /// `border_bits` cells (1: the family as designed; 2: Kalibr's AprilGrid tags, the same
    /// code inside one more black ring). The wider border is the library's own table with
    /// the black square two cells wider and every data bit one cell further in, so the
    /// library's quad decoder samples the bits where an AprilGrid prints them. `None` for a
    /// border outside 1–2 or when the library's allocation failed.
    pub fn with_border(family: TagFamily, border_bits: u32) -> Option<Self> {
        if !(1..=2).contains(&border_bits) {
            return None;
        }
        let table = Self::new(family)?;
        let extra = border_bits - 1;
        if extra > 0 {
            // SAFETY: `ptr` is non-null and owned by `table` alone; the detector has not seen
            // it yet. `bit_x` / `bit_y` hold `nbits` entries each (allocated by the
            // constructor and freed by the destructor, which only frees them): shifting their
            // values in place changes no allocation.
            unsafe {
                let raw = &mut *table.ptr;
                raw.width_at_border += 2 * extra as i32;
                raw.total_width += 2 * extra as i32;
                if !raw.bit_x.is_null() && !raw.bit_y.is_null() {
                    for i in 0..raw.nbits as usize {
                        *raw.bit_x.add(i) += extra;
                        *raw.bit_y.add(i) += extra;
                    }
                }
            }
        }
        Some(table)
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

    /// Number of data bits (the tests check the bit positions against it).
    #[cfg(test)]
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
        unsafe { (CONSTRUCTORS[self.family.index()].1)(self.ptr) }
    }
}

/// The layout of `family`, read from the library once per process and cached.
pub(crate) fn family_layout(family: TagFamily) -> &'static FamilyLayout {
    use std::sync::OnceLock;
    static LAYOUTS: [OnceLock<FamilyLayout>; 3] = [OnceLock::new(), OnceLock::new(), OnceLock::new()];
    LAYOUTS[family.index()].get_or_init(|| match FamilyTable::new(family) {
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

/// The bitmap of tag `id` of `family`, read from the AprilTag library's family table.
pub fn tag_bitmap(family: TagFamily, id: u32) -> Result<TagBitmap, TagError> {
    TagBitmap::from_layout(family_layout(family), id)
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
            assert_eq!((t.width_at_border(), t.total_width()), (f.facts().width_at_border, f.facts().total_width), "{f}: facts table");
        }
        let t = FamilyTable::new(TagFamily::Tag36h11).unwrap();
        let wide = FamilyTable::with_border(TagFamily::Tag36h11, 2).unwrap();
        assert_eq!((wide.width_at_border(), wide.total_width()), (10, 12));
        let shifted: Vec<(u32, u32)> = t.bit_positions().iter().map(|&(x, y)| (x + 1, y + 1)).collect();
        assert_eq!(wide.bit_positions(), shifted);
        assert_eq!(wide.code(5), t.code(5));
        assert!(FamilyTable::with_border(TagFamily::Tag36h11, 3).is_none());
        assert_eq!(t.nbits(), 36);
        assert_eq!((t.width_at_border(), t.total_width()), (8, 10));
        assert_eq!(t.code(0), Some(0x0000_000d_7e00_984b));
    }
}

#[cfg(test)]
mod bitmap_tests {
    use super::tag_bitmap;
    use tagdeflect_core::tags::{TagError, TagFamily};

    /// Reads an apriltag-imgs PNG (RGBA) as a white/black grid.
    fn read_png(path: &std::path::Path) -> Option<(u32, Vec<bool>)> {
        let img = image::open(path).ok()?.to_luma8();
        let (w, h) = img.dimensions();
        assert_eq!(w, h);
        Some((w, img.pixels().map(|p| p.0[0] > 127).collect()))
    }

    #[test]
    fn bitmaps_match_apriltag_imgs() {
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/realdata/apriltag-imgs");
        let mut checked = 0;
        for (family, dir, prefix, ids) in [
            (TagFamily::Tag36h11, "tag36h11", "tag36_11_", vec![0u32, 1, 7, 42, 100, 311, 586]),
            (TagFamily::Tag25h9, "tag25h9", "tag25_09_", vec![0u32, 1, 5, 17, 34]),
        ] {
            for id in ids {
                let path = root.join(dir).join(format!("{prefix}{id:05}.png"));
                let (w, px) = read_png(&path).unwrap_or_else(|| panic!("cannot read {}", path.display()));
                let bm = tag_bitmap(family, id).unwrap();
                assert_eq!(w, bm.total_width, "{}", path.display());
                assert_eq!(px, bm.white, "{family} id {id} differs from {}", path.display());
                checked += 1;
            }
        }
        println!("{checked} bitmaps match apriltag-imgs pixel for pixel");
    }

    #[test]
    fn unknown_id_is_an_error() {
        assert!(matches!(tag_bitmap(TagFamily::Tag25h9, 35), Err(TagError::UnknownId { count: 35, .. })));
    }

    #[test]
    fn cell_lookup_follows_the_printed_orientation() {
        let bm = tag_bitmap(TagFamily::Tag36h11, 0).unwrap();
        // 30 mm black square: cell 3.75 mm, printed 37.5 mm.
        assert_eq!(bm.cell_at(-18.0, 18.0, 30.0), Some((0, 0)));
        assert_eq!(bm.cell_at(18.0, -18.0, 30.0), Some((9, 9)));
        assert_eq!(bm.cell_at(-14.0, -14.0, 30.0), Some((1, 8)));
        assert_eq!(bm.cell_at(19.0, 0.0, 30.0), None);
        assert!(!bm.is_white(1, 1) && bm.is_white(0, 0));
    }
}
