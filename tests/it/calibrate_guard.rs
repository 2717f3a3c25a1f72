//! `tagdeflect calibrate`'s guard rails: each mistake a new user makes is refused or flagged —
//! too few views, two cameras in one folder (OpenCV's left and right samples), another focus
//! setting (rendered with truth), a wrong board size — and every calibration ends with a
//! verdict and its hints.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use nalgebra::Vector3;
use tagdeflect_calibrate::guard::{check_board, sigma_text, split_views, split_views_stats, verdict, Grade};
use tagdeflect_calibrate::render::{render_target, RenderOptions};
use tagdeflect_calibrate::report::Coverage;
use tagdeflect_calibrate::solve::{SolveOptions, View};
use tagdeflect_calibrate::target::{TargetDetector, TargetSpec};
use tagdeflect_calibrate::{calibrate_views, detect_views_seen, image_files, CalibrateError};
use tagdeflect_core::camera::{CameraIntrinsics, Pose};

/// `shared/realdata` beside the checkout (or beside a folder above it, for a worktree).
pub(crate) fn realdata_dir() -> PathBuf {
    let here = Path::new(env!("CARGO_MANIFEST_DIR"));
    here.ancestors()
        .skip(1)
        .map(|a| a.join("shared/realdata"))
        .find(|d| d.join("MANIFEST.md").is_file())
        .unwrap_or_else(|| panic!("real test data not found: these tests need ../shared/realdata beside {}", here.display()))
}

/// `calibrate`'s options as the command line's defaults give them, for `target` (no files,
/// no camera; live mode's 20 views in 1 s).
pub(crate) fn plain_options(target: &str) -> tagdeflect_calibrate::CalibrateOptions {
    tagdeflect_calibrate::CalibrateOptions {
        images: None,
        config: None,
        camera: None,
        target: target.into(),
        out: "unused.yaml".into(),
        fix_k3: false,
        fix_aspect_ratio: false,
        aspect_ratio: 1.0,
        zero_tangent_dist: false,
        fix_principal_point: false,
        keep_outliers: false,
        force: false,
        distance_mm: None,
        coverage: None,
        views: 20,
        duration_s: 1.0,
    }
}

fn samples() -> PathBuf {
    realdata_dir().join("opencv-samples-data")
}

fn sample_files(prefixes: &[&str]) -> Vec<PathBuf> {
    image_files(&samples())
        .unwrap()
        .into_iter()
        .filter(|p| {
            let n = p.file_name().unwrap().to_string_lossy();
            prefixes.iter().any(|pre| n.starts_with(pre)) && n.ends_with(".jpg")
        })
        .collect()
}

/// A folder holding copies of `files`.
fn folder(files: &[PathBuf]) -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    for f in files {
        std::fs::copy(f, dir.path().join(f.file_name().unwrap())).unwrap();
    }
    dir
}

fn calibrate_cmd(images: &Path, target: &str, extra: &[&str]) -> (Output, String, String) {
    let out = images.join("cam.yaml");
    let o = Command::new(env!("CARGO_BIN_EXE_tagdeflect"))
        .args(["calibrate", "--images"])
        .arg(images)
        .args(["--target", target, "--out"])
        .arg(&out)
        .args(extra)
        .output()
        .unwrap();
    let (so, se) = (String::from_utf8_lossy(&o.stdout).into_owned(), String::from_utf8_lossy(&o.stderr).into_owned());
    eprintln!("calibrate {target} {extra:?}: {:?}\n{so}{se}", o.status.code());
    (o, so, se)
}

