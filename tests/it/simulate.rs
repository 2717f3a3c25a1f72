//! The synthetic rig and `simulate`: the recording is valid, the truth matches the images
//! (sampled intensities, sub-pixel edge positions, the real detector), the beam follows
//! the requested deflection, and the options (bump, hidden tag, drops, shuffle) act.

use nalgebra::{Point2, Vector3};
use tagdeflect::commands::simulate::simulate;
use tagdeflect::config::Recording;
use tagdeflect::config::{Config, TagRole};
use tagdeflect_core::camera::{CameraIntrinsics, Pose};
use tagdeflect_core::frame::GrayImage;
use tagdeflect_core::tags::TagFamily;
use tagdeflect_detect::{Detector, DetectorOptions};
use tagdeflect_io::recording::{read_jsonl_file, FrameEntry, TruthLine};
use tagdeflect_io::utm::UtmSample;
use tagdeflect_sim::{SimParams, SimRig, SimTruthLine, SIM_TRUTH_FILE};

fn small(cameras: u32, width: u32, height: u32, frame_sets: u32) -> SimParams {
    SimParams { cameras, width, height, frame_sets, rest_frames: 1, ..SimParams::default() }
}

fn project(k: &CameraIntrinsics, pose: &Pose, w: &Vector3<f64>) -> Point2<f64> {
    // The simulator's own lens model (independent of the product's).
    tagdeflect_sim::lens::Lens::of(k).pixel(&pose.transform(w)).expect("in front of the camera")
}

#[test]
fn simulate_writes_a_valid_recording() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("rec");
    let params = SimParams { shuffle: true, drop_prob: 0.25, jitter_ms: 2.0, seed: 7, ..small(3, 320, 240, 6) };
    let summary = simulate(&params, &out).unwrap();
    assert_eq!(summary.frames + summary.dropped, 18);
    println!("summary: {summary:?}");

    // The config parses and validates as a whole; intrinsics are there, poses are not.
    let config = Config::load(&out.join("tagdeflect.toml")).unwrap();
    assert_eq!(config.cameras.len(), 3);
    assert!(config.cameras.iter().all(|c| c.rvec.is_none() && c.tvec_mm.is_none() && c.fx > 0.0));
    assert_eq!(config.background.family, TagFamily::Tag25h9);
    assert!(config.background.tags.len() >= 8);
    assert_eq!(config.specimen.family, TagFamily::Tag36h11);
    assert_eq!(config.specimen.tags.len(), 9);
    assert_eq!(config.specimen.tags.iter().filter(|t| t.role == Some(TagRole::Midspan)).count(), 3);
    assert_eq!(config.specimen.tags.iter().filter(|t| t.role == Some(TagRole::Support)).count(), 6);
    assert_eq!(config.sim.as_ref(), Some(&params));

    // Every line parses with serde; every frame file exists and has the camera's size.
    let frames: Vec<FrameEntry> = read_jsonl_file(&out.join("frames.jsonl")).unwrap();
    assert_eq!(frames.len() as u64, summary.frames);
    let sorted = frames.windows(2).all(|w| w[0].t_ns <= w[1].t_ns);
    assert!(!sorted, "shuffle = true must leave frames.jsonl unsorted");
    for f in &frames {
        let img = image::open(out.join(&f.file)).unwrap().to_luma8();
        assert_eq!(img.dimensions(), (320, 240), "{}", f.file);
    }
    let truth: Vec<TruthLine> = read_jsonl_file(&out.join("truth.jsonl")).unwrap();
    assert_eq!(truth.len(), 6);
    assert!(truth.iter().all(|l| l.tags.len() == 9));
    let utm: Vec<UtmSample> = read_jsonl_file(&out.join("utm.jsonl")).unwrap();
    let (t0, t1) = (frames.iter().map(|f| f.t_ns).min().unwrap(), frames.iter().map(|f| f.t_ns).max().unwrap());
    assert!(utm.first().unwrap().t_ns < t0 && utm.last().unwrap().t_ns > t1, "UTM samples cover the frames");
    let dt = utm[1].t_ns - utm[0].t_ns;
    assert!((dt - 20_000_000).abs() <= 1, "50 Hz: {dt} ns");
    let sim: Vec<SimTruthLine> = read_jsonl_file(&out.join(SIM_TRUTH_FILE)).unwrap();
    assert_eq!(sim.len(), 6);
    let dropped_in_truth = sim.iter().flat_map(|l| &l.cameras).filter(|c| c.frame_t_ns.is_none()).count() as u64;
    assert_eq!(dropped_in_truth, summary.dropped);

    // The product's own reader accepts it.
    let rec = Recording::open(&out).unwrap();
    assert_eq!(rec.frames.len() as u64, summary.frames);
    assert_eq!(rec.truth.len(), 6);
    assert!(!rec.utm.is_empty());
    assert!(rec.skipped_lines.is_empty());

    // Writing twice into the same folder is refused, nothing overwritten.
    assert!(simulate(&params, &out).is_err());
}

