//! The checks of the simulated rig's parameters: every option in its range, and the options
//! of real tests (load law, notched beam, UTM clock) consistent with each other.

use tagdeflect_core::Problem;

use super::{SimParams, SimTest};
use crate::scene::BACKGROUND_TAGS;

/// The problem of `option` (its key in `[sim]`).
fn bad(option: &'static str, message: impl Into<String>) -> Result<(), Problem> {
    Err(Problem::new(option, message))
}

impl SimParams {
    /// Checks every option (the `[sim]` section and the options of `simulate`); the problem
    /// names the option (its key in `[sim]`) and the accepted range.
    pub fn validate(&self) -> Result<(), Problem> {
        let finite_pos = |v: f64| v.is_finite() && v > 0.0;
        let finite_nonneg = |v: f64| v.is_finite() && v >= 0.0;
        if !(1..=3).contains(&self.cameras) {
            return bad("cameras", format!("{} cameras: expected 1 to 3", self.cameras));
        }
        if !(64..=8192).contains(&self.width) || !(48..=8192).contains(&self.height) {
            return bad("width", format!("{}x{}: expected 64..8192 x 48..8192 pixels", self.width, self.height));
        }
        if self.frame_sets == 0 {
            return bad("frame_sets", "expected at least 1 frame set");
        }
        if self.seed > i64::MAX as u64 {
            return bad("seed", format!("{}: expected 0 to {} (TOML integers are signed 64-bit)", self.seed, i64::MAX));
        }
        if !(self.fps.is_finite() && (0.01..=1000.0).contains(&self.fps)) {
            return bad("fps", format!("{}: expected 0.01 ≤ fps ≤ 1000", self.fps));
        }
        // Every frame time must fit in i64 nanoseconds (with a day to spare).
        if self.frame_sets as f64 / self.fps * 1e9 + self.start_ns as f64 > i64::MAX as f64 - 8.64e13 || self.start_ns < 0 {
            return bad("start_ns", format!("{}: the recording's times must lie between 1970 and 2262", self.start_ns));
        }
        if !finite_nonneg(self.noise_sigma) || self.noise_sigma > 100.0 {
            return bad("noise_sigma", format!("{}: expected 0 to 100 grey levels", self.noise_sigma));
        }
        if !finite_nonneg(self.blur_sigma) || self.blur_sigma > 10.0 {
            return bad("blur_sigma", format!("{}: expected 0 to 10 pixels", self.blur_sigma));
        }
        if !finite_nonneg(self.post_blur_px) || self.post_blur_px > 10.0 {
            return bad("post_blur_px", format!("{}: expected 0 to 10 pixels", self.post_blur_px));
        }
        if !finite_nonneg(self.sharpen) || self.sharpen > 4.0 {
            return bad("sharpen", format!("{}: expected an amount from 0 to 4", self.sharpen));
        }
        self.validate_formation()?;
        if !finite_nonneg(self.motion_blur_px) || self.motion_blur_px > 50.0 {
            return bad("motion_blur_px", format!("{}: expected 0 to 50 pixels", self.motion_blur_px));
        }
        if !finite_nonneg(self.jitter_ms) || self.jitter_ms * 3.0 >= 500.0 / self.fps {
            return bad("jitter_ms", format!("{} ms: expected ≥ 0 and 3 sigma under half the frame period", self.jitter_ms));
        }
        if !(0.0..1.0).contains(&self.drop_prob) {
            return bad("drop_prob", format!("{}: expected a probability in [0, 1)", self.drop_prob));
        }
        for (option, cam) in [
            ("bump_camera", self.bump_camera),
            ("drift_camera", self.drift_camera),
            ("strong_distortion_camera", self.strong_distortion_camera),
            ("hide_camera", Some(self.hide_camera)),
        ] {
            if let Some(c) = cam {
                if c >= self.cameras {
                    return bad(option, format!("camera {c} does not exist: expected 0..{}", self.cameras));
                }
            }
        }
        if !self.bump_rot_deg.is_finite()
            || self.bump_rot_deg.abs() > 30.0
            || !self.bump_trans_mm.is_finite()
            || self.bump_trans_mm.abs() > 300.0
        {
            return bad("bump_rot_deg", "expected a bump of at most 30 degrees and 300 mm");
        }
        if !self.drift_rot_deg.is_finite() || self.drift_rot_deg.abs() > 10.0 {
            return bad("drift_rot_deg", format!("{}: expected at most 10 degrees", self.drift_rot_deg));
        }
        if !self.drift_trans_mm.is_finite() || self.drift_trans_mm.abs() > 100.0 {
            return bad("drift_trans_mm", format!("{}: expected at most 100 mm", self.drift_trans_mm));
        }
        if self.drift_start_set >= self.frame_sets.max(1) {
            return bad("drift_start_set", format!("{}: expected less than frame_sets ({})", self.drift_start_set, self.frame_sets));
        }
        if let Some(id) = self.hide_tag {
            if id >= self.specimen_tags {
                return bad("hide_tag", format!("specimen tag {id} does not exist: expected 0..{}", self.specimen_tags));
            }
        }
        if let Some(id) = self.hide_background_tag {
            if id >= BACKGROUND_TAGS {
                return bad("hide_background_tag", format!("background tag {id} does not exist: expected 0..{BACKGROUND_TAGS}"));
            }
        }
        if !self.k1.is_finite() || self.k1.abs() > 0.5 || !self.strong_k1.is_finite() || self.strong_k1.abs() > 0.5 {
            return bad("k1", "expected |k1| ≤ 0.5");
        }
        if !finite_nonneg(self.max_deflection_mm) || self.max_deflection_mm > 0.1 * self.span_mm {
            return bad("max_deflection_mm", format!("{}: expected 0 to span/10", self.max_deflection_mm));
        }
        let steps = self.verify_positions_mm()?;
        if steps.iter().any(|p| p.abs() > self.max_deflection_mm) {
            return bad(
                "verify_steps",
                format!("a step beyond max_deflection_mm ({} mm): the scene is framed for it", self.max_deflection_mm),
            );
        }
        if !steps.is_empty() && (self.frame_sets as usize) < steps.len() || (!steps.is_empty() && self.cyclic) {
            return bad("verify_steps", format!("{} steps: expected at least one frame set each and no cyclic load", steps.len()));
        }
        if !self.rate_phases()?.is_empty() && !steps.is_empty() {
            return bad("rates", "a verification run (verify_steps) has no loading rates");
        }
        let stage = self.verify_stage_half_width_mm;
        if !finite_nonneg(stage) || stage >= 0.5 * self.span_mm || (stage > 0.0 && steps.is_empty()) {
            return bad(
                "verify_stage_half_width_mm",
                format!("{stage}: expected 0 (the whole bar moves), or below half the span with verify_steps"),
            );
        }
        let seating = self.seat_frames > 0 || self.seat_mm != 0.0;
        if seating && (!finite_pos(self.seat_mm) || self.seat_mm >= self.max_deflection_mm || self.seat_frames == 0 || !steps.is_empty()) {
            return bad(
                "seat_mm",
                format!(
                    "{} mm over {} frame sets: expected both above 0 and below max_deflection_mm, in a test",
                    self.seat_mm, self.seat_frames
                ),
            );
        }
        let slow = self.slow_to_mm;
        if slow != 0.0 && (!finite_pos(slow) || slow <= self.seat_mm || slow >= self.max_deflection_mm || !steps.is_empty()) {
            return bad("slow_to_mm", format!("{slow}: expected 0 (one rate), or above seat_mm and below max_deflection_mm, in a test"));
        }
        if self.cyclic && self.hold_frames > 0 {
            return bad("hold_frames", format!("{}: a cyclic load history holds nowhere (expected 0 with cyclic)", self.hold_frames));
        }
        if !finite_pos(self.beam_height_mm) || !finite_pos(self.beam_width_mm) || self.beam_height_mm > 400.0 || self.beam_width_mm > 400.0
        {
            return bad("beam_height_mm", "expected beam height and width in (0, 400] mm");
        }
        if !finite_pos(self.span_mm)
            || !finite_pos(self.beam_length_mm)
            || self.span_mm > self.beam_length_mm
            || self.beam_length_mm > 1200.0
        {
            return bad(
                "span_mm",
                format!("span {} mm, length {} mm: expected 0 < span ≤ length ≤ 1200 mm", self.span_mm, self.beam_length_mm),
            );
        }
        if !finite_nonneg(self.load_span_mm) || self.load_span_mm >= self.span_mm {
            return bad("load_span_mm", format!("{}: expected 0 ≤ load span < span", self.load_span_mm));
        }
        if !(1..=15).contains(&self.specimen_tags) {
            return bad("specimen_tags", format!("{}: expected 1 to 15", self.specimen_tags));
        }
        if !finite_pos(self.specimen_tag_mm) || self.specimen_tag_mm * 10.0 / 8.0 > self.beam_height_mm / 3.0 {
            return bad(
                "specimen_tag_mm",
                format!(
                    "{}: expected > 0 and three printed tags (with their white ring) stacked within the beam height",
                    self.specimen_tag_mm
                ),
            );
        }
        if !finite_pos(self.background_tag_mm) || self.background_tag_mm > 150.0 {
            return bad("background_tag_mm", format!("{}: expected 0 < size ≤ 150 mm", self.background_tag_mm));
        }
        if !((0.01..=10_000.0).contains(&self.utm_hz) && self.utm_phase_ms.abs() <= 1e6) {
            return bad("utm_hz", "expected 0.01 ≤ utm_hz ≤ 10000 and a phase within ±1000 s");
        }
        if !finite_nonneg(self.stiffness_kn_per_mm) || !finite_nonneg(self.compliance_mm_per_kn) {
            return bad("stiffness_kn_per_mm", "expected non-negative stiffness and compliance");
        }
        if !(1..=32).contains(&self.subsamples) {
            return bad("subsamples", format!("{}: expected 1 to 32", self.subsamples));
        }
        if self.utm_outage_at_s.is_some_and(|a| !(a.is_finite() && a >= 0.0)) || !(self.utm_outage_s.is_finite() && self.utm_outage_s > 0.0)
        {
            return bad("utm_outage_at_s", "expected an outage start ≥ 0 s and a positive utm_outage_s");
        }
        self.validate_test()
    }

