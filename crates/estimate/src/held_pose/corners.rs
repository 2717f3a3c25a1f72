//! The background corners' running means while a camera is static: the bump statistic,
//! the corner noise, the averaged corners a pose is refined from.

use nalgebra::{Point2, Vector2, Vector3};

use super::HeldCameraPose;
use crate::camera_pose::BackgroundTagObservation;
use tagdeflect_core::camera::Pose;

/// One background corner's running mean (Welford) in the image, and its world point.
#[derive(Debug, Clone, Copy)]
pub(super) struct CornerStats {
    world: Vector3<f64>,
    n: f64,
    mean: Vector2<f64>,
    m2: f64,
}

impl HeldCameraPose {
    /// Pooled per-axis scatter (px) of the background corners around their running means.
    pub fn noise_px(&self) -> Option<f64> {
        let (m2, dof) = self.corners.values().fold((self.archived_m2, self.archived_dof), |(m, d), c| (m + c.m2, d + (c.n - 1.0).max(0.0)));
        (dof >= 10.0).then(|| (m2 / (2.0 * dof)).sqrt())
    }

    /// Distance (px) of an observed corner from its running mean moved by the drift
    /// (`held` → `now`; when averaged over ≥ 3 updates) or else from `now`'s projection.
    pub(super) fn corner_shift(&self, held: &Pose, now: &Pose, tag: &BackgroundTagObservation, k: usize) -> f64 {
        let px = tag.pixels[k];
        match self.corners.get(&(tag.id, k)) {
            Some(c) if c.n >= 3.0 && (c.world - tag.world[k]).norm() < 1e-9 => {
                (Vector2::new(px.x, px.y) - c.mean - self.drift_motion(held, now, &tag.world[k])).norm()
            }
            _ => self.intrinsics.project(&now.transform(&tag.world[k])).map_or(f64::INFINITY, |p| (p - px).norm()),
        }
    }

    /// Image motion (px) of a world point between poses `held` and `now` (zero when equal).
    pub(super) fn drift_motion(&self, held: &Pose, now: &Pose, world: &Vector3<f64>) -> Vector2<f64> {
        if held == now {
            return Vector2::zeros();
        }
        match (self.intrinsics.project(&now.transform(world)), self.intrinsics.project(&held.transform(world))) {
            (Some(a), Some(b)) => a - b,
            _ => Vector2::zeros(),
        }
    }

    pub(super) fn rms(&self, pose: &Pose, tags: &[BackgroundTagObservation]) -> Option<f64> {
        let mut s = 0.0;
        let mut n = 0;
        for t in tags {
            for k in 0..4 {
                let p = self.intrinsics.project(&pose.transform(&t.world[k]))?;
                s += (p - t.pixels[k]).norm_squared();
                n += 2;
            }
        }
        (n > 0).then(|| (s / n as f64).sqrt())
    }

    pub(super) fn accumulate(&mut self, tags: &[BackgroundTagObservation], skip: &[u32]) {
        self.period_updates += 1;
        // De-drifted: each corner as it would be seen from the held pose.
        let (held, now) = match (self.raw, self.current_raw()) {
            (Some(h), Some(n)) => (h, n),
            _ => (Pose::identity(), Pose::identity()),
        };
        for t in tags.iter().filter(|t| !skip.contains(&t.id)) {
            for k in 0..4 {
                let px = Vector2::new(t.pixels[k].x, t.pixels[k].y) - self.drift_motion(&held, &now, &t.world[k]);
                let c = self.corners.entry((t.id, k)).or_insert(CornerStats { world: t.world[k], n: 0.0, mean: px, m2: 0.0 });
                c.world = t.world[k];
                c.n += 1.0;
                let d = px - c.mean;
                c.mean += d / c.n;
                c.m2 += d.dot(&(px - c.mean));
            }
        }
    }

    pub(super) fn archive_noise(&mut self) {
        for c in self.corners.values() {
            self.archived_m2 += c.m2;
            self.archived_dof += (c.n - 1.0).max(0.0);
        }
    }

    pub(super) fn averaged_observations(&self) -> Vec<BackgroundTagObservation> {
        let mut ids: Vec<u32> = self.corners.keys().map(|(id, _)| *id).collect();
        ids.sort_unstable();
        ids.dedup();
        ids.into_iter()
            .filter_map(|id| {
                let c: Vec<&CornerStats> = (0..4).map(|k| self.corners.get(&(id, k))).collect::<Option<_>>()?;
                Some(BackgroundTagObservation {
                    id,
                    pixels: [0, 1, 2, 3].map(|k| Point2::new(c[k].mean.x, c[k].mean.y)),
                    world: [0, 1, 2, 3].map(|k| c[k].world),
                })
            })
            .collect()
    }
}