#[test]
fn same_seed_same_images_and_deflection_reaches_the_maximum() {
    let p = small(1, 200, 150, 5);
    let a = SimRig::new(&p).unwrap();
    let b = SimRig::new(&p).unwrap();
    let t = a.frame_time_ns(0, 3).unwrap();
    assert_eq!(a.render(0, t), b.render(0, t));
    // Rest, then the ramp; the last nominal set time is exactly at the maximum.
    assert_eq!(a.midspan_deflection(a.set_time_ns(0)), 0.0);
    assert_eq!(a.midspan_deflection(a.set_time_ns(1)), 0.0);
    let last = a.set_time_ns(4);
    assert!((a.midspan_deflection(last) - p.max_deflection_mm).abs() < 1e-9);
    assert!((a.midspan_deflection(a.set_time_ns(2)) - 2.0).abs() < 1e-9, "linear ramp: 1/3 of 6 mm");
    // The middle tag at midspan (neutral axis, zero slope) moves straight down by δ.
    let c0 = a.tag_centres(a.set_time_ns(0));
    let c1 = a.tag_centres(last);
    let d = c1[0].1 - c0[0].1;
    assert!(d.x.abs() < 1e-9 && d.y.abs() < 1e-12 && (d.z + 6.0).abs() < 1e-9, "midspan tag moved {d}");
    // A top tag over a support moves along the beam (section rotation), not down.
    let top_support = 4; // slots: middle row (0..3), then top row: midspan, left, right
    let d = c1[top_support].1 - c0[top_support].1;
    assert!(d.x > 0.5 && d.z.abs() < 0.1, "top tag over the left support moved {d}");
    // Truth of the net deflection (feed sense): zero at rest, ≈ δ at the end (supports ≈ 0).
    assert_eq!(a.truth_line(0).net_deflection_mm, Some(0.0));
    let net = a.truth_line(4).net_deflection_mm.unwrap();
    assert!((net - 6.0).abs() < 0.01, "net deflection {net}");
    // Cyclic history (live demo): up, down, and again; the truth's rest state stays at δ = 0.
    let c = SimRig::new(&SimParams { cyclic: true, ..p.clone() }).unwrap();
    let period = c.set_time_ns(1) - c.set_time_ns(0);
    assert!((c.midspan_deflection(c.set_time_ns(4)) - 6.0).abs() < 1e-9);
    assert!((c.midspan_deflection(c.set_time_ns(7)) - 0.0).abs() < 1e-9);
    assert!((c.midspan_deflection(c.set_time_ns(7) + period * 4) - 6.0).abs() < 1e-6);
    assert!(c.truth_line(6).net_deflection_mm.unwrap() > 1.0);
    // The UTM: load ∝ deflection; stroke = load-point deflection + compliance × load.
    let s = a.utm_sample(last);
    assert!((s.load_kn - p.stiffness_kn_per_mm * 6.0).abs() < 1e-9);
    let under_load = a.beam().deflection(0.5 * p.load_span_mm, 6.0);
    assert!((s.stroke_mm.unwrap() - (under_load + p.compliance_mm_per_kn * s.load_kn)).abs() < 1e-9);
}

/// Sub-pixel position of the 50 % crossing along a sampled profile (dark → light).
fn crossing(profile: &[(f64, f64)], dark: f64, light: f64) -> Option<f64> {
    let mid = 0.5 * (dark + light);
    profile.windows(2).find(|w| (w[0].1 - mid) * (w[1].1 - mid) <= 0.0 && w[0].1 != w[1].1).map(|w| {
        let f = (mid - w[0].1) / (w[1].1 - w[0].1);
        w[0].0 + f * (w[1].0 - w[0].0)
    })
}

