//! Camera poses over time: the bumped camera's pose from frame set `bump_at` on, the
//! drifting camera's gradual tilt and settling, and the cache key of a pose.

use nalgebra::{Rotation3, Unit, Vector3};

use tagdeflect_core::camera::Pose;

use super::SimRig;

impl SimRig {
    /// Pose of camera `cam` at `t_ns` (after the bump from frame set `bump_at` on; moved by
    /// the drift of the frame set nearest to `t_ns` for the drifting camera).
    /// Panics if `cam >= camera_count()`.
    pub fn camera_pose(&self, cam: usize, t_ns: i64) -> Pose {
        let base = match self.layout.bumped {
            Some((c, pose)) if c == cam && self.set_index_at(t_ns) >= self.params.bump_at as i64 => pose,
            _ => self.layout.poses[cam],
        };
        match self.drift_step(cam, t_ns) {
            Some(k) => self.drifted(&base, k),
            None => base,
        }
    }

    /// For the drifting camera: the frame set (clamped to the recording) whose drift applies at `t_ns`.
    fn drift_step(&self, cam: usize, t_ns: i64) -> Option<i64> {
        (self.params.drift_camera == Some(cam as u32))
            .then(|| self.set_index_at(t_ns).clamp(0, self.params.frame_sets.saturating_sub(1) as i64))
    }

    /// `base` after the drift of frame set `k`: a linear share of
    /// `drift_rot_deg` (about an oblique, mostly horizontal axis through the camera centre —
    /// a tripod head tilting) and of `drift_trans_mm` (the centre moving mostly down — the
    /// floor settling): 0 up to set `drift_start_set`, all of it `drift_sets` sets later (0:
    /// at the last set) and after.
    fn drifted(&self, base: &Pose, k: i64) -> Pose {
        let p = &self.params;
        let from = p.drift_start_set as i64;
        let len = if p.drift_sets > 0 { p.drift_sets as i64 } else { p.frame_sets as i64 - 1 - from };
        let u = if len > 0 { ((k - from) as f64 / len as f64).clamp(0.0, 1.0) } else { f64::from(u8::from(k >= from)) };
        let axis = Unit::new_normalize(Vector3::new(1.0, 0.3, 0.2));
        let dr = Rotation3::from_axis_angle(&axis, u * p.drift_rot_deg.to_radians());
        let dt = Vector3::new(0.3, 0.2, -1.0).normalize() * (u * p.drift_trans_mm);
        let centre = base.centre() + dt;
        let rotation = dr * base.rotation;
        Pose { rotation, translation: -(rotation * centre) }
    }

    /// Cache key of camera `cam`'s pose at `t_ns` (bump epoch and drift step).
    pub(crate) fn pose_key(&self, cam: usize, t_ns: i64) -> u64 {
        self.pose_epoch(cam, t_ns) as u64 | self.drift_step(cam, t_ns).map_or(0, |k| (k as u64 + 1) << 8)
    }

    pub(crate) fn pose_epoch(&self, cam: usize, t_ns: i64) -> u8 {
        match self.layout.bumped {
            Some((c, _)) if c == cam && self.set_index_at(t_ns) >= self.params.bump_at as i64 => 1,
            _ => 0,
        }
    }
}

#[cfg(test)]
mod tests {
    use crate::{SimParams, SimRig};

    /// A drift from set 10 over 5 sets: still before, linear within, held after.
    #[test]
    fn a_drift_can_start_and_end_mid_recording() {
        let p = SimParams { frame_sets: 30, drift_camera: Some(1), drift_start_set: 10, drift_sets: 5, ..SimParams::default() };
        let rig = SimRig::new(&p).unwrap();
        let centre = |k| rig.camera_pose(1, rig.set_time_ns(k)).centre();
        let shift = |k| (centre(k) - centre(0)).norm();
        assert_eq!(shift(10), 0.0, "still up to the start");
        assert!((shift(12) - 0.4 * p.drift_trans_mm).abs() < 1e-9, "{}", shift(12));
        assert!((shift(15) - p.drift_trans_mm).abs() < 1e-9 && (shift(29) - p.drift_trans_mm).abs() < 1e-9);
        assert_eq!((rig.camera_pose(0, rig.set_time_ns(29)).centre() - rig.camera_pose(0, 0).centre()).norm(), 0.0, "the others are still");
        let bad = SimParams { frame_sets: 30, drift_start_set: 30, ..SimParams::default() };
        assert!(bad.validate().unwrap_err().to_string().contains("drift_start_set"));
    }
}
