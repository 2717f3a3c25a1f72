//! Unit tests of the tag pose solve and its covariance.

use super::*;
use crate::lm::retract;
use nalgebra::Vector6;

fn view() -> TagView {
    TagView {
        intrinsics: CameraIntrinsics {
            width: 1280,
            height: 960,
            fx: 1400.0,
            fy: 1400.0,
            cx: 639.5,
            cy: 479.5,
            dist: [-0.25, 0.08, 0.0, 0.0, 0.0],
        },
        camera_pose: Pose::from_rvec_tvec([1.5, 0.1, 0.05], [20.0, -30.0, 1500.0]),
        camera_pose_covariance: None,
        corners: [Point2::new(600.0, 500.0); 4],
        corner_sigma_factor: 1.0,
    }
}

#[test]
fn jacobians_match_finite_differences() {
    let v = view();
    let tag = Pose::from_rvec_tvec([1.4, -0.1, 0.2], [50.0, 10.0, -20.0]);
    let corner = Vector3::new(15.0, -15.0, 0.0);
    let px = v.corners[0];
    let (_, jt, jc) = tag_corner_terms(&v, &tag, &corner, &px).expect("in front");
    for k in 0..6 {
        let h = if k < 3 { 1e-7 } else { 1e-4 };
        let mut d = Vector6::zeros();
        d[k] = h;
        let (a, _, _) = tag_corner_terms(&v, &retract(&tag, &d), &corner, &px).unwrap();
        let (b, _, _) = tag_corner_terms(&v, &retract(&tag, &-d), &corner, &px).unwrap();
        let fd = (a - b) / (2.0 * h);
        assert!((fd - jt.column(k)).norm() < 1e-5 * jt.column(k).norm().max(1.0), "tag column {k}: {fd} vs {}", jt.column(k));
        let mut vp = v;
        vp.camera_pose = retract(&v.camera_pose, &d);
        let mut vm = v;
        vm.camera_pose = retract(&v.camera_pose, &-d);
        let (a, _, _) = tag_corner_terms(&vp, &tag, &corner, &px).unwrap();
        let (b, _, _) = tag_corner_terms(&vm, &tag, &corner, &px).unwrap();
        let fd = (a - b) / (2.0 * h);
        assert!((fd - jc.column(k)).norm() < 1e-5 * jc.column(k).norm().max(1.0), "camera column {k}: {fd} vs {}", jc.column(k));
    }
}

#[test]
fn monocular_noise_free_is_exact() {
    let mut v = view();
    let tag = Pose::from_rvec_tvec([1.5, 0.2, -0.1], [40.0, 0.0, 10.0]);
    let corners = tag_corners(30.0);
    v.corners = [0, 1, 2, 3].map(|k| v.intrinsics.project(&v.camera_pose.transform(&tag.transform(&corners[k]))).unwrap());
    let s = solve_tag(&[v], 30.0, None, Some(0.1)).expect("solves");
    assert!((s.centre_mm - tag.translation).norm() < 1e-6, "centre {} vs {}", s.centre_mm, tag.translation);
    assert!(s.tag_to_world.angle_to(&tag) < 1e-6);
    assert_eq!((s.views, s.dof), (1, 2));
    assert!(s.sigma_mm.iter().all(|x| x.is_finite() && *x > 0.0));
}

#[test]
fn a_views_corner_sigma_factor_widens_the_covariance_and_never_moves_the_solution() {
    // Two views of a tag (the second camera 300 mm to the side), noise-free corners.
    let tag = Pose::from_rvec_tvec([1.5, 0.2, -0.1], [40.0, 0.0, 10.0]);
    let corners = tag_corners(30.0);
    let mut views = [view(), view()];
    views[1].camera_pose = Pose::from_rvec_tvec([1.5, 0.3, 0.05], [-280.0, -30.0, 1500.0]);
    for v in views.iter_mut() {
        v.corners = [0, 1, 2, 3].map(|k| v.intrinsics.project(&v.camera_pose.transform(&tag.transform(&corners[k]))).unwrap());
    }
    let solve = |f: [f64; 2]| {
        let mut vs = views;
        vs[0].corner_sigma_factor = f[0];
        vs[1].corner_sigma_factor = f[1];
        solve_tag(&vs, 30.0, None, Some(0.1)).expect("solves")
    };
    let plain = solve([1.0, 1.0]);
    let doubled = solve([2.0, 2.0]);
    let one = solve([1.0, 2.0]);
    // Both views twice as noisy: σ twice; the solution itself unchanged.
    assert_eq!(doubled.centre_mm, plain.centre_mm);
    for a in 0..3 {
        assert!((doubled.sigma_mm[a] / plain.sigma_mm[a] - 2.0).abs() < 1e-6, "axis {a}");
        assert!(
            one.sigma_mm[a] > plain.sigma_mm[a] * 1.0001 && one.sigma_mm[a] < doubled.sigma_mm[a],
            "axis {a}: one view widened lies between"
        );
    }
    // A factor below 1 (or not finite) never narrows σ.
    assert_eq!(solve([0.5, f64::NAN]).sigma_mm, plain.sigma_mm);
}