#[test]
fn truth_matches_the_images() {
    let p = SimParams { noise_sigma: 0.0, ..small(3, 800, 600, 4) };
    let rig = SimRig::new(&p).unwrap();
    let cams = rig.cameras();
    let k = 3;
    let mut dark_max: f64 = 0.0;
    let mut light_min: f64 = 255.0;
    let mut edge_err = Vec::new();
    let mut bad = Vec::new();
    for (c, cam) in cams.iter().enumerate() {
        let t = rig.frame_time_ns(c, k).unwrap();
        let img = rig.render(c, t);
        let pose = rig.camera_pose(c, t);
        // Specimen tags at the frame's own time, background tags fixed.
        // (corners, cell edge): tag36h11 has 8 cells across the black square, tag25h9 7.
        let mut squares: Vec<([Vector3<f64>; 4], f64)> =
            rig.tag_corners_world(t).into_iter().map(|(_, q)| (q, p.specimen_tag_mm / 8.0)).collect();
        for b in rig.background_tags() {
            squares.push((b.corners_mm.map(Vector3::from), p.background_tag_mm / 7.0));
        }
        for (si, &(q, cell)) in squares.iter().enumerate() {
            let centre = (q[0] + q[1] + q[2] + q[3]) / 4.0;
            for corner in q {
                let inward = (centre - corner).normalize();
                // Half a cell inside the black border's corner, and half a cell outside it
                // (in the white ring), along the diagonal.
                let inside = project(&cam.intrinsics, &pose, &(corner + inward * (0.5 * cell * 2f64.sqrt())));
                let outside = project(&cam.intrinsics, &pose, &(corner - inward * (0.5 * cell * 2f64.sqrt())));
                assert!(cam.intrinsics.in_image(&inside, 2.0), "camera {} does not see a tag corner: {inside}", cam.name);
                let (vi, vo) = (img.sample(inside.x, inside.y), img.sample(outside.x, outside.y));
                if vi >= 90.0 || vo <= 160.0 {
                    bad.push(format!("camera {} square {} corner at {inside}: inside {vi:.0}, outside {vo:.0}", cam.name, si));
                }
                dark_max = dark_max.max(vi);
                light_min = light_min.min(vo);
            }
            // Edge positions: the 50 % crossing across the middle of each black-square edge.
            for e in 0..4 {
                let (a, b) = (q[e], q[(e + 1) % 4]);
                let m = (a + b) / 2.0;
                let outward = (m - centre).normalize();
                let p0 = project(&cam.intrinsics, &pose, &m);
                let p1 = project(&cam.intrinsics, &pose, &(m + outward * (0.5 * cell)));
                let n = (p1 - p0).normalize();
                let span = 0.45 * cell * ((p1 - p0).norm() / (0.5 * cell));
                let profile: Vec<(f64, f64)> = (-20..=20)
                    .map(|i| {
                        let s = span * i as f64 / 20.0;
                        let pt = p0 + n * s;
                        (s, img.sample(pt.x, pt.y))
                    })
                    .collect();
                if let Some(x) = crossing(&profile, 28.0, 228.0) {
                    edge_err.push(x);
                }
            }
        }
    }
    let mean = edge_err.iter().sum::<f64>() / edge_err.len() as f64;
    let rms = (edge_err.iter().map(|e| e * e).sum::<f64>() / edge_err.len() as f64).sqrt();
    println!(
        "corner samples: darkest inside {dark_max:.0}, lightest outside {light_min:.0}; edge 50% crossing vs projected truth over {} edges: mean {mean:+.3} px, RMS {rms:.3} px",
        edge_err.len()
    );
    assert!(bad.is_empty(), "corners not dark inside / light outside:\n{}", bad.join("\n"));
    assert!(dark_max < 90.0, "inside a black corner should be dark: {dark_max}");
    assert!(light_min > 160.0, "outside a black corner should be light: {light_min}");
    assert!(edge_err.len() >= 3 * (9 + 11) * 4 * 9 / 10, "edges found: {}", edge_err.len());
    assert!(rms < 0.1 && mean.abs() < 0.03, "edge positions off the truth: mean {mean}, RMS {rms}");
}

