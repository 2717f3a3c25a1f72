//! Tag families and tag geometry: family names, corner order, tag-frame corners.
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

impl TagFamily {
    /// All supported families.
    pub const ALL: [TagFamily; 3] = [TagFamily::Tag36h11, TagFamily::Tag25h9, TagFamily::Tag16h5];

    /// The family's name as the AprilTag library spells it.
    pub fn name(self) -> &'static str {
        match self {
            TagFamily::Tag36h11 => "tag36h11",
            TagFamily::Tag25h9 => "tag25h9",
            TagFamily::Tag16h5 => "tag16h5",
        }
    }

    /// Number of codes (valid ids are `0..code_count()`).
    pub fn code_count(self) -> u32 {
        match self {
            TagFamily::Tag36h11 => 587,
            TagFamily::Tag25h9 => 35,
            TagFamily::Tag16h5 => 30,
        }
    }
}

impl fmt::Display for TagFamily {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for TagFamily {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        TagFamily::ALL
            .into_iter()
            .find(|f| f.name() == s)
            .ok_or_else(|| format!("unknown tag family \"{s}\": expected one of tag36h11, tag25h9, tag16h5"))
    }
}

impl TryFrom<String> for TagFamily {
    type Error = String;
    fn try_from(s: String) -> Result<Self, String> {
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