#[test]
fn bad_input_is_an_error() {
    assert!(solve_tag(&[], 30.0, None, None).is_err());
    assert!(solve_tag(&[view()], -1.0, None, None).is_err());
    assert!(solve_tag(&[view()], 30.0, None, None).is_err(), "four identical corners are degenerate");
}

#[test]
fn noise_pool_pools() {
    let mut p = PixelNoisePool::new(1.0, 20.0);
    assert_eq!(p.sigma_px(), None);
    for _ in 0..10 {
        p.add(0.01 * 2.0, 2);
    }
    assert!((p.sigma_px().unwrap() - 0.1).abs() < 1e-12);
}

/// Corners correlated through their edges (−0.5 along an edge's normal, see
/// [`EDGE_CORNER_CORRELATION`]): the covariance the switch gives is the scatter of the
/// solve's centre over runs with corner noise correlated so; the independent corners'
/// covariance (the plain one) is not.
#[test]
fn corners_correlated_through_their_edges_give_the_centres_scatter_under_such_noise() {
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};
    let mut v = view();
    let tag = Pose::from_rvec_tvec([1.5, 0.12, 0.05], [40.0, 0.0, 10.0]);
    let corners = tag_corners(30.0);
    v.corners = [0, 1, 2, 3].map(|k| v.intrinsics.project(&v.camera_pose.transform(&tag.transform(&corners[k]))).unwrap());
    let problem = TagProblem { views: vec![(0, &v)], corners };
    let mut h = Matrix6::zeros();
    for k in 0..4 {
        h += tag_corner_terms(&v, &tag, &corners[k], &v.corners[k]).map(|t| t.1.transpose() * t.1).expect("in front");
    }
    let h_inv = h.try_inverse().expect("regular");
    let s2 = 0.01;
    assert_eq!(widened(h_inv * s2, &problem, &tag, &h_inv, (s2, false)), h_inv * s2);
    let correlated = widened(h_inv * s2, &problem, &tag, &h_inv, (s2, true));
    // Corner noise of variance s2 per coordinate, the corners of each edge at −0.5 along it.
    let mut cov = nalgebra::SMatrix::<f64, 8, 8>::identity() * s2;
    for a in 0..4 {
        let b = (a + 1) % 4;
        let u = v.corners[b] - v.corners[a];
        let n = Vector2::new(-u.y, u.x).normalize();
        let block = n * n.transpose() * (EDGE_CORNER_CORRELATION * s2);
        cov.fixed_view_mut::<2, 2>(2 * a, 2 * b).copy_from(&block);
        cov.fixed_view_mut::<2, 2>(2 * b, 2 * a).copy_from(&block);
    }
    let l = cov.cholesky().expect("positive definite").l();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
    let normal = Normal::new(0.0, 1.0).unwrap();
    let runs = 2000;
    let mut scatter = [0.0; 2];
    for _ in 0..runs {
        let e = l * nalgebra::SVector::<f64, 8>::from_fn(|_, _| normal.sample(&mut rng));
        let mut vn = v;
        vn.corners = [0, 1, 2, 3].map(|k| v.corners[k] + Vector2::new(e[2 * k], e[2 * k + 1]));
        let c = solve_tag(&[vn], 30.0, Some(&tag), Some(0.1)).expect("solves").centre_mm - tag.translation;
        for (axis, sum) in scatter.iter_mut().enumerate() {
            *sum += (tag.rotation * Vector3::ith(axis, 1.0)).dot(&c).powi(2) / runs as f64;
        }
    }
    for (axis, scatter) in scatter.iter().enumerate() {
        let a: Vector3<f64> = tag.rotation * Vector3::ith(axis, 1.0);
        let var = |m: &Matrix6<f64>| (a.transpose() * m.fixed_view::<3, 3>(3, 3) * a)[(0, 0)];
        let (with, plain) = (scatter / var(&correlated), scatter / var(&(h_inv * s2)));
        println!("tag axis {axis}: scatter / correlated {with:.3}, scatter / independent {plain:.3}");
        // 2000 runs: the scatter's relative standard error is 3 %; the independent corners give 0.88.
        assert!((0.93..=1.07).contains(&with), "tag axis {axis}: scatter / correlated covariance {with:.3}");
    }
}

