//! What a [`Measurement`](super::Measurement) is built from.

use tagdeflect_core::camera_config::CameraConfig;
use tagdeflect_core::rig::{BackgroundConfig, SpecimenConfig, WorldConfig};

/// What a [`Measurement`](super::Measurement) is built from: the rig it measures and the
/// sections it owns (`[measure]`, `[[gauge]]`, `[clock_check]`), each already validated.
#[derive(Debug, Clone, PartialEq)]
pub struct MeasurementRig {
    /// `[world]`.
    pub world: WorldConfig,
    /// The cameras, in config order (intrinsics, optional fixed poses).
    pub cameras: Vec<CameraConfig>,
    /// `[background]`.
    pub background: BackgroundConfig,
    /// `[specimen]`.
    pub specimen: SpecimenConfig,
    /// `[measure]`.
    pub measure: crate::measure_config::MeasureConfig,
    /// `[[gauge]]`.
    pub gauges: Vec<crate::gauges::GaugeConfig>,
    /// `[clock_check]`.
    pub clock_check: Option<crate::clock_offset::ClockCheckConfig>,
    /// The UTM's polling rate when one is configured, Hz: load is not interpolated across
    /// a gap longer than five polling periods (at least 0.5 s).
    pub utm_poll_hz: Option<f64>,
}
