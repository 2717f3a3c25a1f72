//! One detected tag in one image.

use nalgebra::Point2;

use tagdeflect_core::tags::TagFamily;

/// One detected tag in one image.
#[derive(Debug, Clone, PartialEq)]
pub struct Detection {
    /// Family of the tag.
    pub family: TagFamily,
    /// Tag id within its family.
    pub id: u32,
    /// Corners of the black square in pixels (OpenCV convention), SPEC order:
    /// bottom-left, bottom-right, top-right, top-left as printed.
    pub corners: [Point2<f64>; 4],
    /// The detector's decision margin (higher is more confident).
    pub decision_margin: f32,
    /// Bits corrected by the decoder.
    pub hamming: u8,
}

impl Detection {
    /// Centre of the four corners.
    pub fn centre(&self) -> Point2<f64> {
        let s = self.corners.iter().fold(nalgebra::Vector2::zeros(), |a, p| a + p.coords);
        Point2::from(s / 4.0)
    }
}
