//! Virtual gauges, the clock check and the simulator's real tests (issue "Gauges and the
//! test report", items 1–3): `[[gauge]]` validation, each gauge kind on synthetic tag poses
//! with known answers, σ honest against Monte Carlo and against simulated truth, the
//! softening four-point test and the notched three-point test rendered and replayed with
//! gauges matching truth, the UTM clock offset recovered.

use std::collections::BTreeMap;
use std::path::Path;

use nalgebra::{Matrix6, Rotation3, Unit, Vector3, Vector6};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};

use crate::common::*;
use tagdeflect::config::{Config, SpecimenConfig, SpecimenTag, TagRole};
use tagdeflect_core::camera::Pose;
use tagdeflect_core::feed::FeedLine;
use tagdeflect_core::tags::TagFamily;
use tagdeflect_estimate::clock_offset::{estimate_from_feed, estimate_from_utm};
use tagdeflect_estimate::gauges::{GaugeConfig, GaugeKind, GaugeTag, Gauges};
use tagdeflect_estimate::lm::retract;
use tagdeflect_io::recording::read_jsonl_file;
use tagdeflect_sim::{LoadLaw, SimParams, SimRig, SimTest, SimTruthLine, SIM_TRUTH_FILE};

// ---------------------------------------------------------------------------------------
// Config validation.

fn base_config() -> String {
    let p = SimParams { cameras: 1, width: 320, height: 240, frame_sets: 2, ..SimParams::default() };
    tagdeflect::config::Config::from_sim(&SimRig::new(&p).unwrap()).to_toml_string()
}

fn load_with(gauges: &str) -> Result<Config, String> {
    let text = format!("{}\n{gauges}", base_config());
    Config::from_toml_str(&text, Path::new("/etc/rig.toml")).map_err(|e| e.to_string())
}

