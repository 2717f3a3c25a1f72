//! The `[sim]` defaults: the built-in rig's values, and the tests that keep an option at its
//! default out of a written config (a recording of the default rig reads as it always did).

use super::{LoadLaw, SimParams, SimTest, DEFAULT_START_NS};

pub(super) fn is_default<T: Default + PartialEq>(v: &T) -> bool {
    *v == T::default()
}
// Options added later are not written when at their defaults: a recording of the default rig
// reads as it always did.
pub(super) fn is_default_drift_rot(v: &f64) -> bool {
    *v == 0.05
}
pub(super) fn is_default_drift_trans(v: &f64) -> bool {
    *v == 0.3
}
pub(super) fn is_default_fill(v: &f64) -> bool {
    *v == 1.0
}
pub(super) fn is_default_bits(v: &u32) -> bool {
    *v == 8
}
pub(super) fn is_default_outage(v: &f64) -> bool {
    *v == 5.0
}
pub(super) fn is_default_crack(v: &f64) -> bool {
    *v == 0.3
}
pub(super) fn is_default_drop(v: &f64) -> bool {
    *v == 0.1
}
pub(super) fn is_default_softening(v: &f64) -> bool {
    *v == 0.5
}
pub(super) fn is_default_notch(v: &f64) -> bool {
    *v == 25.0
}
pub(super) fn is_default_notch_width(v: &f64) -> bool {
    *v == 3.0
}

impl Default for SimParams {
    fn default() -> Self {
        Self {
            seed: 1,
            cameras: 3,
            width: 1280,
            height: 960,
            frame_sets: 40,
            fps: 10.0,
            noise_sigma: 2.0,
            blur_sigma: 0.6,
            motion_blur_every: 0,
            motion_blur_px: 3.0,
            post_blur_px: 0.0,
            sharpen: 0.0,
            bayer: false,
            bayer_raw: false,
            defocus_radius_px: 0.0,
            astig_major_px: 0.0,
            astig_minor_px: 0.0,
            astig_angle_deg: 0.0,
            fill_factor: 1.0,
            jpeg_quality: None,
            bit_depth: 8,
            exposure: 1.0,
            full_well_e: 0.0,
            jitter_ms: 1.0,
            drop_prob: 0.0,
            bump_camera: None,
            bump_at: 20,
            bump_rot_deg: 0.3,
            bump_trans_mm: 2.0,
            drift_camera: None,
            drift_rot_deg: 0.05,
            drift_trans_mm: 0.3,
            drift_start_set: 0,
            drift_sets: 0,
            hide_tag: None,
            hide_background_tag: None,
            hide_camera: 0,
            hide_from: 10,
            hide_count: 10,
            k1: -0.05,
            strong_distortion_camera: None,
            strong_k1: -0.25,
            max_deflection_mm: 6.0,
            rest_frames: 3,
            hold_frames: 0,
            seat_frames: 0,
            seat_mm: 0.0,
            slow_to_mm: 0.0,
            verify_steps: String::new(),
            rates: String::new(),
            verify_stage_half_width_mm: 0.0,
            cyclic: false,
            beam_length_mm: 550.0,
            beam_height_mm: 150.0,
            beam_width_mm: 150.0,
            span_mm: 450.0,
            load_span_mm: 150.0,
            specimen_tags: 9,
            specimen_tag_mm: 30.0,
            background_tag_mm: 70.0,
            utm_hz: 50.0,
            utm_phase_ms: 7.0,
            stiffness_kn_per_mm: 10.0,
            compliance_mm_per_kn: 0.01,
            shuffle: false,
            start_ns: DEFAULT_START_NS,
            subsamples: 8,
            utm_outage_at_s: None,
            utm_outage_s: 5.0,
            test: SimTest::FourPoint,
            load_law: LoadLaw::Elastic,
            crack_deflection_mm: 0.3,
            crack_drop: 0.1,
            residual_ratio: None,
            softening_mm: 0.5,
            notch_mm: 25.0,
            notch_width_mm: 3.0,
            crack_tip_mm: None,
            utm_clock_offset_ms: 0.0,
        }
    }
}
