//! A partial frame set's view of a tag, freed of its cameras' pose bias.
//!
//! Why: every camera's pose is held from the background tags and carries a small error of
//! its own, the same in every frame set while the camera is still. A tag solved from all its
//! usual cameras carries the *mean* of their errors, the same in every full set, so it
//! cancels from displacements. A set that lacks a camera solves the tag from the others:
//! their mean error is a different one, and the displacement jumps by the difference — for
//! a monocular set, by that one camera's pose error along its line of sight. That jump is
//! not noise (it is the same in every set with the same cameras), so no weighting of a
//! single set can remove it.
//!
//! What: the corners of the tag's last few full sets are kept ([`RecentFull`]). When a set
//! sees the tag with a subset `S` of its cameras, each kept set is solved twice with the
//! cameras' *current* poses — from all its views and from the views of `S` only — and the
//! mean difference is the subset's offset `o_S`. The partial set's solve minus `o_S` is a
//! measurement of the tag referred to the full sets: the camera-pose part cancels (to first
//! order), what is left is pixel noise:
//!
//! * `Var(z_S(k) − o_S) = N_S(k) + Var(o_S)`, where `N_S` is the subset solve's pixel-noise
//!   covariance and, the full solve being the efficient one of the two nested least-squares
//!   problems on the same pixels, `Var(z_S(j) − z_full(j)) = N_S(j) − N_full(j)`, averaged
//!   over the `n` kept sets and divided by `n`.
//! * A kept set whose cameras were re-posed since (a bump: its corners belong to another
//!   camera position) is not used; drift is followed by the current poses.
//!
//! Cost: two small solves per kept set (at most [`KEPT_SETS`]) per tag, only in partial sets.

use std::collections::VecDeque;

use nalgebra::{Matrix3, Point2, Vector3};
use tagdeflect_core::camera::Pose;

use crate::{solve_tag, TagView};

/// Full sets kept per tag.
pub const KEPT_SETS: usize = 4;
/// A kept set older than this is not used, ns (the offset depends on the tag's place in
/// the images only slowly, but a kept set should describe the test as it is now).
pub const MAX_AGE_NS: i64 = 30_000_000_000;

/// One full set's views of the tag.
#[derive(Debug, Clone)]
struct KeptSet {
    t_ns: i64,
    /// (camera index, the camera's pose epoch then, corners) per view used.
    views: Vec<(usize, u64, [Point2<f64>; 4])>,
    /// The full solve's tag pose (the warm start of both solves).
    pose: Pose,
}

/// The last full sets' views of one tag (see the module docs).
#[derive(Debug, Clone, Default)]
pub struct RecentFull {
    sets: VecDeque<KeptSet>,
}

/// A partial set's solve referred to the full sets.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Referred {
    /// The partial solve minus the subset's offset, mm.
    pub centre_mm: Vector3<f64>,
    /// Its covariance: the partial solve's pixel noise plus the offset's, mm².
    pub covariance: Matrix3<f64>,
    /// The offset removed, mm.
    pub offset_mm: Vector3<f64>,
    /// Kept sets it was averaged over.
    pub sets: usize,
}

impl RecentFull {
    /// Keeps a full set's views: `views[i]` was seen by camera `cameras[i]` whose pose epoch
    /// is `epochs[cameras[i]]`; `rejected` are indices of views the solve dropped.
    pub fn push(&mut self, t_ns: i64, views: &[TagView], cameras: &[usize], rejected: &[usize], epochs: &[u64], pose: &Pose) {
        if self.sets.len() == KEPT_SETS {
            self.sets.pop_front();
        }
        let views = views
            .iter()
            .zip(cameras)
            .enumerate()
            .filter(|(i, _)| !rejected.contains(i))
            .map(|(_, (v, &c))| (c, epochs.get(c).copied().unwrap_or(0), v.corners))
            .collect();
        self.sets.push_back(KeptSet { t_ns, views, pose: *pose });
    }

    /// Full sets kept.
    pub fn len(&self) -> usize {
        self.sets.len()
    }

    /// True when no full set is kept.
    pub fn is_empty(&self) -> bool {
        self.sets.is_empty()
    }