#[test]
fn too_few_views_refused_with_the_reason_unless_forced() {
    let files = sample_files(&["left0"]);
    let dir = folder(&files[..3]);
    let (o, _, err) = calibrate_cmd(dir.path(), "checkerboard:9x6:25", &[]);
    assert_eq!(o.status.code(), Some(2));
    assert!(err.contains("found in 3 views, need at least 10") && err.contains("--force"), "{err}");
    assert!(err.contains("every image showed the target"), "{err}");
    assert!(!err.contains("()"), "no empty brackets: {err}");
    assert!(!dir.path().join("cam.yaml").exists(), "nothing written");
    // --force calibrates, and the verdict says poor: written, but exit 3 so a script stops.
    let (o, out, err) = calibrate_cmd(dir.path(), "checkerboard:9x6:25", &["--force", "--fix-k3"]);
    assert_eq!(o.status.code(), Some(3), "{err}");
    assert!(out.contains("verdict: POOR") && out.contains("3 views (good from 15"), "{out}");
    assert!(out.contains("WARNING --force: calibrated from 3 views"), "{out}");
    assert!(err.contains("calibration verdict POOR (3 views"), "{err}");
    assert!(dir.path().join("cam.yaml").is_file(), "written all the same");
    // No σ larger than the figure it qualifies is printed as a number.
    for l in out.lines().filter(|l| l.contains("deflection")) {
        let um: Vec<f64> = l.split("± ").skip(1).filter_map(|t| t.split(" µm").next()?.parse().ok()).collect();
        assert!(um.iter().all(|v| *v <= 10_000.0), "a σ over the 10 mm it qualifies: {l}");
    }
    // Two views, forced: the absolute minimum is three; the message is complete.
    let dir = folder(&files[..2]);
    let (o, _, err) = calibrate_cmd(dir.path(), "checkerboard:9x6:25", &["--force"]);
    assert_eq!(o.status.code(), Some(2));
    assert!(err.contains("found in 2 views, need at least 3; every image showed the target: take more views"), "{err}");
}

#[test]
fn two_cameras_in_one_folder_are_detected_and_named() {
    let spec: TargetSpec = "checkerboard:9x6:25".parse().unwrap();
    let o = SolveOptions { fix_aspect_ratio: true, ..SolveOptions::default() };
    // One camera alone: no split (the F statistic of the best split found, for the record).
    for prefix in ["left", "right"] {
        let d = detect_views_seen(&sample_files(&[prefix]), &spec).unwrap();
        let run = calibrate_views(d.views, d.width, d.height, &o, false).unwrap();
        let stats = split_views_stats(&run, &o);
        eprintln!(
            "{prefix} alone: best split {:?}",
            stats.as_ref().map(|s| (s.split.f, s.ssr_drop, s.split.minority.len(), s.split.rms_joint_px, s.split.rms_split_px))
        );
        assert!(split_views(&run, &o).is_none(), "{prefix}: {:?}", stats.map(|s| s.split.describe(&run.views)));
    }
    // Both cameras' views in one set: split exactly into the left and the right views.
    let d = detect_views_seen(&sample_files(&["left", "right"]), &spec).unwrap();
    assert_eq!(d.views.len(), 26);
    let run = calibrate_views(d.views, d.width, d.height, &o, false).unwrap();
    let stats = split_views_stats(&run, &o).expect("a split");
    eprintln!("left + right: F {:.1}, SSR drop {:.2}: {}", stats.split.f, stats.ssr_drop, stats.split.describe(&run.views));
    let split = split_views(&run, &o).expect("two cameras found");
    let names = |idx: &[usize]| -> Vec<String> {
        let mut n: Vec<String> = idx.iter().map(|&i| run.views[i].name.clone()).collect();
        n.sort();
        n
    };
    let (a, b) = (names(&split.majority), names(&split.minority));
    let (left, right) = if a[0].starts_with("left") { (a, b) } else { (b, a) };
    let rejected: Vec<&str> = run.rejected.iter().map(|r| r.name.as_str()).collect();
    assert!(left.iter().all(|n| n.starts_with("left")) && right.iter().all(|n| n.starts_with("right")), "{left:?} / {right:?}");
    assert_eq!(left.len() + right.len() + rejected.len(), 26, "every kept view in one group; rejected as outliers: {rejected:?}");
    // The command line refuses, naming both groups.
    let dir = folder(&sample_files(&["left", "right"]));
    let (o, _, err) = calibrate_cmd(dir.path(), "checkerboard:9x6:25", &["--fix-aspect-ratio"]);
    assert_eq!(o.status.code(), Some(2));
    assert!(err.contains("two cameras or two focus settings") && err.contains("left0") && err.contains("right0"), "{err}");
    assert!(!dir.path().join("cam.yaml").exists());
}

/// A strongly distorted 800×600 camera (the one of tests/it/calibrate.rs).
fn sim_camera() -> CameraIntrinsics {
    CameraIntrinsics { width: 800, height: 600, fx: 620.0, fy: 615.0, cx: 408.0, cy: 293.0, dist: [-0.38, 0.17, 0.0012, -0.0009, -0.035] }
}

