use super::*;
use crate::refine::profile::tests::{gauss, uniform};

/// A pixel's value by brute force: `n` points of its aperture, each seeing the edge's light
/// through a Gaussian offset drawn from `Σ` (white where the displaced point lies on the
/// edge's white side).
fn response_sampled(light: &Light, normal: &Vector2<f64>, t: f64, n: usize, seed: &mut u64) -> f64 {
    let (sx, sy, r, w) = (light.sigma_x_px, light.sigma_y_px, light.corr, light.width_px);
    let mut white = 0usize;
    for _ in 0..n {
        let u = Vector2::new((uniform(seed) - 0.5) * w, (uniform(seed) - 0.5) * w);
        let (z1, z2) = (gauss(seed), gauss(seed));
        // Σ's Cholesky factor: x = sx z1, y = sy (r z1 + √(1 − r²) z2).
        let g = Vector2::new(sx * z1, sy * (r * z1 + (1.0 - r * r).sqrt() * z2));
        white += usize::from(normal.dot(&(u + g)) + t > 0.0);
    }
    white as f64 / n as f64
}

#[test]
fn a_pixels_response_matches_brute_force_sub_sampling_of_a_blurred_edge() {
    let mut seed = 0x2545_f491_4f6c_dd1d_u64;
    let n = 400_000;
    let lights = [
        Light { sigma_x_px: 0.7, sigma_y_px: 0.7, corr: 0.0, width_px: 1.0 },
        Light { sigma_x_px: 0.9, sigma_y_px: 0.4, corr: 0.5, width_px: 1.0 },
        Light { sigma_x_px: 0.0, sigma_y_px: 0.0, corr: 0.0, width_px: 0.707 },
        Light { sigma_x_px: 0.3, sigma_y_px: 0.5, corr: -0.3, width_px: 0.6 },
        Light { sigma_x_px: 0.15, sigma_y_px: 0.15, corr: 0.0, width_px: 0.9 },
    ];
    let mut worst = 0.0f64;
    for light in lights {
        for deg in [0.0f64, 0.02, 3.0, 17.0, 45.0, 71.0] {
            let normal = Vector2::new(deg.to_radians().sin(), deg.to_radians().cos());
            let (a, b) = light.widths(&normal);
            let sigma = light.sigma_across(&normal);
            for t in [-1.1, -0.45, -0.2, 0.0, 0.13, 0.38, 0.9] {
                let model = response(t, a, b, sigma).0;
                let sampled = response_sampled(&light, &normal, t, n, &mut seed);
                // The sampling's standard error is ≤ 0.5/√n = 0.0008.
                assert!((model - sampled).abs() < 0.004, "{light:?} at {deg}°, t {t}: {model} against {sampled}");
                worst = worst.max((model - sampled).abs());
            }
        }
    }
    println!("worst difference from sampling: {worst:.5}");
}

#[test]
fn the_responses_slope_matches_finite_differences() {
    for (a, b, sigma) in [(1.0, 0.0, 0.5), (0.9, 0.2, 0.4), (0.7, 0.0005, 0.3), (0.8, 0.3, 0.0), (0.6, 0.5, 1.2), (1.0, 0.05, 0.021)] {
        for t in [-1.3, -0.5, -0.1, 0.0, 0.24, 0.6, 1.5] {
            let h = 1e-6;
            let fd = (response(t + h, a, b, sigma).0 - response(t - h, a, b, sigma).0) / (2.0 * h);
            let slope = response(t, a, b, sigma).1;
            assert!((slope - fd).abs() < 1e-4, "({a}, {b}, {sigma}) at {t}: {slope} against {fd}");
        }
    }
    // Continuous where the form changes: one uniform below b = 1e-3, the area at σ → 0.
    let (v1, v2) = (response(0.2, 0.8, 0.00099, 0.4).0, response(0.2, 0.8, 0.00101, 0.4).0);
    assert!((v1 - v2).abs() < 1e-6, "{v1} against {v2}");
    let (v1, v2) = (response(0.2, 0.8, 0.3, 0.0199).0, response(0.2, 0.8, 0.3, 0.0201).0);
    assert!((v1 - v2).abs() < 2e-3, "{v1} against {v2}");
}