    /// Checks the image formations before the pixel (defocus, astigmatism, fill factor) and
    /// after it (JPEG, bit depth).
    fn validate_formation(&self) -> Result<(), Problem> {
        let finite_nonneg = |v: f64| v.is_finite() && v >= 0.0;
        if !finite_nonneg(self.defocus_radius_px) || self.defocus_radius_px > 10.0 {
            return bad("defocus_radius_px", format!("{}: expected 0 to 10 pixels", self.defocus_radius_px));
        }
        if !finite_nonneg(self.astig_major_px) || self.astig_major_px > 10.0 {
            return bad("astig_major_px", format!("{}: expected 0 to 10 pixels", self.astig_major_px));
        }
        let (major, minor) = (self.astig_major_px, self.astig_minor_px);
        let minor_ok = if major > 0.0 { minor.is_finite() && minor >= 0.05 && minor <= major } else { minor == 0.0 };
        if !minor_ok {
            return bad("astig_minor_px", format!("{minor}: expected 0.05 px up to astig_major_px ({major}), or 0 with no astig_major_px"));
        }
        if !(self.astig_angle_deg.is_finite() && self.astig_angle_deg.abs() <= 360.0) {
            return bad("astig_angle_deg", format!("{}: expected -360 to 360 degrees", self.astig_angle_deg));
        }
        if !(self.fill_factor.is_finite() && (0.1..=1.0).contains(&self.fill_factor)) {
            return bad("fill_factor", format!("{}: expected 0.1 to 1 of the pixel's area", self.fill_factor));
        }
        if self.jpeg_quality.is_some_and(|q| !(1..=100).contains(&q)) {
            return bad("jpeg_quality", format!("{}: expected 1 to 100", self.jpeg_quality.unwrap_or_default()));
        }
        if self.bayer_raw && (self.bayer || self.bit_depth != 8) {
            return bad("bayer_raw", "a raw 8-bit mosaic: not with bayer (a demosaiced one) nor a bit_depth above 8".to_string());
        }
        if !(8..=16).contains(&self.bit_depth) {
            return bad("bit_depth", format!("{} bits: expected 8 to 16", self.bit_depth));
        }
        if !(self.exposure.is_finite() && (0.001..=1.0).contains(&self.exposure)) {
            return bad("exposure", format!("{}: expected 0.001 to 1 of the default scene's light", self.exposure));
        }
        if !(self.full_well_e == 0.0 || (self.full_well_e.is_finite() && (100.0..=1e7).contains(&self.full_well_e))) {
            return bad("full_well_e", format!("{} electrons: expected 0 (no shot noise) or 100 to 10^7", self.full_well_e));
        }
        Ok(())
    }