    /// Refers a partial solve (`centre`, pixel-noise covariance `noise`) made from the
    /// cameras `subset` at `t_ns` to the kept full sets. `view_of(camera, corners)` builds a
    /// view with that camera's *current* intrinsics and pose (`None` when it has none);
    /// `epochs` are the cameras' current pose epochs. `None` when no kept set can be used.
    #[allow(clippy::too_many_arguments)]
    pub fn refer(
        &self,
        t_ns: i64,
        centre: Vector3<f64>,
        noise: &Matrix3<f64>,
        subset: &[usize],
        epochs: &[u64],
        size_mm: f64,
        pooled_sigma_px: Option<f64>,
        view_of: impl Fn(usize, [Point2<f64>; 4]) -> Option<TagView>,
    ) -> Option<Referred> {
        let mut sum = Vector3::zeros();
        let mut var = Matrix3::zeros();
        let mut n = 0usize;
        let mut all = Vec::with_capacity(4);
        let mut part = Vec::with_capacity(4);
        for kept in &self.sets {
            if t_ns - kept.t_ns > MAX_AGE_NS || kept.t_ns > t_ns {
                continue;
            }
            // Every camera of the kept set still where it was then.
            if kept.views.iter().any(|(c, e, _)| epochs.get(*c).copied() != Some(*e)) {
                continue;
            }
            all.clear();
            part.clear();
            for (c, _, corners) in &kept.views {
                let Some(v) = view_of(*c, *corners) else { continue };
                if subset.contains(c) {
                    part.push(v);
                }
                all.push(v);
            }
            // The kept set must have seen the tag with every camera of the subset, and with
            // more cameras than the subset.
            if part.len() != subset.len() || all.len() <= part.len() {
                continue;
            }
            let (Ok(full), Ok(sub)) =
                (solve_tag(&all, size_mm, Some(&kept.pose), pooled_sigma_px), solve_tag(&part, size_mm, Some(&kept.pose), pooled_sigma_px))
            else {
                continue;
            };
            // An outlier view dropped by either solve changes what is compared: skip the set.
            if full.views != all.len() || sub.views != part.len() {
                continue;
            }
            let n_full: Matrix3<f64> = full.noise_covariance.fixed_view::<3, 3>(3, 3).into_owned();
            let n_sub: Matrix3<f64> = sub.noise_covariance.fixed_view::<3, 3>(3, 3).into_owned();
            sum += sub.centre_mm - full.centre_mm;
            var += psd_difference(&n_sub, &n_full);
            n += 1;
        }
        if n == 0 {
            return None;
        }
        let offset = sum / n as f64;
        let cov_offset = var / (n * n) as f64;
        let covariance = noise + cov_offset;
        Some(Referred { centre_mm: centre - offset, covariance: (covariance + covariance.transpose()) * 0.5, offset_mm: offset, sets: n })
    }
}

