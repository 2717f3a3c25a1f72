//! The frame schedule of the simulated rig: the nominal time of each frame set, each
//! camera's capture time (jitter) or dropped frame, and which frames carry motion blur or
//! hide a specimen tag.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};

use super::rig::mix;
use super::SimRig;

impl SimRig {
    /// Nominal time of frame set `k`, ns.
    pub fn set_time_ns(&self, k: u64) -> i64 {
        self.params.start_ns + (k as f64 * 1e9 / self.params.fps).round() as i64
    }

    /// The frame set whose nominal time is nearest to `t_ns` (may be negative before the start).
    pub(crate) fn set_index_at(&self, t_ns: i64) -> i64 {
        ((t_ns - self.params.start_ns) as f64 * self.params.fps / 1e9).round() as i64
    }

    /// Capture time of camera `cam`'s frame of set `k`, or `None` when the camera dropped it.
    pub fn frame_time_ns(&self, cam: usize, k: u64) -> Option<i64> {
        let mut rng = ChaCha8Rng::seed_from_u64(mix(mix(self.params.seed, 0x7111), mix(cam as u64, k)));
        let z: f64 = StandardNormal.sample(&mut rng);
        let drop: f64 = rng.gen();
        if drop < self.params.drop_prob {
            return None;
        }
        let jitter_ns = (z.clamp(-3.0, 3.0) * self.params.jitter_ms * 1e6).round() as i64;
        Some(self.set_time_ns(k) + jitter_ns)
    }

    /// True when camera `cam`'s frame of set `k` carries motion blur.
    pub fn has_motion_blur(&self, cam: usize, k: i64) -> bool {
        let every = self.params.motion_blur_every as i64;
        every > 0
            && k >= 1
            && k % every == every / 2
            && ((k / every) as usize % self.camera_count()) == cam
            && self.params.motion_blur_px > 0.0
    }

    /// The specimen tag hidden from camera `cam` in set `k`, if any.
    pub(crate) fn hidden_tag(&self, cam: usize, k: i64) -> Option<u32> {
        self.params.hide_tag.filter(|_| self.hides(cam, k))
    }

    /// The background tag hidden from camera `cam` in set `k`, if any.
    pub(crate) fn hidden_background_tag(&self, cam: usize, k: i64) -> Option<u32> {
        self.params.hide_background_tag.filter(|_| self.hides(cam, k))
    }

    /// Whether camera `cam` has its hidden tags covered in set `k`.
    fn hides(&self, cam: usize, k: i64) -> bool {
        let p = &self.params;
        cam == p.hide_camera as usize && k >= p.hide_from as i64 && k < p.hide_from as i64 + p.hide_count as i64
    }
}