#[test]
fn gauge_config_errors_name_file_line_and_key() {
    let ok = load_with(
        r#"
[[gauge]]
name = "net"
kind = "net_deflection"

[[gauge]]
name = "cmod"
kind = "opening"
tags = [3, 4]
direction = [2.0, 0.0, 0.0]
at_mm = [0.0, 0.0, 0.0]

[[gauge]]
name = "ext"
kind = "distance"
tags = [1, 2]
gauge_length_mm = 450.0

[[gauge]]
name = "slope_left"
kind = "rotation"
tags = [1]
axis = [0.0, 1.0, 0.0]

[[gauge]]
name = "curv"
kind = "curvature"
tags = [1, 0, 2]
"#,
    )
    .expect("valid gauges");
    assert_eq!(ok.gauges.len(), 5);
    assert_eq!(ok.gauges[1].direction, Some([1.0, 0.0, 0.0]), "directions are normalised");
    // Written back into a recording's config and read again: the same.
    let again = Config::from_toml_str(&ok.to_toml_string(), Path::new("/r/tagdeflect.toml")).unwrap();
    assert_eq!(again.gauges, ok.gauges);

    let base_lines = base_config().lines().count() + 1;
    let cases: &[(&str, &str, &str)] = &[
        ("name = \"a\"\nkind = \"distance\"\ntags = [1, 99]", "gauge[0].tags", "tag 99 is not a [[specimen.tag]] id"),
        ("name = \"a\"\nkind = \"distance\"\ntags = [1]", "gauge[0].tags", "uses 2 specimen tags, got 1"),
        ("name = \"a\"\nkind = \"curvature\"\ntags = [1, 2]", "gauge[0].tags", "uses 3 specimen tags"),
        ("name = \"a\"\nkind = \"rotation\"\ntags = [1, 2]\naxis = [0.0, 1.0, 0.0]", "gauge[0].tags", "uses 1 specimen tag,"),
        ("name = \"a\"\nkind = \"opening\"\ntags = [3, 4]\ndirection = [0.0, 0.0, 0.0]", "gauge[0].direction", "non-zero direction"),
        ("name = \"a\"\nkind = \"opening\"\ntags = [3, 4]", "gauge[0].direction", "needs `direction"),
        ("name = \"a\"\nkind = \"rotation\"\ntags = [1]", "gauge[0].axis", "needs `axis"),
        ("name = \"a\"\nkind = \"rotation\"\ntags = [1]\ndirection = [0.0, 1.0, 0.0]", "gauge[0].direction", "takes `axis"),
        ("name = \"a\"\nkind = \"clip\"\ntags = [1]", "gauge[0].kind", "not a gauge kind"),
        ("name = \"a b\"\nkind = \"rotation\"\ntags = [1]\naxis = [0.0, 1.0, 0.0]", "gauge[0].name", "letters, digits"),
        ("name = \"a\"\nkind = \"opening\"\ntags = [3, 3]\ndirection = [1.0, 0.0, 0.0]", "gauge[0].tags", "listed twice"),
        (
            "name = \"a\"\nkind = \"opening\"\ntags = [3, 4]\ndirection = [1.0, 0.0, 0.0]\ngauge_length_mm = 5.0",
            "gauge[0].gauge_length_mm",
            "not used by",
        ),
        ("name = \"a\"\nkind = \"distance\"\ntags = [1, 2]\ngauge_length_mm = 0.0", "gauge[0].gauge_length_mm", "positive length"),
        ("name = \"a\"\nkind = \"net_deflection\"\ntags = [0, 3]", "gauge[0].tags", "role = \"support\""),
        ("name = \"a\"\nkind = \"distance\"\ntags = [1, 2]\ncolour = 3", "colour", "unknown field"),
    ];
    for (body, key, message) in cases {
        let e = load_with(&format!("[[gauge]]\n{body}\n")).expect_err(body);
        assert!(e.starts_with("/etc/rig.toml:"), "{e}");
        assert!(e.contains(&format!("`{key}`")), "key {key} in: {e}");
        assert!(e.contains(message), "\"{message}\" in: {e}");
        let line: usize = e.split(':').nth(1).and_then(|l| l.parse().ok()).unwrap_or_else(|| panic!("a line in {e}"));
        assert!(line >= base_lines && line <= base_lines + 7, "line {line} (gauge starts at {base_lines}): {e}");
    }
    let e =
        load_with("[[gauge]]\nname = \"a\"\nkind = \"net_deflection\"\n[[gauge]]\nname = \"a\"\nkind = \"net_deflection\"\n").unwrap_err();
    assert!(e.contains("`gauge[1].name`") && e.contains("duplicate gauge name \"a\""), "{e}");
    assert!(e.contains(&format!(":{}:", base_lines + 5)), "the second name's line: {e}");

    // [specimen.beam] and [clock_check].
    let text = base_config().replace("[specimen]\n", "[specimen.beam]\nwidth_mm = 150.0\ndepth_mm = 150.0\nspan_mm = 0.0\n\n[specimen]\n");
    let e = Config::from_toml_str(&text, Path::new("/etc/rig.toml")).unwrap_err().to_string();
    assert!(e.contains("`specimen.beam.span_mm`") && e.contains("positive length"), "{e}");
    let text = format!("{}\n[clock_check]\nwarn_ms = -1.0\n", base_config());
    let e = Config::from_toml_str(&text, Path::new("/etc/rig.toml")).unwrap_err().to_string();
    assert!(e.contains("`clock_check.warn_ms`"), "{e}");
}

// ---------------------------------------------------------------------------------------
// Each kind on synthetic tag poses with known answers.

fn specimen(roles: &[(u32, Option<TagRole>)]) -> SpecimenConfig {
    SpecimenConfig {
        family: TagFamily::Tag36h11,
        size_mm: 30.0,
        tags: roles.iter().map(|&(id, role)| SpecimenTag { id, role }).collect(),
        beam: None,
    }
}

/// A tag on a face with outward normal `normal` (tag z), at `centre`.
fn face_pose(centre: [f64; 3], normal: Vector3<f64>) -> Pose {
    let z = normal.normalize();
    let y = Vector3::z();
    let x = y.cross(&z);
    let r = Rotation3::from_matrix_unchecked(nalgebra::Matrix3::from_columns(&[x, y, z]));
    Pose { rotation: r, translation: Vector3::from(centre) }
}

fn gauge(name: &str, kind: GaugeKind, tags: &[u32]) -> GaugeConfig {
    GaugeConfig { name: name.into(), kind, tags: tags.to_vec(), direction: None, axis: None, gauge_length_mm: None, at_mm: None }
}