#[test]
fn the_real_detector_decodes_rendered_tags_of_both_families() {
    let p = SimParams { noise_sigma: 2.0, ..small(1, 1280, 960, 2) };
    let rig = SimRig::new(&p).unwrap();
    let t = rig.frame_time_ns(0, 1).unwrap();
    let img = rig.render(0, t);
    let cam = &rig.cameras()[0];
    let pose = rig.camera_pose(0, t);
    let mut det = Detector::new(DetectorOptions::for_families(&[TagFamily::Tag36h11, TagFamily::Tag25h9])).unwrap();
    let found = det.detect(&img);
    let mut errs = Vec::new();
    let mut check = |family: TagFamily, id: u32, corners: [Vector3<f64>; 4]| {
        let d = found.iter().find(|d| d.family == family && d.id == id);
        let d = d.unwrap_or_else(|| {
            panic!("{family} id {id} not decoded; found {:?}", found.iter().map(|d| (d.family, d.id)).collect::<Vec<_>>())
        });
        for (c, w) in d.corners.iter().zip(&corners) {
            let px = project(&cam.intrinsics, &pose, w);
            errs.push((c - px).norm());
        }
    };
    for (id, q) in rig.tag_corners_world(t) {
        check(TagFamily::Tag36h11, id, q);
    }
    for b in rig.background_tags() {
        check(TagFamily::Tag25h9, b.id, b.corners_mm.map(Vector3::from));
    }
    let mean = errs.iter().sum::<f64>() / errs.len() as f64;
    let max = errs.iter().cloned().fold(0.0, f64::max);
    println!("detector: {} tags decoded; corner distance to projected truth mean {mean:.3} px, max {max:.3} px", found.len());
    assert!(found.iter().all(|d| d.hamming == 0));
    assert!(mean < 0.1 && max < 0.5, "corners (SPEC order) must lie on the projected truth: mean {mean}, max {max}");
}

fn mean_abs_diff(a: &GrayImage, b: &GrayImage, x0: f64, y0: f64, r: f64) -> f64 {
    let mut s = 0.0;
    let mut n = 0.0;
    for y in (y0 - r).max(0.0) as u32..((y0 + r) as u32).min(a.height) {
        for x in (x0 - r).max(0.0) as u32..((x0 + r) as u32).min(a.width) {
            s += (a.get(x, y) as f64 - b.get(x, y) as f64).abs();
            n += 1.0;
        }
    }
    s / n
}

#[test]
fn bump_moves_the_camera_and_hide_covers_the_tag() {
    let p = SimParams {
        noise_sigma: 0.0,
        bump_camera: Some(1),
        bump_at: 2,
        bump_rot_deg: 0.5,
        hide_tag: Some(0),
        hide_camera: 0,
        hide_from: 1,
        hide_count: 1,
        ..small(2, 400, 300, 4)
    };
    let rig = SimRig::new(&p).unwrap();
    let cams = rig.cameras();
    let (t1, t2) = (rig.set_time_ns(1), rig.set_time_ns(2));
    assert_eq!(rig.camera_pose(1, t1), cams[1].pose);
    assert!(rig.camera_pose(1, t2).angle_to(&cams[1].pose).to_degrees() > 0.49);
    assert_eq!(rig.camera_pose(0, t2), cams[0].pose);
    let line = rig.truth_line(2);
    assert!(line.cameras[1].bumped && !line.cameras[0].bumped);
    // A background tag centre moves in camera 1's image after the bump.
    let b = &rig.background_tags()[2];
    let centre = b.corners_mm.iter().map(|c| Vector3::from(*c)).sum::<Vector3<f64>>() / 4.0;
    let before = project(&cams[1].intrinsics, &rig.camera_pose(1, t1), &centre);
    let after = project(&cams[1].intrinsics, &rig.camera_pose(1, t2), &centre);
    assert!((after - before).norm() > 2.0, "{before} → {after}");
    let (i1, i2) = (rig.render(1, t1), rig.render(1, t2));
    assert!(mean_abs_diff(&i1, &i2, before.x, before.y, 20.0) > 5.0);
    // Tag 0 is covered by a flat grey card in camera 0 during set 1 only.
    let pose0 = rig.camera_pose(0, t1);
    let (_, q) = rig.tag_corners_world(t1)[0];
    let c = project(&cams[0].intrinsics, &pose0, &((q[0] + q[2]) / 2.0));
    let hidden = rig.render(0, t1);
    let seen = rig.render(0, rig.set_time_ns(0));
    assert!(rig.truth_line(1).cameras[0].hidden_tag == Some(0) && rig.truth_line(2).cameras[0].hidden_tag.is_none());
    let (mut lo, mut hi) = (255u8, 0u8);
    for dy in -4..=4 {
        for dx in -4..=4 {
            let v = hidden.get((c.x.round() as i32 + dx) as u32, (c.y.round() as i32 + dy) as u32);
            lo = lo.min(v);
            hi = hi.max(v);
        }
    }
    assert!(hi - lo <= 2 && (110..=126).contains(&lo), "the card is flat grey: {lo}..{hi}");
    assert!(mean_abs_diff(&hidden, &seen, c.x, c.y, 8.0) > 30.0);
}

