//! Closed-form starts: plane-to-image homographies and their decomposition into a pose,
//! with the planar (mirror) ambiguity's second solution.
//!
//! These only seed the least-squares problems; accuracy comes from the LM refinement with
//! the full distortion model. Image points are first undistorted to normalised coordinates.

use nalgebra::{Matrix3, Rotation3, Unit, Vector3};

pub use tagdeflect_core::camera::homography;

/// Decomposes a plane → normalised-image homography into the pose of the plane frame
/// (plane points `(u, v, 0)`) in the camera: `x_cam = R [u v 0]ᵀ + t`, with the plane in
/// front of the camera. `None` when degenerate.
pub fn pose_from_homography(h: &Matrix3<f64>) -> Option<(Rotation3<f64>, Vector3<f64>)> {
    let h1 = h.column(0).into_owned();
    let h2 = h.column(1).into_owned();
    let h3 = h.column(2).into_owned();
    let scale = 0.5 * (h1.norm() + h2.norm());
    if !scale.is_finite() || scale <= 1e-300 {
        return None;
    }
    let mut lambda = 1.0 / scale;
    if h3.z * lambda < 0.0 {
        lambda = -lambda;
    }
    let r1 = h1 * lambda;
    let r2 = h2 * lambda;
    let r3 = r1.cross(&r2);
    let m = Matrix3::from_columns(&[r1, r2, r3]);
    let svd = m.svd(true, true);
    let (u, vt) = (svd.u?, svd.v_t?);
    let mut r = u * vt;
    if r.determinant() < 0.0 {
        let mut u2 = u;
        u2.column_mut(2).neg_mut();
        r = u2 * vt;
    }
    let t = h3 * lambda;
    if !t.iter().all(|v| v.is_finite()) || t.z <= 0.0 {
        return None;
    }
    Some((Rotation3::from_matrix_unchecked(r), t))
}

/// The other solution of the planar pose ambiguity: the plane's normal mirrored about the
/// line of sight to the plane's origin, same origin. Equal to the input for a frontal view.
pub(crate) fn mirrored(rotation: &Rotation3<f64>, t: &Vector3<f64>) -> Rotation3<f64> {
    let n = rotation * Vector3::z();
    let ray = t.normalize();
    let n_alt = ray * (2.0 * n.dot(&ray)) - n;
    match Rotation3::rotation_between(&n, &n_alt) {
        Some(q) => q * rotation,
        None => {
            // Opposite normals (edge-on view): rotate by π about any axis ⟂ n.
            let axis = Unit::new_normalize(n.cross(&Vector3::x()).try_normalize(1e-9).unwrap_or_else(|| n.cross(&Vector3::y())));
            Rotation3::from_axis_angle(&axis, std::f64::consts::PI) * rotation
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector2;
    use tagdeflect_core::camera::rotation_angle;

    #[test]
    fn homography_pose_round_trip() {
        let r = Rotation3::new(Vector3::new(0.3, -0.4, 0.2));
        let t = Vector3::new(20.0, -10.0, 500.0);
        let plane: Vec<Vector2<f64>> =
            vec![Vector2::new(-15.0, -15.0), Vector2::new(15.0, -15.0), Vector2::new(15.0, 15.0), Vector2::new(-15.0, 15.0)];
        let image: Vec<Vector2<f64>> = plane
            .iter()
            .map(|p| {
                let c = r * Vector3::new(p.x, p.y, 0.0) + t;
                Vector2::new(c.x / c.z, c.y / c.z)
            })
            .collect();
        let h = homography(&plane, &image).expect("homography");
        let (r2, t2) = pose_from_homography(&h).expect("pose");
        assert!(rotation_angle(&(r2.inverse() * r)) < 1e-8);
        assert!((t2 - t).norm() < 1e-6);
        let m = mirrored(&r2, &t2);
        assert!(rotation_angle(&(m.inverse() * r2)) > 0.1, "mirror differs for an oblique view");
        let back = mirrored(&m, &t2);
        let err = rotation_angle(&(back.inverse() * r2));
        assert!(err < 1e-9, "mirroring twice is the identity: {err}");
    }
}