fn moved(p: &Pose, dx: [f64; 3]) -> Pose {
    Pose { rotation: p.rotation, translation: p.translation + Vector3::from(dx) }
}

fn turned(p: &Pose, about: Vector3<f64>, axis: Vector3<f64>, angle: f64) -> Pose {
    let r = Rotation3::from_axis_angle(&Unit::new_normalize(axis), angle);
    Pose { rotation: r * p.rotation, translation: r * (p.translation - about) + about }
}

fn iso(sigma_mm: f64, sigma_rad: f64) -> Matrix6<f64> {
    Matrix6::from_diagonal(&Vector6::new(
        sigma_rad.powi(2),
        sigma_rad.powi(2),
        sigma_rad.powi(2),
        sigma_mm.powi(2),
        sigma_mm.powi(2),
        sigma_mm.powi(2),
    ))
}

#[test]
fn each_gauge_kind_gives_the_known_answer() {
    let front = -Vector3::y();
    let back = Vector3::y();
    let sp = specimen(&[
        (0, Some(TagRole::Midspan)),
        (1, Some(TagRole::Support)),
        (2, Some(TagRole::Support)),
        (3, None),
        (4, None),
        (10, Some(TagRole::Midspan)),
        (11, Some(TagRole::Support)),
        (12, Some(TagRole::Support)),
    ]);
    let rest: BTreeMap<u32, Pose> = [
        (0, face_pose([0.0, 0.0, 75.0], front)),
        (1, face_pose([-200.0, 0.0, 75.0], front)),
        (2, face_pose([250.0, 0.0, 75.0], front)),
        (3, face_pose([-20.0, 0.0, 20.0], front)),
        (4, face_pose([20.0, 0.0, 20.0], front)),
        (10, face_pose([0.0, 150.0, 75.0], back)),
        (11, face_pose([-200.0, 150.0, 75.0], back)),
        (12, face_pose([250.0, 150.0, 75.0], back)),
    ]
    .into_iter()
    .collect();
    let sigma = 0.01;
    let as_tags = |poses: &BTreeMap<u32, Pose>| -> Vec<GaugeTag> {
        poses.iter().map(|(id, p)| GaugeTag { id: *id, pose: *p, covariance: iso(sigma, 1e-4) }).collect()
    };
    let hinge = Vector3::new(0.0, 0.0, 110.0);
    let phi = 0.004;
    let mut now = rest.clone();
    // Front: supports down 0.1 (x = −200) and 0.55 (x = 250): the line at x = 0 is at 0.3;
    // midspan down 2.3 → 2.0. Back: supports 0, midspan 2.2 → 2.2. Mean 2.1.
    now.insert(0, moved(&rest[&0], [0.4, 0.0, -2.3]));
    now.insert(1, moved(&rest[&1], [0.0, 0.0, -0.1]));
    now.insert(2, turned(&moved(&rest[&2], [0.0, 0.0, -0.55]), rest[&2].translation, Vector3::y(), 0.01));
    now.insert(10, moved(&rest[&10], [0.0, 0.0, -2.2]));
    // The halves across the notch turn by ∓φ about the crack tip at 110 mm.
    now.insert(3, turned(&rest[&3], hinge, Vector3::y(), phi));
    now.insert(4, turned(&rest[&4], hinge, Vector3::y(), -phi));
    let configs = vec![
        gauge("net", GaugeKind::NetDeflection, &[]),
        gauge("net_front", GaugeKind::NetDeflection, &[0, 1, 2]),
        GaugeConfig { direction: Some([1.0, 0.0, 0.0]), at_mm: Some([0.0, 0.0, 0.0]), ..gauge("cmod", GaugeKind::Opening, &[3, 4]) },
        GaugeConfig { direction: Some([-1.0, 0.0, 0.0]), ..gauge("open_at_tags", GaugeKind::Opening, &[3, 4]) },
        gauge("dist", GaugeKind::Distance, &[1, 2]),
        GaugeConfig { gauge_length_mm: Some(100.0), ..gauge("dist100", GaugeKind::Distance, &[1, 2]) },
        GaugeConfig { axis: Some([0.0, 1.0, 0.0]), ..gauge("rot", GaugeKind::Rotation, &[2]) },
        gauge("curv", GaugeKind::Curvature, &[1, 0, 2]),
    ];
    let mut g = Gauges::new(&configs, [0.0, 0.0, 1.0], &sp);
    let first = g.evaluate(&as_tags(&rest));
    for (name, r) in &first {
        assert!(r.value.abs() < 1e-9, "{name} is zero at the reference: {r:?}");
        assert!(r.sigma <= 1e-3, "{name}: the reference frame set is exact relative to itself (σ at the unit's resolution): {r:?}");
    }
    let out = g.evaluate(&as_tags(&now));
    println!("gauges: {out:#?}");
    let v = |k: &str| out.get(k).unwrap_or_else(|| panic!("{k} missing")).value;
    assert!((v("net_front") - 2.0).abs() < 2e-5, "{}", v("net_front"));
    assert!((v("net") - 2.1).abs() < 2e-5, "both faces averaged: {}", v("net"));
    // Mouth at z = 0, 110 mm below the tip: opening 2 · 110 · sin φ; at the tags (20 mm up): 2 · 90 · sin φ.
    assert!((v("cmod") - 220.0 * phi.sin()).abs() < 1e-4, "{}", v("cmod"));
    assert!((v("open_at_tags") - 180.0 * phi.sin()).abs() < 1e-3, "direction sign does not matter: {}", v("open_at_tags"));
    let p1 = now[&1].translation;
    let p2 = now[&2].translation;
    let change = (p2 - p1).norm() - 450.0;
    assert!((v("dist") - change).abs() < 2e-5, "{} vs {change}", v("dist"));
    assert_eq!(out["dist.strain"].unit, "µε");
    assert!((v("dist.strain") - change / 450.0 * 1e6).abs() < 0.01);
    assert!((v("dist100.strain") - change / 100.0 * 1e6).abs() < 0.01);
    assert_eq!(out["rot"].unit, "mrad");
    assert!((v("rot") - 10.0).abs() < 1e-4, "{}", v("rot"));
    // Curvature through s = −200, 0, 250 with upward displacements −0.1, −2.3, −0.55.
    let up = |k: u32| now[&k].translation.z - rest[&k].translation.z;
    let (ya, yb, yc) = (up(1), up(0), up(2));
    let k = 2.0 * ((yc - yb) / 250.0 - (yb - ya) / 200.0) / 450.0 * 1e6;
    assert_eq!(out["curv"].unit, "1/km");
    assert!((v("curv") - k).abs() < 1e-3, "{} vs {k}", v("curv"));

    // σ: net_front = mid − (w₁ s₁ + w₂ s₂) with line weights at x = 0 of 250/450 and 200/450;
    // each tag's vertical σ now (the reference counts as exact).
    let (w1, w2): (f64, f64) = (250.0 / 450.0, 200.0 / 450.0);
    let expect = sigma * (1.0 + w1 * w1 + w2 * w2).sqrt();
    assert!((out["net_front"].sigma - expect).abs() < 2e-5, "{} vs {expect}", out["net_front"].sigma);
    // A rotation counts its reference set's noise too and the turn of the corners' edge
    // lines: 1.5 × (σ_now² + σ_ref²).
    let expect_rot = (1.5f64 * 2.0).sqrt() * 1e-4 * 1e3;
    assert!((out["rot"].sigma - expect_rot).abs() < 1e-4, "{} vs {expect_rot}", out["rot"].sigma);

    // A gauge whose tag is not solved is absent (never interpolated).
    let without: Vec<GaugeTag> = as_tags(&now).into_iter().filter(|t| t.id != 4 && t.id != 2).collect();
    let out = g.evaluate(&without);
    assert!(!out.contains_key("cmod") && !out.contains_key("dist") && !out.contains_key("rot") && !out.contains_key("curv"), "{out:?}");
    assert!(out.contains_key("net_front"), "net deflection from the supports and midspan still seen");
}