/// Rendered checkerboard views spread over the image, `n` of them from `seed`.
fn rendered_views(k: &CameraIntrinsics, spec: &TargetSpec, n: usize, seed: u64, prefix: &str) -> Vec<View> {
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let pts = spec.board_points();
    let centre = pts.iter().fold(Vector3::zeros(), |a, p| a + p) / pts.len() as f64;
    let mut det = TargetDetector::new(spec.clone()).unwrap();
    let mut views = Vec::new();
    let mut i = 0;
    while views.len() < n && i < 4 * n {
        let (sx, sy) = (rng.gen_range(-1.0..1.0), rng.gen_range(-1.0..1.0));
        let rvec = [rng.gen_range(-0.5..0.5), rng.gen_range(-0.5..0.5), rng.gen_range(-0.4..0.4)];
        let r = nalgebra::Rotation3::new(Vector3::from(rvec));
        let z = rng.gen_range(450.0..600.0);
        let target = Vector3::new(sx * 0.3 * k.width as f64 / k.fx * z, sy * 0.3 * k.height as f64 / k.fy * z, z);
        let pose = Pose { rotation: r, translation: target - r * centre };
        let img = render_target(spec, k, &pose, &RenderOptions { seed: seed * 1000 + i as u64, noise: 2.0, ..RenderOptions::default() });
        if let Ok(v) = det.detect(&img, &format!("{prefix}{i:02}")) {
            views.push(v);
        }
        i += 1;
    }
    assert_eq!(views.len(), n, "rendered views found");
    views
}

#[test]
fn views_at_another_focus_are_rejected_and_named() {
    let spec: TargetSpec = "checkerboard:9x6:30".parse().unwrap();
    let k = sim_camera();
    // The same camera refocused: focal length +2.5 %, distortion changed with it.
    let refocused = CameraIntrinsics { fx: k.fx * 1.025, fy: k.fy * 1.025, dist: [-0.34, 0.14, 0.0012, -0.0009, -0.035], ..k };
    let mut views = rendered_views(&k, &spec, 14, 7, "focus-a-");
    let o = SolveOptions::default();
    let alone = calibrate_views(views.clone(), 800, 600, &o, false).unwrap();
    let stats = split_views_stats(&alone, &o);
    eprintln!("one focus: best split {:?}", stats.as_ref().map(|s| (s.split.f, s.ssr_drop)));
    assert!(split_views(&alone, &o).is_none());
    views.extend(rendered_views(&refocused, &spec, 4, 8, "focus-b-"));
    let run = calibrate_views(views, 800, 600, &o, false).unwrap();
    eprintln!("mixed: RMS {:.3} px, outliers {:?}", run.calibration.rms_px, run.rejected);
    let split = split_views(&run, &o).expect("the refocused views found");
    eprintln!("{}", split.describe(&run.views));
    let mut minority: Vec<&str> = split.minority.iter().map(|&i| run.views[i].name.as_str()).collect();
    minority.sort();
    let named_as_outliers = run.rejected.iter().filter(|r| r.name.starts_with("focus-b-")).count();
    assert!(minority.iter().all(|n| n.starts_with("focus-b-")), "{minority:?}");
    assert_eq!(minority.len() + named_as_outliers, 4, "{minority:?}");
    // The guarded calibration rejects them and names them, and recovers the first focus.
    let opts = plain_options("checkerboard:9x6:30");
    let (guarded, notes) = tagdeflect_calibrate::calibrate_guarded(run.views.clone(), 800, 600, &[], &[], &spec, &opts).unwrap();
    eprintln!("{notes:?}");
    assert!(notes.iter().any(|n| n.contains("another camera or focus") && n.contains("focus-b-")), "{notes:?}");
    assert!(guarded.views.iter().all(|v| v.name.starts_with("focus-a-")));
    let s = guarded.calibration.sigmas();
    assert!((guarded.calibration.intrinsics.fx - k.fx).abs() < 4.0 * s[0], "fx {} ± {}", guarded.calibration.intrinsics.fx, s[0]);
}