    /// Checks the options of real tests (load law, notched beam, UTM clock).
    fn validate_test(&self) -> Result<(), Problem> {
        if !(self.crack_deflection_mm.is_finite() && self.crack_deflection_mm > 0.0) {
            return bad("crack_deflection_mm", format!("{}: expected a positive deflection", self.crack_deflection_mm));
        }
        if !(0.0..1.0).contains(&self.crack_drop) {
            return bad("crack_drop", format!("{}: expected a fraction in [0, 1)", self.crack_drop));
        }
        if let Some(r) = self.residual_ratio {
            if !(r.is_finite() && (0.0..=5.0).contains(&r)) {
                return bad("residual_ratio", format!("{r}: expected 0 to 5"));
            }
        }
        if !(self.softening_mm.is_finite() && self.softening_mm > 0.0) {
            return bad("softening_mm", format!("{}: expected a positive deflection scale", self.softening_mm));
        }
        if !(self.utm_clock_offset_ms.is_finite() && self.utm_clock_offset_ms.abs() <= 10_000.0) {
            return bad("utm_clock_offset_ms", format!("{}: expected at most 10 s either way", self.utm_clock_offset_ms));
        }
        if self.test == SimTest::ThreePointNotched {
            if !(self.notch_mm.is_finite() && self.notch_mm > 0.0 && self.notch_mm <= 0.5 * self.beam_height_mm) {
                return bad("notch_mm", format!("{}: expected 0 < notch ≤ half the beam height", self.notch_mm));
            }
            if !(self.notch_width_mm.is_finite() && self.notch_width_mm > 0.0 && self.notch_width_mm <= 10.0) {
                return bad("notch_width_mm", format!("{}: expected 0 to 10 mm", self.notch_width_mm));
            }
            let tip = self.crack_tip_height();
            if !(tip.is_finite() && tip > self.notch_mm && tip < self.beam_height_mm) {
                return bad("crack_tip_mm", format!("{tip}: expected above the notch and below the top face"));
            }
            if !(5..=9).contains(&self.specimen_tags) {
                return bad("specimen_tags", "the notched test has 5 to 9 tags (midspan, two supports, two across the notch, then more)");
            }
        }
        Ok(())
    }
}