/// σ from linearised propagation against Monte Carlo: noisy poses drawn from their
/// covariance, ≈ 95 % of the gauges' errors within 2σ.
#[test]
fn gauge_sigma_matches_monte_carlo() {
    let sp = specimen(&[(0, Some(TagRole::Midspan)), (1, Some(TagRole::Support)), (2, Some(TagRole::Support)), (3, None), (4, None)]);
    let front = -Vector3::y();
    let rest: Vec<(u32, Pose)> = vec![
        (0, face_pose([0.0, 0.0, 75.0], front)),
        (1, face_pose([-225.0, 0.0, 75.0], front)),
        (2, face_pose([225.0, 0.0, 75.0], front)),
        (3, face_pose([-23.0, 0.0, 21.0], front)),
        (4, face_pose([23.0, 0.0, 21.0], front)),
    ];
    let hinge = Vector3::new(0.0, 0.0, 100.0);
    let now: Vec<(u32, Pose)> = rest
        .iter()
        .map(|(id, p)| {
            let q = match id {
                0 => moved(p, [0.0, 0.0, -3.0]),
                3 => turned(p, hinge, Vector3::y(), 0.01),
                4 => turned(p, hinge, Vector3::y(), -0.01),
                _ => turned(p, p.translation, Vector3::y(), if *id == 1 { -0.01 } else { 0.01 }),
            };
            (*id, q)
        })
        .collect();
    let configs = vec![
        gauge("net", GaugeKind::NetDeflection, &[]),
        GaugeConfig { direction: Some([1.0, 0.0, 0.0]), at_mm: Some([0.0, 0.0, 0.0]), ..gauge("cmod", GaugeKind::Opening, &[3, 4]) },
        gauge("dist", GaugeKind::Distance, &[1, 2]),
        GaugeConfig { axis: Some([0.0, 1.0, 0.0]), ..gauge("rot", GaugeKind::Rotation, &[1]) },
        gauge("curv", GaugeKind::Curvature, &[1, 0, 2]),
    ];
    // Anisotropic, correlated covariance (a tag's depth is worse; rotation and position couple).
    let mut cov = Matrix6::<f64>::zeros();
    let l = nalgebra::Matrix6::<f64>::from_fn(|i, j| {
        if i < j {
            0.0
        } else if i == j {
            [2e-4, 1e-4, 3e-4, 0.004, 0.02, 0.006][i]
        } else {
            0.3 * [2e-4, 1e-4, 3e-4, 0.004, 0.02, 0.006][j]
        }
    });
    cov += l * l.transpose();
    let exact = |poses: &[(u32, Pose)]| poses.iter().map(|(id, p)| GaugeTag::exact(*id, *p)).collect::<Vec<_>>();
    let mut truth_g = Gauges::new(&configs, [0.0, 0.0, 1.0], &sp);
    truth_g.evaluate(&exact(&rest));
    let truth = truth_g.evaluate(&exact(&now));
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let mut noisy = |poses: &[(u32, Pose)]| -> Vec<GaugeTag> {
        poses
            .iter()
            .map(|(id, p)| {
                let z = Vector6::from_fn(|_, _| StandardNormal.sample(&mut rng));
                GaugeTag { id: *id, pose: retract(p, &(l * z)), covariance: cov }
            })
            .collect()
    };
    let mut within: BTreeMap<String, (usize, usize)> = BTreeMap::new();
    for _ in 0..400 {
        // The reference is taken as exact (see `solve::gauges`): the noise is in the present poses.
        let mut g = Gauges::new(&configs, [0.0, 0.0, 1.0], &sp);
        g.evaluate(&exact(&rest));
        for (name, r) in g.evaluate(&noisy(&now)) {
            let e = within.entry(name.clone()).or_default();
            e.1 += 1;
            // A rotation's σ holds 1.5 × the variance the pose covariance gives (the turn of
            // a tag's edge lines, which poses drawn from that covariance do not carry).
            let sigma = if name == "rot" { r.sigma / 1.5f64.sqrt() } else { r.sigma };
            if (r.value - truth[&name].value).abs() <= 2.0 * sigma {
                e.0 += 1;
            }
        }
    }
    for (name, (ok, n)) in &within {
        let f = *ok as f64 / *n as f64;
        println!("GAUGE σ Monte Carlo {name}: {:.1} % within 2σ", 100.0 * f);
        assert!((0.92..=0.98).contains(&f), "{name}: {:.1} % within 2σ", 100.0 * f);
    }
    assert_eq!(within.len(), 6, "net, cmod, dist, dist.strain, rot, curv");
}