/// `a − b` made positive semi-definite (its negative eigenvalues set to zero): the variance
/// of the difference of two nested least-squares estimates.
fn psd_difference(a: &Matrix3<f64>, b: &Matrix3<f64>) -> Matrix3<f64> {
    let d = a - b;
    let d = (d + d.transpose()) * 0.5;
    let eig = d.symmetric_eigen();
    let vals = eig.eigenvalues.map(|v| v.max(0.0));
    eig.eigenvectors * Matrix3::from_diagonal(&vals) * eig.eigenvectors.transpose()
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Rotation3;
    use tagdeflect_core::camera::CameraIntrinsics;

    fn camera(x_mm: f64) -> (CameraIntrinsics, Pose) {
        // Cameras 1500 mm in front of the tag (tag at the origin, facing +z), spread along x,
        // each looking at the origin.
        let k =
            CameraIntrinsics { fx: 1400.0, fy: 1400.0, cx: 640.0, cy: 480.0, width: 1280, height: 960, dist: [-0.05, 0.0, 0.0, 0.0, 0.0] };
        let eye = Vector3::new(x_mm, 0.0, 1500.0);
        // Camera z towards the origin, y down.
        let z = (-eye).normalize();
        let x = Vector3::new(0.0, -1.0, 0.0).cross(&z).normalize();
        let y = z.cross(&x);
        let r = Rotation3::from_matrix_unchecked(nalgebra::Matrix3::from_rows(&[x.transpose(), y.transpose(), z.transpose()]));
        (k, Pose { rotation: r, translation: -(r * eye) })
    }

    fn project(k: &CameraIntrinsics, p: &Pose, centre: Vector3<f64>, size: f64) -> [Point2<f64>; 4] {
        let h = size / 2.0;
        let c = [(-h, -h), (h, -h), (h, h), (-h, h)];
        c.map(|(x, y)| k.project(&(p.rotation * (centre + Vector3::new(x, y, 0.0)) + p.translation)).unwrap())
    }

    /// Camera 0's held pose is off by 0.002° (as a pose from background tags may be); the tag
    /// moves by 0.1 mm down between the kept full sets and a set seen by camera 0 alone. The
    /// monocular solve's displacement is thrown by the pose error; referred to the full
    /// sets, it is right.
    #[test]
    fn a_monocular_set_referred_to_the_full_sets_loses_its_camera_pose_error() {
        let size = 30.0;
        let cams: Vec<(CameraIntrinsics, Pose)> = [-600.0, 0.0, 600.0].iter().map(|&x| camera(x)).collect();
        // The held (believed) pose of camera 0 is turned by 0.02° about its y axis.
        let err = Rotation3::from_euler_angles(0.0, 0.002f64.to_radians(), 0.0);
        let held: Vec<Pose> = cams
            .iter()
            .enumerate()
            .map(|(i, (_, p))| if i == 0 { Pose { rotation: err * p.rotation, translation: err * p.translation } } else { *p })
            .collect();
        let view = |c: usize, corners: [Point2<f64>; 4]| {
            Some(TagView { intrinsics: cams[c].0, camera_pose: held[c], camera_pose_covariance: None, corners, corner_sigma_factor: 1.0 })
        };
        let tag_at = |y: f64| Pose { rotation: Rotation3::identity(), translation: Vector3::new(0.0, y, 0.0) };
        let epochs = [0u64, 0, 0];
        let mut recent = RecentFull::default();
        let mut full_centre = Vector3::zeros();
        for k in 0..KEPT_SETS {
            let views: Vec<TagView> = (0..3).map(|c| view(c, project(&cams[c].0, &cams[c].1, Vector3::zeros(), size)).unwrap()).collect();
            let sol = solve_tag(&views, size, Some(&tag_at(0.0)), Some(0.05)).unwrap();
            full_centre = sol.centre_mm;
            recent.push(k as i64 * 100_000_000, &views, &[0, 1, 2], &[], &epochs, &sol.tag_to_world);
        }
        let moved = Vector3::new(0.0, -0.1, 0.0);
        let mono = [view(0, project(&cams[0].0, &cams[0].1, moved, size)).unwrap()];
        let sol = solve_tag(&mono, size, Some(&tag_at(0.0)), Some(0.05)).unwrap();
        let raw_disp = sol.centre_mm - full_centre;
        let noise: Matrix3<f64> = sol.noise_covariance.fixed_view::<3, 3>(3, 3).into_owned();
        let r = recent.refer(1_000_000_000, sol.centre_mm, &noise, &[0], &epochs, size, Some(0.05), view).unwrap();
        let disp = r.centre_mm - full_centre;
        assert_eq!(r.sets, KEPT_SETS);
        assert!((raw_disp - moved).norm() > 0.03, "the pose error throws the raw monocular displacement: {raw_disp}");
        assert!((disp - moved).norm() < 1e-4, "referred: {disp} against {moved}");
        // A camera re-posed since: nothing kept can be used.
        assert!(recent.refer(1_000_000_000, sol.centre_mm, &noise, &[0], &[1, 0, 0], size, Some(0.05), view).is_none());
    }

    #[test]
    fn psd_difference_drops_negative_directions() {
        let a = Matrix3::from_diagonal(&Vector3::new(4.0, 1.0, 1.0));
        let b = Matrix3::from_diagonal(&Vector3::new(1.0, 2.0, 1.0));
        let d = psd_difference(&a, &b);
        assert!((d - Matrix3::from_diagonal(&Vector3::new(3.0, 0.0, 0.0))).norm() < 1e-12);
    }
}