#[test]
fn wrong_board_sizes_are_refused() {
    let files = sample_files(&["left"]);
    let seen_for = |target: &str| {
        let spec: TargetSpec = target.parse().unwrap();
        let d = detect_views_seen(&files, &spec).unwrap();
        let r = check_board(&spec, target, &d.seen, false);
        eprintln!("{target}: {} views; {:?}", d.views.len(), r.as_ref().map_err(|e| e.to_string()));
        for (n, s) in &d.seen {
            eprintln!("  {n}: grid {:?}, labelled {:?}", s.grid, s.labelled);
        }
        (d, r)
    };
    for (target, says) in [
        ("checkerboard:10x7:25", "largest grid seen is 9x6"),
        ("checkerboard:8x5:25", "show more: a 9x6 grid"),
        ("checkerboard:9x5:25", "show more: a 9x6 grid"),
        ("checkerboard:7x6:25", "show more"),
    ] {
        let (_, r) = seen_for(target);
        let e = r.unwrap_err();
        assert!(matches!(e, CalibrateError::BoardMismatch(_)) && e.is_bad_input());
        assert!(e.to_string().contains(says) && e.to_string().contains(target), "{target}: {e}");
    }
    // 6x9 is the same board turned by 90°: the same corners and the same calibration.
    let (a, ra) = seen_for("checkerboard:9x6:25");
    let (b, rb) = seen_for("checkerboard:6x9:25");
    assert!(ra.is_ok() && rb.is_ok());
    let o = SolveOptions { fix_aspect_ratio: true, ..SolveOptions::default() };
    let ka = calibrate_views(a.views, 640, 480, &o, true).unwrap().calibration.intrinsics;
    let kb = calibrate_views(b.views, 640, 480, &o, true).unwrap().calibration.intrinsics;
    assert!((ka.fx - kb.fx).abs() < 1e-6 * ka.fx && (ka.cx - kb.cx).abs() < 1e-6, "{ka:?} vs {kb:?}");
    // The command line: exit 2, nothing written.
    let dir = folder(&files);
    let (o, _, err) = calibrate_cmd(dir.path(), "checkerboard:10x7:25", &[]);
    assert_eq!(o.status.code(), Some(2));
    assert!(err.contains("Is the board 9x6?"), "{err}");
    assert!(!dir.path().join("cam.yaml").exists());
}

#[test]
fn tag_board_of_another_size_is_refused() {
    let k = sim_camera();
    let real: TargetSpec = "tagboard:tag36h11:6x4:32:44".parse().unwrap();
    let pts = real.board_points();
    let centre = pts.iter().fold(Vector3::zeros(), |a, p| a + p) / pts.len() as f64;
    let mut r = nalgebra::Rotation3::new(Vector3::new(0.15, -0.1, 0.05));
    r *= nalgebra::Rotation3::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI);
    let pose = Pose { rotation: r, translation: Vector3::new(0.0, 0.0, 560.0) - r * centre };
    let img = render_target(&real, &k, &pose, &RenderOptions::default());
    for (target, says) in [
        ("tagboard:tag36h11:6x3:32:44", "tags 18..23 of tag36h11 are seen too"),
        ("tagboard:tag36h11:6x5:32:44", "ids 24..29 are in none of the 1 views"),
    ] {
        let spec: TargetSpec = target.parse().unwrap();
        let mut det = TargetDetector::new(spec.clone()).unwrap();
        let (_, seen) = det.detect_seen(&img, "board.png").unwrap();
        let e = check_board(&spec, target, &[("board.png".into(), seen.clone())], false).unwrap_err();
        eprintln!("{target}: {e}");
        assert!(e.to_string().contains(says), "{e}");
        assert!(check_board(&spec, target, &[("board.png".into(), seen)], true).is_ok(), "--force lets it through");
    }
    let mut det = TargetDetector::new(real.clone()).unwrap();
    let (_, seen) = det.detect_seen(&img, "board.png").unwrap();
    assert_eq!(seen.ids, (0..24).collect::<Vec<u32>>());
    assert!(check_board(&real, "tagboard:tag36h11:6x4:32:44", &[("board.png".into(), seen)], false).is_ok());
}