// ---------------------------------------------------------------------------------------
// Simulated tests: rendered, replayed, compared with truth.

struct Compared {
    /// Per gauge: errors (feed − truth) and σ.
    errors: BTreeMap<String, Vec<(f64, f64)>>,
}

impl Compared {
    fn rms(&self, name: &str) -> f64 {
        let e = &self.errors[name];
        (e.iter().map(|(x, _)| x * x).sum::<f64>() / e.len() as f64).sqrt()
    }
    fn max(&self, name: &str) -> f64 {
        self.errors[name].iter().map(|(x, _)| x.abs()).fold(0.0, f64::max)
    }
    /// RMS of error / σ (1 when σ is exactly right).
    fn z_rms(&self) -> f64 {
        let all: Vec<&(f64, f64)> = self.errors.values().flatten().collect();
        (all.iter().map(|(e, s)| (e / s).powi(2)).sum::<f64>() / all.len() as f64).sqrt()
    }
    fn within_2sigma(&self) -> (usize, usize) {
        let all: Vec<&(f64, f64)> = self.errors.values().flatten().collect();
        (all.iter().filter(|(e, s)| e.abs() <= 2.0 * s).count(), all.len())
    }
}

/// Feed gauges against the rig's true gauges at each line's time.
fn compare(rig: &SimRig, lines: &[FeedLine]) -> Compared {
    let mut errors: BTreeMap<String, Vec<(f64, f64)>> = BTreeMap::new();
    for l in lines {
        let truth = rig.gauge_truth(rig.midspan_deflection(l.t_ns));
        for (name, r) in &l.gauges {
            let t = truth.get(name).unwrap_or_else(|| panic!("no truth for gauge {name}"));
            errors.entry(name.clone()).or_default().push((r.value - t, r.sigma));
        }
    }
    Compared { errors }
}