/// A learner holding edges of the formation `light` (no kernel after the pixel) at many
/// angles and phases, each pixel's value with noise of `noise` of the contrast.
fn learner_of(light: &Light, edges: usize, noise: f64, seed: u64) -> FormationLearner {
    let mut learner = FormationLearner::default();
    let mut seed = seed;
    for e in 0..edges {
        let tilt = if e % 5 == 4 { 5.0 + 35.0 * uniform(&mut seed) } else { 4.0 * (uniform(&mut seed) - 0.5) };
        let deg = tilt + 90.0 * (e % 2) as f64 + 180.0 * ((e / 2) % 2) as f64;
        let normal = Vector2::new(deg.to_radians().sin(), deg.to_radians().cos());
        let c = uniform(&mut seed);
        let (a, b) = light.widths(&normal);
        let sigma = light.sigma_across(&normal);
        for y in -8..=8 {
            for x in -8..=8 {
                let d = normal.x * x as f64 + normal.y * y as f64 - c;
                if d.abs() < 2.9 {
                    let v = response(d, a, b, sigma).0 + noise * gauss(&mut seed);
                    learner.push(((x & 1) + 2 * (y & 1)) as usize, &normal, d, v, 0);
                }
            }
        }
        learner.close_edge();
    }
    learner
}

#[test]
fn a_known_formations_light_is_recovered_from_its_edges() {
    for (light, noise) in [
        (Light { sigma_x_px: 0.7, sigma_y_px: 0.7, corr: 0.0, width_px: 1.0 }, 0.01),
        (Light { sigma_x_px: 0.6, sigma_y_px: 0.3, corr: 0.4, width_px: 1.0 }, 0.01),
        (Light { sigma_x_px: 0.0, sigma_y_px: 0.0, corr: 0.0, width_px: 0.707 }, 0.01),
    ] {
        let learner = learner_of(&light, 160, noise, 17);
        let (found, _) = learner.search(false, None).expect("samples enough");
        println!("true {light:?}\nfound {found:?}");
        for deg in [0.0f64, 90.0, 30.0, 120.0] {
            let n = Vector2::new(deg.to_radians().sin(), deg.to_radians().cos());
            let (want, got) = (light.sigma_across(&n), found.sigma_across(&n));
            assert!((want - got).abs() < 0.05, "σ across {deg}°: {got} against {want}");
        }
        assert!((found.width_px - light.width_px).abs() < 0.06, "width {} against {}", found.width_px, light.width_px);
        let kernel = learner.kernel_of(&found, Some(false), None).expect("a kernel");
        let k = kernel.site(0);
        assert!((k[TAPS / 2] - 1.0).abs() < 0.1, "the kernel after the pixel stays near the identity: {k:?}");
    }
}

#[test]
fn the_formation_is_taken_over_the_profile_where_it_predicts_held_out_edges_better() {
    // An astigmatic blur: the spread changes with the edge's angle, which the profile's
    // classes (two orientations) do not hold for the tilted edges.
    let light = Light { sigma_x_px: 0.9, sigma_y_px: 0.3, corr: 0.5, width_px: 1.0 };
    let mut learner = learner_of(&light, 160, 0.01, 23);
    let kernel = learner.solve(false).expect("the formation predicts held-out edges better");
    let found = kernel.light().expect("with its light");
    let n = Vector2::new(30f64.to_radians().sin(), 30f64.to_radians().cos());
    assert!((found.sigma_across(&n) - light.sigma_across(&n)).abs() < 0.05, "{found:?}");
    // Too few samples: no formation (the profile is kept).
    assert!(learner_of(&light, 10, 0.01, 23).solve(false).is_none());
}