/// `hide_background_tag` covers a background tag with a flat grey card in one camera over
/// the hide window only (a person walking past a reference tag).
#[test]
fn hide_background_tag_covers_it_in_one_camera() {
    let p =
        SimParams { noise_sigma: 0.0, hide_background_tag: Some(2), hide_camera: 0, hide_from: 1, hide_count: 1, ..small(2, 400, 300, 4) };
    let rig = SimRig::new(&p).unwrap();
    let cams = rig.cameras();
    let b = rig.background_tags().into_iter().find(|b| b.id == 2).unwrap();
    let centre = b.corners_mm.iter().map(|c| Vector3::from(*c)).sum::<Vector3<f64>>() / 4.0;
    let (t0, t1, t2) = (rig.set_time_ns(0), rig.set_time_ns(1), rig.set_time_ns(2));
    let c = project(&cams[0].intrinsics, &rig.camera_pose(0, t1), &centre);
    let hidden = rig.render(0, t1);
    let (mut lo, mut hi) = (255u8, 0u8);
    for dy in -3..=3 {
        for dx in -3..=3 {
            let v = hidden.get((c.x.round() as i32 + dx) as u32, (c.y.round() as i32 + dy) as u32);
            lo = lo.min(v);
            hi = hi.max(v);
        }
    }
    assert!(hi - lo <= 2 && (110..=126).contains(&lo), "the card is flat grey: {lo}..{hi}");
    assert!(mean_abs_diff(&hidden, &rig.render(0, t0), c.x, c.y, 6.0) > 30.0, "the tag is seen before the card");
    assert!(mean_abs_diff(&rig.render(0, t0), &rig.render(0, t2), c.x, c.y, 6.0) < 1.0, "and after it");
    // The other camera is not covered.
    let c1 = project(&cams[1].intrinsics, &rig.camera_pose(1, t1), &centre);
    assert!(mean_abs_diff(&rig.render(1, t1), &rig.render(1, t0), c1.x, c1.y, 6.0) < 1.0);
}

#[test]
fn every_tag_is_in_view_for_common_rigs() {
    for cameras in 1..=3 {
        for (w, h) in [(640, 480), (800, 600), (1280, 960), (1920, 1080)] {
            for strong in [None, Some(0)] {
                let p = SimParams { strong_distortion_camera: strong, bump_camera: Some(0), bump_at: 2, ..small(cameras, w, h, 4) };
                let rig = SimRig::new(&p).unwrap();
                for (c, cam) in rig.cameras().iter().enumerate() {
                    for k in [0, 3] {
                        let t = rig.set_time_ns(k);
                        let pose = rig.camera_pose(c, t);
                        let mut pts: Vec<Vector3<f64>> = rig.tag_corners_world(t).into_iter().flat_map(|(_, q)| q).collect();
                        pts.extend(rig.background_tags().iter().flat_map(|b| b.corners_mm.map(Vector3::from)));
                        for q in pts {
                            let px = project(&cam.intrinsics, &pose, &q);
                            assert!(
                                cam.intrinsics.in_image(&px, 8.0),
                                "{cameras} cameras {w}x{h}, strong distortion {strong:?}: camera {} set {k} sees {q} at {px}",
                                cam.name
                            );
                        }
                    }
                }
            }
        }
    }
}

#[test]
fn hard_case_frames_still_decode() {
    let p = SimParams {
        noise_sigma: 5.0,
        blur_sigma: 1.0,
        motion_blur_every: 2,
        motion_blur_px: 3.0,
        strong_distortion_camera: Some(0),
        ..small(2, 1280, 960, 4)
    };
    let rig = SimRig::new(&p).unwrap();
    assert_eq!(rig.cameras()[0].intrinsics.dist[0], -0.25);
    // Set 1 carries motion blur in camera 0 (every 2nd set, cameras in turn).
    assert!(rig.has_motion_blur(0, 1) && !rig.has_motion_blur(1, 1) && !rig.has_motion_blur(0, 2));
    let mut det = Detector::new(DetectorOptions::for_families(&[TagFamily::Tag36h11, TagFamily::Tag25h9])).unwrap();
    for (cam, k) in [(0usize, 1u64), (0, 2), (1, 1)] {
        let t = rig.frame_time_ns(cam, k).unwrap();
        let found = det.detect(&rig.render(cam, t));
        let n36 = found.iter().filter(|d| d.family == TagFamily::Tag36h11).count();
        let n25 = found.iter().filter(|d| d.family == TagFamily::Tag25h9).count();
        println!(
            "camera {cam} set {k} (motion blur {}): {n36} specimen + {n25} background tags decoded",
            rig.has_motion_blur(cam, k as i64)
        );
        assert_eq!((n36, n25), (9, rig.background_tags().len()), "camera {cam} set {k}");
    }
}