#[test]
fn verdict_on_the_opencv_samples_names_k3_and_the_corners() {
    let spec: TargetSpec = "checkerboard:9x6:25".parse().unwrap();
    let d = detect_views_seen(&sample_files(&["left"]), &spec).unwrap();
    let o = SolveOptions { fix_aspect_ratio: true, ..SolveOptions::default() };
    let run = calibrate_views(d.views.clone(), d.width, d.height, &o, false).unwrap();
    let pts: Vec<_> = run.views.iter().flat_map(|v| v.image.iter().copied()).collect();
    let cov = Coverage::new(640, 480, &pts);
    let v = verdict(&run, &cov, 500.0);
    eprintln!("{}", v.text());
    // With k3 free the image corners are extrapolated far beyond the views: poor.
    assert_eq!(v.grade, Grade::Poor, "13 views without the image corners, k3 free");
    assert!(v.hints.iter().any(|h| h.contains("--fix-k3")), "k3 undetermined: {:?}", v.hints);
    assert!(v.hints.iter().any(|h| h.contains("corner")), "{:?}", v.hints);
    assert!(v.reasons.iter().any(|(g, r)| *g == Grade::Usable && r.contains("13 views")));
    // With k3 fixed the hint goes away.
    let o3 = SolveOptions { fix_k3: true, ..o };
    let run3 = calibrate_views(d.views, d.width, d.height, &o3, false).unwrap();
    let v3 = verdict(&run3, &cov, 500.0);
    eprintln!("with --fix-k3:\n{}", v3.text());
    assert!(!v3.hints.iter().any(|h| h.contains("--fix-k3")), "{:?}", v3.hints);
    // Rendered views that fill the image with 20 views: good.
    let k = sim_camera();
    let cb: TargetSpec = "checkerboard:9x6:30".parse().unwrap();
    let views = rendered_views(&k, &cb, 20, 21, "sim");
    let run = calibrate_views(views, 800, 600, &SolveOptions { fix_k3: true, ..SolveOptions::default() }, false).unwrap();
    let pts: Vec<_> = run.views.iter().flat_map(|v| v.image.iter().copied()).collect();
    let v = verdict(&run, &Coverage::new(800, 600, &pts), 500.0);
    eprintln!("{}", v.text());
    assert!(v.grade <= Grade::Usable, "{}", v.text());
}

#[test]
fn an_undetermined_sigma_says_so_instead_of_a_number() {
    assert_eq!(sigma_text(181.5857, 10.0, 1e3, 1, "µm"), "undetermined", "181 mm on a 10 mm deflection");
    assert_eq!(sigma_text(f64::NAN, 10.0, 1e3, 1, "µm"), "undetermined");
    assert_eq!(sigma_text(f64::INFINITY, 0.5, 1e6, 0, "ppm"), "undetermined");
    assert_eq!(sigma_text(0.0123, 10.0, 1e3, 1, "µm"), "± 12.3 µm");
    assert_eq!(sigma_text(0.00044 / 533.7, 0.5, 1e6, 0, "ppm"), "± 1 ppm");
}

/// A black 8-bit grey PNG of `width`x`height`, streamed by Python's zlib (a 20000² image is
/// ~400 KB of file for 400 Mpx), whose image data holds its first `rows` rows (`rows` <
/// `height`: the header's size over a few bytes of data).
fn black_png(path: &Path, width: u32, height: u32, rows: u32) {
    let script = r#"
import struct, sys, zlib
w, h, rows, out = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
def chunk(kind, data):
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xffffffff)
z = zlib.compressobj(9)
row = b"\0" * (w + 1)
idat = b"".join(z.compress(row) for _ in range(rows)) + z.flush()
with open(out, "wb") as f:
    f.write(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0)) + chunk(b"IDAT", idat) + chunk(b"IEND", b""))
"#;
    let o = Command::new(crate::common::python())
        .args(["-c", script, &width.to_string(), &height.to_string(), &rows.to_string()])
        .arg(path)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
}

#[test]
fn images_of_absurd_size_are_refused_from_their_header_before_decoding() {
    // The thin image as found; a 20 000² header over one row of data (refused from the header,
    // it costs nothing; decoded, it fails only after the decoder took the header's size); the
    // 20 000² image as found (389 KB; decoded: ~18 s and ~2 GB), after the small one, so a
    // build without the cap fails on the small one first.
    let cases = [
        (1, 100_000, 100_000, "a side under 32 px"),
        (20_000, 20_000, 1, "more than 268435456 pixels"),
        (20_000, 20_000, 20_000, "more than 268435456 pixels"),
    ];
    for (w, h, rows, why) in cases {
        let dir = tempfile::tempdir().unwrap();
        black_png(&dir.path().join("view.png"), w, h, rows);
        let (o, _, err) = calibrate_cmd(dir.path(), "checkerboard:9x6:25", &[]);
        assert_eq!(o.status.code(), Some(2), "{w}x{h}: {err}");
        assert!(err.contains(&format!("is {w}x{h} (from its header; nothing decoded): {why}")), "{err}");
        assert!(err.lines().count() < 20, "one error, not a flood: {err}");
    }
}