fn real_test(test: SimTest, law: LoadLaw, offset_ms: f64, seed: u64) -> SimParams {
    SimParams {
        cameras: 3,
        width: 1280,
        height: 960,
        frame_sets: 16,
        rest_frames: 3,
        test,
        load_law: law,
        span_mm: if test == SimTest::ThreePointNotched { 500.0 } else { 450.0 },
        stiffness_kn_per_mm: 100.0,
        max_deflection_mm: 4.0,
        utm_clock_offset_ms: offset_ms,
        seed,
        ..SimParams::default()
    }
}

#[test]
fn softening_four_point_test_replays_with_gauges_and_clock_offset() {
    let dir = tempfile::tempdir().unwrap();
    // The clock is read on the elastic ramp before the first crack: crack at 1.6 of 4 mm.
    let p = SimParams {
        frame_sets: 24,
        rest_frames: 5,
        crack_deflection_mm: 1.6,
        ..real_test(SimTest::FourPoint, LoadLaw::Softening, 80.0, 61)
    };
    let rec = simulate(dir.path(), "soft", &p);
    // The live check's first estimate after 8 lines, then every 4 (defaults: 20, 10).
    let toml = rec.join("tagdeflect.toml");
    let text = std::fs::read_to_string(&toml).unwrap() + "\n[clock_check]\nmin_points = 8\nevery_lines = 4\n";
    std::fs::write(&toml, text).unwrap();
    let rig = SimRig::new(&p).unwrap();
    let (recording, lines, _) = replay_lines(&rec, false);
    feedcheck(&lines, &rec.join("tagdeflect.toml"));
    assert_eq!(lines.len(), 24);
    assert!(recording.config.specimen.beam.is_some(), "[specimen.beam] written");

    // The load follows the law, not the deflection: up to the crack, drop, softening.
    let truth: Vec<SimTruthLine> = read_jsonl_file(&rec.join(SIM_TRUTH_FILE)).unwrap();
    let peak = recording.utm.iter().map(|s| s.load_kn).fold(0.0, f64::max);
    let last = truth.last().unwrap();
    // First-crack load k δc = 160 kN; the 50 Hz samples step by 2.2 mm/s × 20 ms × 100 kN/mm.
    assert!(peak <= 160.0 + 1e-9 && peak > 160.0 - 4.5, "first-crack load ≈ k δc = 160 kN (50 Hz UTM samples): {peak}");
    assert!(
        last.load_kn < 0.6 * peak && last.midspan_deflection_mm > 3.9,
        "softened: {} kN at {} mm",
        last.load_kn,
        last.midspan_deflection_mm
    );
    assert!(last.gauges.contains_key("net") && last.gauges.contains_key("curv") && last.gauges.contains_key("rot1"));

    let c = compare(&rig, &lines);
    for name in ["net", "curv", "rot1"] {
        println!(
            "GAUGES softening 4-point {name}: RMS {:.5}, max {:.5} {} over {} lines",
            c.rms(name),
            c.max(name),
            lines[5].gauges[name].unit,
            c.errors[name].len()
        );
        assert_eq!(c.errors[name].len(), lines.len(), "{name} in every line");
    }
    // Floors ~1.4 × the worst of three runs on this seed (2026-12-06, load 14–20 on 2 cores:
    // net 0.00119 mm, curvature 0.0336 1/km, the end rotation 0.228 mrad — every run the same
    // figures); the rotation's floor stays at 1.3 ×: most of its error is the reference set's,
    // common to every line — see `ROTATION_VARIANCE_FACTOR`. docs/accuracy.md.
    assert!(c.rms("net") <= 0.0017, "net deflection RMS {} mm", c.rms("net"));
    assert!(c.rms("rot1") <= 0.30, "end rotation RMS {} mrad", c.rms("rot1"));
    assert!(c.rms("curv") <= 0.047, "curvature RMS {} 1/km", c.rms("curv"));
    let (ok, n) = c.within_2sigma();
    println!("GAUGES softening 4-point: {ok} of {n} errors within 2σ, RMS error/σ {:.2}", c.z_rms());
    // σ honest both ways (measured 65 of 72, RMS error/σ 1.20, 2026-12-06; a doubled σ gives 0.60,
    // under the 0.75 asserted).
    assert!(ok as f64 >= 0.85 * n as f64, "σ honest: {ok} of {n} within 2σ");
    assert!((0.75..=1.3).contains(&c.z_rms()), "RMS error/σ {:.3}", c.z_rms());

    // Clock: the UTM is stamped 80 ms ahead.
    let from_utm = estimate_from_utm(&lines, &recording.utm, 1000.0);
    let from_feed = estimate_from_feed(&lines, 1000.0);
    let live = lines.iter().rev().find_map(|l| l.clock_offset_ms);
    println!("CLOCK 80 ms: from utm.jsonl {from_utm:?}; from the feed {from_feed:?}; live {live:?}");
    let (from_utm, from_feed, live) = (from_utm.expect("from utm.jsonl"), from_feed.expect("from the feed"), live.expect("live"));
    // σ covers the deflection's noise; the stroke between UTM samples is interpolated
    // linearly, which rounds the kink at the ramp's start: up to a quarter of the sampling
    // period (5 ms at 50 Hz; 25 ms between the feed's lines at 10 Hz) on top.
    assert!((from_utm.offset_ms - 80.0).abs() <= 3.0 * from_utm.sigma_ms + 5.0, "{from_utm:?}");
    assert!((live.value - 80.0).abs() <= 3.0 * live.sigma + 5.0, "{live:?}");
    // Measured: 76.6 ± 0.9 ms from utm.jsonl, 70.0 ± 5.5 ms from the feed.
    assert!((from_feed.offset_ms - 80.0).abs() <= 3.0 * from_feed.sigma_ms + 5.0, "{from_feed:?}");
    assert!(from_utm.sigma_ms < 10.0, "{from_utm:?}");
}

