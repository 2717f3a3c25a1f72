//! What the measurement saw in a frame set, for the sinks that show it (the live page's
//! thumbnails and camera poses): part of its output, like the feed line. Written by
//! `estimate::measure`, read by the sinks.

use nalgebra::Point2;

use crate::camera::Pose;
use crate::tags::TagFamily;

/// A tag detected in one camera's frame of the last frame set (what the live page outlines
/// on the camera thumbnails).
#[derive(Debug, Clone, PartialEq)]
pub struct SeenTag {
    /// Tag family.
    pub family: TagFamily,
    /// Tag id within the family.
    pub id: u32,
    /// A specimen tag (else a background tag).
    pub specimen: bool,
    /// Corners in the frame, pixels (OpenCV convention), the detector's order.
    pub corners: [Point2<f64>; 4],
}

/// What the measurement saw in a frame set, for the sinks that show it (the live page's
/// thumbnails and camera poses): part of its output, like the feed line.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Observed {
    /// The tags detected in each camera's frame, as (camera index, tags); cameras without a
    /// frame in the set are absent.
    pub seen: Vec<(usize, Vec<SeenTag>)>,
    /// Each camera's pose (world → camera) after the set, `None` until posed.
    pub camera_poses: Vec<Option<Pose>>,
}