/// Each view's edges offset along their normals (both corners of an edge alike; variance `q`
/// per edge, independent from edge to edge): the centre's scatter over runs is the
/// covariance [`common_shift_covariance`] gives, and the views' edge-offset residuals keep
/// the share [`ViewShift::residual_share`] says.
#[test]
fn offsets_of_each_views_edges_give_the_centres_scatter() {
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};
    let tag = Pose::from_rvec_tvec([1.5, 0.2, -0.1], [40.0, 0.0, 10.0]);
    let corners = tag_corners(30.0);
    let views: Vec<TagView> = [[1.5, 0.1, 0.05], [1.45, 0.45, 0.1], [1.55, -0.35, 0.0]]
        .iter()
        .map(|r| {
            let mut v = view();
            v.camera_pose = Pose::from_rvec_tvec(*r, [20.0, -30.0, 1500.0]);
            v.corners = [0, 1, 2, 3].map(|k| v.intrinsics.project(&v.camera_pose.transform(&tag.transform(&corners[k]))).unwrap());
            v
        })
        .collect();
    // The shifts at the true pose (what a noiseless solve finds), from the edges' Jacobians
    // directly: a solve hands them over only with the corners' correlation switched on.
    let problem = TagProblem { views: views.iter().enumerate().collect(), corners: tag_corners(30.0) };
    let h_inv = problem.evaluate(&tag, true).expect("in front").jtj.try_inverse().expect("regular");
    let shifts = shift::view_shifts(&edge_jacobians(&problem, &tag), &h_inv);
    let q = 0.01;
    let predicted = common_shift_covariance(&shifts, |_| q);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
    let normal = Normal::new(0.0, q.sqrt()).unwrap();
    let runs = 2000;
    let (mut scatter, mut mean_sq) = (Matrix3::zeros(), [0.0; 3]);
    for _ in 0..runs {
        let shifted: Vec<TagView> = views
            .iter()
            .map(|v| {
                let n = edge_normals(&v.corners);
                let d: [f64; 4] = std::array::from_fn(|_| normal.sample(&mut rng));
                TagView { corners: std::array::from_fn(|k| v.corners[k] + n[k] * d[k] + n[(k + 3) % 4] * d[(k + 3) % 4]), ..*v }
            })
            .collect();
        // A pooled noise above the shifts: no view is taken for an outlier.
        let s = solve_tag(&shifted, 30.0, Some(&tag), Some(1.0)).expect("solves");
        assert!(s.rejected_views.is_empty());
        let c = s.centre_mm - tag.translation;
        scatter += c * c.transpose() / runs as f64;
        for (i, v) in shifted.iter().enumerate() {
            let r = corner_residuals_px(v, &s.tag_to_world, 30.0).unwrap();
            let n = edge_normals(&views[i].corners);
            mean_sq[i] += (0..4).map(|e| (n[e].dot(&(r[e] + r[(e + 1) % 4])) / 2.0).powi(2)).sum::<f64>() / runs as f64;
        }
    }
    let ratios: Vec<f64> = (0..3).map(|axis| scatter[(axis, axis)] / predicted[(axis, axis)]).collect();
    let shares: Vec<f64> = shifts.iter().enumerate().map(|(i, s)| mean_sq[i] / (4.0 * q * s.residual_share)).collect();
    println!(
        "centre scatter / predicted by axis {ratios:.3?}; views' mean residual / predicted {shares:.3?}, shares {:.3?}",
        shifts.iter().map(|s| s.residual_share).collect::<Vec<_>>()
    );
    for r in ratios.iter().chain(&shares) {
        assert!((0.9..=1.1).contains(r), "scatter / predicted {r:.3}");
    }
}