#[test]
fn notched_three_point_test_replays_with_cmod() {
    let dir = tempfile::tempdir().unwrap();
    let p = real_test(SimTest::ThreePointNotched, LoadLaw::Softening, 0.0, 67);
    let rec = simulate(dir.path(), "notched", &p);
    let rig = SimRig::new(&p).unwrap();
    let (recording, lines, _) = replay_lines(&rec, false);
    feedcheck(&lines, &rec.join("tagdeflect.toml"));
    assert_eq!(recording.config.specimen.beam.as_ref().and_then(|b| b.notch_mm), Some(25.0));
    let truth: Vec<SimTruthLine> = read_jsonl_file(&rec.join(SIM_TRUTH_FILE)).unwrap();
    let last = truth.last().unwrap();
    let cmod = last.cmod_mm.expect("cmod in the truth");
    println!("notched: final deflection {} mm, CMOD {cmod} mm, load {} kN", last.midspan_deflection_mm, last.load_kn);
    assert!(cmod > 2.0, "the mouth opens: {cmod}");
    // The gauge carries the mouth point with each tag's pose: the concrete between the tags
    // (23 mm either side) and the mouth bends elastically, which a rigid carry misses.
    println!("notched: true cmod gauge (the tags' rigid carry to the mouth) {} vs the mouth's opening {cmod} mm", last.gauges["cmod"]);
    assert!(
        (last.gauges["cmod"] - cmod).abs() < 0.03,
        "the cmod gauge's definition is the mouth opening: {} vs {cmod}",
        last.gauges["cmod"]
    );

    let c = compare(&rig, &lines);
    for name in ["net", "cmod", "rot1"] {
        println!("GAUGES notched 3-point {name}: RMS {:.5}, max {:.5} over {} lines", c.rms(name), c.max(name), c.errors[name].len());
        assert_eq!(c.errors[name].len(), lines.len(), "{name} in every line");
    }
    // Floors ~1.4 × the worst of three runs on this seed (2026-12-06, load 14–20 on 2 cores:
    // net 0.00207 mm, CMOD 0.00412 mm, end rotation 0.0826 mrad — every run the same figures).
    assert!(c.rms("net") <= 0.0029, "net deflection RMS {} mm", c.rms("net"));
    assert!(c.rms("cmod") <= 0.0058, "CMOD RMS {} mm", c.rms("cmod"));
    assert!(c.rms("rot1") <= 0.116, "end rotation RMS {} mrad", c.rms("rot1"));
    // Against the physical mouth opening of the truth file, line by line.
    let worst =
        lines.iter().map(|l| (l.gauges["cmod"].value - rig.cmod_at(rig.midspan_deflection(l.t_ns)).unwrap()).abs()).fold(0.0, f64::max);
    println!("GAUGES notched 3-point: CMOD vs the true mouth opening, max error {worst:.4} mm");
    assert!(worst <= 0.06, "{worst}");
    let (ok, n) = c.within_2sigma();
    println!("GAUGES notched 3-point: {ok} of {n} errors within 2σ, RMS error/σ {:.2}", c.z_rms());
    // σ honest both ways (measured 43 of 48, RMS error/σ 1.12, 2026-12-06; a doubled σ gives 0.56).
    assert!(ok as f64 >= 0.85 * n as f64, "σ honest: {ok} of {n} within 2σ");
    assert!((0.75..=1.3).contains(&c.z_rms()), "RMS error/σ {:.3}", c.z_rms());
    // No clock check here: this test cracks on its second loaded frame set (two points
    // before the peak), too few for the pre-peak fit; the clock check is asserted on the
    // four-point test above (80 ms), where the ramp has 13 points.
    assert!(estimate_from_utm(&lines, &recording.utm, 1000.0).is_none(), "an estimate from two pre-peak points");
}

/// The default rig is untouched by the real tests: `replay/one-cam` (made by `simulate`
/// before they existed) is reproduced byte for byte.
#[test]
fn default_rig_output_is_unchanged() {
    let dir = tempfile::tempdir().unwrap();
    let p = SimParams { cameras: 1, width: 800, height: 600, frame_sets: 8, rest_frames: 2, ..SimParams::default() };
    let out = simulate(dir.path(), "one-cam", &p);
    let committed = root().join("replay/one-cam");
    let mut files =
        vec!["tagdeflect.toml".to_string(), "frames.jsonl".into(), "truth.jsonl".into(), "utm.jsonl".into(), SIM_TRUTH_FILE.into()];
    for e in std::fs::read_dir(committed.join("centre")).unwrap() {
        files.push(format!("centre/{}", e.unwrap().file_name().to_string_lossy()));
    }
    for f in &files {
        let a = std::fs::read(committed.join(f)).unwrap();
        let b = std::fs::read(out.join(f)).unwrap_or_else(|e| panic!("{f}: {e}"));
        assert!(a == b, "{f} differs from the committed recording");
    }
    assert!(files.len() >= 13);
}
