//! Slow camera drift (issue "A whole test", finding 9): a camera that turns by a few
//! hundredths of a degree over the test must not show up as deflection, a bump must still
//! be caught in the frame set it happens, and the drift is reported in the feed.
//!
//! The rendered scenario runs at one frame set per 100 s (24 sets, 38 minutes), so that
//! the drift has the rate of a real one (0.05° and 0.3 mm over the recording ≈ 0.08°/h,
//! 0.5 mm/h, inside the filter's default rate prior of 0.1°/h and 1 mm/h).

use nalgebra::{Point2, Rotation3, Unit, Vector3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

use crate::common::*;
use tagdeflect::accuracy::{evaluate, evaluate_from, Accuracy};
use tagdeflect::config::Recording;
use tagdeflect::graph::in_process::{self as replay, ReplayOptions};
use tagdeflect_core::camera::{CameraIntrinsics, Pose};
use tagdeflect_core::feed::FeedLine;
use tagdeflect_estimate::{BackgroundTagObservation, DriftConfig, HeldCameraPose, HeldPoseOptions};
use tagdeflect_sim::{SimParams, SimTruthLine, SIM_TRUTH_FILE};

/// Replays `dir` with drift tracking on or off; prints and returns the figures.
fn replay_with(label: &str, dir: &std::path::Path, drift: bool) -> (Accuracy, Vec<FeedLine>, Recording) {
    let mut rec = Recording::open(dir).unwrap_or_else(|e| panic!("{e}"));
    rec.config.measure.drift_tracking = drift;
    let mut lines = Vec::new();
    replay::replay(&rec, ReplayOptions { full_frame: false, progress: false, ..Default::default() }, |l, _, _| lines.push(l.clone()))
        .unwrap();
    let acc = evaluate(&rec.config, &rec.truth, &lines);
    println!("ACCURACY {label}, drift tracking {}: {acc}", if drift { "on" } else { "off" });
    (acc, lines, rec)
}

fn slow_scene(seed: u64, drift_camera: Option<u32>) -> SimParams {
    SimParams {
        cameras: 3,
        width: 1280,
        height: 960,
        frame_sets: 24,
        fps: 0.01,
        utm_hz: 0.5,
        drift_camera,
        drift_rot_deg: 0.05,
        drift_trans_mm: 0.3,
        seed,
        ..SimParams::default()
    }
}

/// A camera drifting 0.05° and 0.3 mm over the recording measures like a static one with
/// drift tracking, and is clearly off without it; the feed's drift matches the truth; static
/// cameras are measured as before (drift tracking on or off within noise).
#[test]
fn drifting_camera_measures_like_a_static_one() {
    let dir = tempfile::tempdir().unwrap();
    let drifting = simulate(dir.path(), "drifting", &slow_scene(61, Some(0)));
    let still = simulate(dir.path(), "still", &slow_scene(61, None));
    let (drift_on, lines, rec) = replay_with("drifting camera", &drifting, true);
    let (drift_off, _, _) = replay_with("drifting camera", &drifting, false);
    let (still_on, still_lines, _) = replay_with("static cameras", &still, true);
    let (still_off, _, _) = replay_with("static cameras", &still, false);
    feedcheck(&lines, &drifting.join("tagdeflect.toml"));
    for a in [&drift_on, &drift_off, &still_on, &still_off] {
        assert_eq!(a.coverage(), 1.0, "every tag solved in every frame set");
    }
    println!(
        "DRIFT displacement RMS: drifting camera {:.4} mm corrected, {:.4} mm held; static cameras {:.4} mm (tracking on), {:.4} mm (off)",
        drift_on.disp_rms_mm, drift_off.disp_rms_mm, still_on.disp_rms_mm, still_off.disp_rms_mm
    );
    println!(
        "DRIFT vertical RMS: drifting {:.4} / {:.4} mm, static {:.4} / {:.4} mm; net deflection RMS: drifting {:.4} / {:.4} mm, static {:.4} / {:.4} mm",
        drift_on.vertical_rms_mm,
        drift_off.vertical_rms_mm,
        still_on.vertical_rms_mm,
        still_off.vertical_rms_mm,
        drift_on.net_rms_mm.unwrap(),
        drift_off.net_rms_mm.unwrap(),
        still_on.net_rms_mm.unwrap(),
        still_off.net_rms_mm.unwrap()
    );
    // Without the correction the drift is plainly visible as displacement (the two static
    // cameras carry most of each solve: measured 1.69×, 0.0071 against 0.0042 mm).
    assert!(drift_off.disp_rms_mm >= 1.4 * still_off.disp_rms_mm, "held pose under drift: {}", drift_off.disp_rms_mm);
    // With it, the drifting camera is at the level of static ones (floor: 1.5× or +3 µm).
    let level = (1.5 * still_on.disp_rms_mm).max(still_on.disp_rms_mm + 0.003);
    assert!(drift_on.disp_rms_mm <= level, "drifting {} vs static {}", drift_on.disp_rms_mm, still_on.disp_rms_mm);
    assert!(drift_on.vertical_rms_mm <= (1.5 * still_on.vertical_rms_mm).max(still_on.vertical_rms_mm + 0.002));
    // Static cameras: tracking the drift changes nothing beyond noise (10 % or 2 µm).
    assert!(
        (still_on.disp_rms_mm - still_off.disp_rms_mm).abs() <= (0.1 * still_off.disp_rms_mm).max(0.002),
        "static: tracking on {} vs off {}",
        still_on.disp_rms_mm,
        still_off.disp_rms_mm
    );

    // The reported drift against the truth (camera 0 from its pose in the first set).
    let truth: Vec<SimTruthLine> =
        std::fs::read_to_string(drifting.join(SIM_TRUTH_FILE)).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    let name = &rec.config.cameras[0].name;
    let pose_of = |l: &SimTruthLine| {
        let c = l.cameras.iter().find(|c| &c.name == name).unwrap();
        Pose::from_rvec_tvec(c.rvec, c.tvec_mm)
    };
    let p0 = pose_of(&truth[0]);
    let (mut worst_deg, mut worst_mm) = (0.0f64, 0.0f64);
    for l in &lines {
        let t = truth.iter().find(|t| t.set == l.seq).unwrap();
        let true_deg = pose_of(t).angle_to(&p0).to_degrees();
        let true_mm = (pose_of(t).centre() - p0.centre()).norm();
        let cam = l.cameras.iter().find(|c| &c.name == name).unwrap();
        let (deg, mm) = (cam.drift_deg.expect("drift reported"), cam.drift_mm.expect("drift reported"));
        worst_deg = worst_deg.max((deg - true_deg).abs());
        worst_mm = worst_mm.max((mm - true_mm).abs());
        if l.seq % 6 == 5 || l.seq + 1 == lines.len() as u64 {
            println!("DRIFT set {:2}: reported {deg:.5}° {mm:.4} mm, true {true_deg:.5}° {true_mm:.4} mm", l.seq);
        }
    }
    let last = lines.last().unwrap().cameras.iter().find(|c| &c.name == name).unwrap();
    println!(
        "DRIFT worst error of the reported drift: {worst_deg:.5}° {worst_mm:.4} mm; at the end {:?}° {:?} mm",
        last.drift_deg, last.drift_mm
    );
    assert!(worst_deg <= 0.005, "reported drift off by {worst_deg}° (tolerance 0.005°)");
    assert!(worst_mm <= 0.1, "reported centre shift off by {worst_mm} mm (tolerance 0.1 mm)");
    // The static cameras report (almost) none.
    let static_cams = lines.iter().flat_map(|l| l.cameras.iter().filter(|c| &c.name != name));
    for c in static_cams.chain(still_lines.iter().flat_map(|l| l.cameras.iter())) {
        assert!(c.drift_deg.unwrap_or(0.0) <= 0.003, "static camera {} reports {:?}°", c.name, c.drift_deg);
    }
    assert!(lines.iter().all(|l| l.cameras.iter().all(|c| !c.bumped)), "drift is never taken for a bump");
}

// ----------------------------------------------------------------------------------------
// The tracker alone, on synthetic corners (no rendering): long drift, then a bump.

fn intrinsics() -> CameraIntrinsics {
    CameraIntrinsics { width: 1280, height: 960, fx: 1500.0, fy: 1500.0, cx: 639.5, cy: 479.5, dist: [-0.05, 0.025, 0.0, 0.0, 0.0] }
}

/// Background tags around the beam (70 mm): a frame behind it and a bench in front, two
/// planes as in the simulated rig.
fn background() -> Vec<[Vector3<f64>; 4]> {
    let h = 35.0;
    let mut out = Vec::new();
    for &(x, z) in &[(-450.0, 50.0), (-450.0, 250.0), (450.0, 50.0), (450.0, 250.0), (-150.0, 380.0), (150.0, 380.0)] {
        let c = Vector3::new(x, 400.0, z);
        out.push([c + Vector3::new(-h, 0.0, -h), c + Vector3::new(h, 0.0, -h), c + Vector3::new(h, 0.0, h), c + Vector3::new(-h, 0.0, h)]);
    }
    for &x in &[-350.0, -120.0, 120.0, 350.0] {
        let c = Vector3::new(x, -250.0, -20.0);
        out.push([c + Vector3::new(-h, -h, 0.0), c + Vector3::new(h, -h, 0.0), c + Vector3::new(h, h, 0.0), c + Vector3::new(-h, h, 0.0)]);
    }
    out
}

/// Points of the beam's front face (where the specimen tags are).
fn beam_points() -> Vec<Vector3<f64>> {
    let mut out = Vec::new();
    for x in [-225.0, 0.0, 225.0] {
        for z in [30.0, 75.0, 120.0] {
            out.push(Vector3::new(x, 0.0, z));
        }
    }
    out
}

/// Largest error (px) of the image motion of the beam's points predicted by the pose in
/// use (`used` against `first`) against their true motion (`truth` against `rest`): what a
/// pose error turns into fake displacement.
fn motion_error_px(k: &CameraIntrinsics, used: &Pose, first: &Pose, truth: &Pose, rest: &Pose) -> f64 {
    beam_points()
        .iter()
        .map(|x| {
            let p = |pose: &Pose| k.project(&pose.transform(x)).unwrap();
            ((p(used) - p(first)) - (p(truth) - p(rest))).norm()
        })
        .fold(0.0, f64::max)
}

fn look_at(centre: Vector3<f64>, target: Vector3<f64>) -> Pose {
    let f = (target - centre).normalize();
    let r = f.cross(&Vector3::z()).normalize();
    let d = f.cross(&r);
    let m = nalgebra::Matrix3::from_rows(&[r.transpose(), d.transpose(), f.transpose()]);
    let rot = Rotation3::from_matrix_unchecked(m);
    Pose { rotation: rot, translation: -(rot * centre) }
}

fn moved(p: &Pose, axis: Vector3<f64>, deg: f64, shift: Vector3<f64>) -> Pose {
    let rotation = Rotation3::from_axis_angle(&Unit::new_normalize(axis), deg.to_radians()) * p.rotation;
    let centre = p.centre() + shift;
    Pose { rotation, translation: -(rotation * centre) }
}

fn observe(
    k: &CameraIntrinsics,
    pose: &Pose,
    tags: &[[Vector3<f64>; 4]],
    sigma: f64,
    rng: &mut ChaCha8Rng,
) -> Vec<BackgroundTagObservation> {
    let n = Normal::new(0.0, sigma).unwrap();
    tags.iter()
        .enumerate()
        .map(|(i, w)| BackgroundTagObservation {
            id: i as u32,
            pixels: [0, 1, 2, 3].map(|c| {
                let p = k.project(&pose.transform(&w[c])).unwrap();
                Point2::new(p.x + n.sample(rng), p.y + n.sample(rng))
            }),
            world: *w,
        })
        .collect()
}

/// 0.1° and 0.5 mm of drift over 100 minutes (an update a minute): followed without a
/// false bump; a 0.3° bump in update 100 is caught in that update; the pose in use follows
/// the true camera motion to a fraction of the held pose's error.
#[test]
fn tracker_follows_drift_and_still_catches_a_bump() {
    let k = intrinsics();
    let tags = background();
    let rest = look_at(Vector3::new(-200.0, -1000.0, 350.0), Vector3::new(0.0, 150.0, 100.0));
    let sigma = 0.08;
    let minute = 60_000_000_000i64;
    let drift_at = |i: usize| {
        let u = (i as f64 / 100.0).min(1.0);
        moved(&rest, Vector3::new(1.0, 0.2, 0.3), 0.1 * u, Vector3::new(0.2, 0.1, -1.0).normalize() * 0.5 * u)
    };
    let bump = |p: &Pose| moved(p, Vector3::new(0.4, 1.0, 0.3), 0.3, Vector3::new(1.5, 0.0, 0.5));
    for tracking in [true, false] {
        let options = HeldPoseOptions { drift: DriftConfig { enabled: tracking, ..DriftConfig::default() }, ..HeldPoseOptions::default() };
        let mut tracker = HeldCameraPose::with_options(k, None, options);
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let first = tracker.update_at(0, &observe(&k, &rest, &tags, sigma, &mut rng));
        assert!(first.first_pose);
        let p0 = first.pose.unwrap();
        let (mut false_bumps, mut worst_px, mut end_px, mut worst_deg, mut worst_mm) = (0, 0.0f64, 0.0f64, 0.0f64, 0.0f64);
        for i in 1..100 {
            let truth = drift_at(i);
            let st = tracker.update_at(i as i64 * minute, &observe(&k, &truth, &tags, sigma, &mut rng));
            false_bumps += st.bumped as usize;
            // The pose in use must move as the camera did since the pose was fixed.
            end_px = motion_error_px(&k, &st.pose.unwrap(), &p0, &truth, &rest);
            worst_px = worst_px.max(end_px);
            if let Some(d) = st.drift {
                worst_deg = worst_deg.max((d.angle_deg() - truth.angle_to(&rest).to_degrees()).abs());
                worst_mm = worst_mm.max((d.shift_mm() - (truth.centre() - rest.centre()).norm()).abs());
            }
        }
        println!(
            "DRIFT tracker (tracking {tracking}): false bumps {false_bumps}/99, beam image-motion error worst {worst_px:.3} px, \
             at the end {end_px:.3} px; worst reported-drift error {worst_deg:.5}° {worst_mm:.4} mm"
        );
        // The bump, in update 100.
        let bumped_pose = bump(&drift_at(100));
        let st = tracker.update_at(100 * minute, &observe(&k, &bumped_pose, &tags, sigma, &mut rng));
        println!("DRIFT tracker (tracking {tracking}): bump update: bumped {}, shift {:?} px", st.bumped, st.shift_px);
        if tracking {
            assert_eq!(false_bumps, 0, "slow drift is not a bump");
            // Held, the error grows to ~3 px at the beam; tracked, it stays under 0.1 px.
            assert!(worst_px <= 0.1, "pose follows the drift: {worst_px} px");
            assert!(worst_deg <= 0.01 && worst_mm <= 0.2, "reported drift within 0.01° and 0.2 mm: {worst_deg}° {worst_mm} mm");
            assert!(st.bumped, "the bump is caught in the update it happens");
            assert!(st.drift.map_or(0.0, |d| d.angle_deg()) < 1e-9, "drift restarts from the re-posed pose");
            let mut more_bumps = 0;
            for i in 101..140 {
                let truth = bump(&drift_at(i));
                more_bumps += tracker.update_at(i as i64 * minute, &observe(&k, &truth, &tags, sigma, &mut rng)).bumped as usize;
            }
            assert_eq!(more_bumps, 0, "no second bump while the re-posed camera settles");
        } else {
            // Held pose: the drift stays in the pose in use (until taken for a bump).
            assert!(worst_px > 1.0 || false_bumps > 0, "without tracking the drift is not followed");
        }
    }
}

/// The `[measure]` drift keys are validated when the config is loaded: file, line and key named.
#[test]
fn drift_options_are_validated_with_the_config() {
    let dir = tempfile::tempdir().unwrap();
    let good = std::fs::read_to_string(root().join("config/one-camera.toml")).unwrap();
    let path = dir.path().join("c.toml");
    std::fs::write(&path, format!("{good}\n[measure]\ndrift_tracking = true\ndrift_rate_deg_per_h = 0.05\n")).unwrap();
    let cfg = tagdeflect::config::Config::load(&path).unwrap();
    assert_eq!(DriftConfig::from_measure(&cfg.measure), DriftConfig { rate_deg_per_h: 0.05, ..DriftConfig::default() });
    std::fs::write(&path, format!("{good}\n[measure]\ndrift_rate_mm_per_h = -1.0\n")).unwrap();
    let e = tagdeflect::config::Config::load(&path).unwrap_err();
    assert_eq!(e.key.as_deref(), Some("measure.drift_rate_mm_per_h"), "{e}");
    assert!(e.line.is_some() && e.message.contains("positive"), "{e}");
    std::fs::write(&path, format!("{good}\n[measure]\ndrift_rate = 1.0\n")).unwrap();
    assert!(tagdeflect::config::Config::load(&path).unwrap_err().to_string().contains("drift_rate"), "unknown key refused");
}

/// A tripod leg settling in the middle of a test: the camera still for 1.5 s, then turning
/// 0.02° and moving 0.2 mm within 2 s (~400 times the rate prior of 0.1°/h and 1 mm/h), then
/// still again. The drift filter's fast model takes over within a few frames and hands back
/// after: the displacements are measured at the static cameras' level, which holding the
/// pose misses by far; a drift is never taken for a bump.
#[test]
fn a_fast_drift_mid_test_is_followed_to_the_static_level() {
    let scene = |seed, drift_camera| SimParams {
        cameras: 3,
        width: 1280,
        height: 960,
        frame_sets: 50,
        fps: 10.0,
        max_deflection_mm: 1.0,
        drift_camera,
        drift_rot_deg: 0.02,
        drift_trans_mm: 0.2,
        drift_start_set: 15,
        drift_sets: 20,
        seed,
        ..SimParams::default()
    };
    let dir = tempfile::tempdir().unwrap();
    let drifting = simulate(dir.path(), "fast-drift", &scene(67, Some(0)));
    let still = simulate(dir.path(), "still", &scene(67, None));
    let (on, lines, rec) = replay_with("fast drift", &drifting, true);
    let (off, held_lines, _) = replay_with("fast drift", &drifting, false);
    let (still_on, still_lines, still_rec) = replay_with("static cameras, fast scene", &still, true);
    // The sets while the camera moves and the one after it.
    let window = |rec: &Recording, lines: &[FeedLine]| {
        let part: Vec<FeedLine> = lines.iter().filter(|l| l.seq <= 36).cloned().collect();
        evaluate_from(&rec.config, &rec.truth, &part, 15)
    };
    let (on_moving, still_moving) = (window(&rec, &lines), window(&still_rec, &still_lines));
    let held_bumps = held_lines.iter().filter(|l| l.cameras.iter().any(|c| c.bumped)).count();
    println!(
        "FAST DRIFT displacement RMS: corrected {:.4} mm, held {:.4} mm ({held_bumps} re-posings by the bump test), static cameras {:.4} mm; while moving {:.4} / {:.4} mm (corrected / static); net deflection {:.4} / {:.4} / {:.4} mm",
        on.disp_rms_mm,
        off.disp_rms_mm,
        still_on.disp_rms_mm,
        on_moving.disp_rms_mm,
        still_moving.disp_rms_mm,
        on.net_rms_mm.unwrap(),
        off.net_rms_mm.unwrap(),
        still_on.net_rms_mm.unwrap()
    );
    // Measured (docs/drift.md): corrected 0.0101 mm against static 0.0101 mm overall, 0.0098
    // against 0.0106 mm while the camera moves (held: 0.0105 and 0.0113); the slow model alone
    // with its process noise adapted to the innovations' lean (before the fast model) gave
    // 0.0124 and 0.0142 mm — worse than holding the pose.
    assert!(on.disp_rms_mm <= 1.1 * still_on.disp_rms_mm, "fast drift: corrected {} vs static {}", on.disp_rms_mm, still_on.disp_rms_mm);
    assert!(
        on_moving.disp_rms_mm <= 1.2 * still_moving.disp_rms_mm,
        "while the camera moves: corrected {} vs static {}",
        on_moving.disp_rms_mm,
        still_moving.disp_rms_mm
    );
    assert!(
        on.net_rms_mm.unwrap() <= 1.3 * still_on.net_rms_mm.unwrap(),
        "net deflection {:?} vs {:?}",
        on.net_rms_mm,
        still_on.net_rms_mm
    );
    // The drift the feed reports at the end is the camera's (0.02°, 0.2 mm).
    let end = lines.last().unwrap().cameras.iter().find(|c| c.name == rec.config.cameras[0].name).unwrap();
    let (deg, mm) = (end.drift_deg.expect("drift reported"), end.drift_mm.expect("drift reported"));
    println!("FAST DRIFT reported at the end: {deg:.5}° {mm:.4} mm (true 0.02000° 0.2000 mm)");
    assert!((deg - 0.02).abs() <= 0.003 && (mm - 0.2).abs() <= 0.05, "reported drift {deg}° {mm} mm");
    assert!(lines.iter().all(|l| l.cameras.iter().all(|c| !c.bumped)), "a drift is never taken for a bump");
}
