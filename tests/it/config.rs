//! Config parsing, validation errors (file, line, key) and calibration import.

use std::path::{Path, PathBuf};
use tagdeflect::config::{load_calibration, Config, ConfigError, TagRole, ValueType, WordOrder};

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn realdata() -> PathBuf {
    let p = root().join("../shared/realdata");
    assert!(p.is_dir(), "real test data missing at {}: the tests need ../shared/realdata", p.display());
    p
}

const GOOD: &str = r#"
[world]
up = [0.0, 0.0, 2.0]

[sync]
tolerance_ms = 8.0

[[camera]]
name = "left"
source = "sim"
width = 640
height = 480
fx = 500.0
fy = 500.0
cx = 319.5
cy = 239.5
dist = [-0.1, 0.01, 0.0, 0.0]

[background]
family = "tag25h9"
size_mm = 60.0
[[background.tag]]
id = 3
corners_mm = [[0.0, 0.0, 0.0], [60.0, 0.0, 0.0], [60.0, 0.0, 60.0], [0.0, 0.0, 60.0]]

[specimen]
family = "tag36h11"
size_mm = 30.0
[[specimen.tag]]
id = 0
role = "support"
[[specimen.tag]]
id = 7
role = "midspan"
[[specimen.tag]]
id = 8

[utm]
address = "127.0.0.1:5020"
[utm.load]
register = 4
type = "i32"
word_order = "little"
scale = 0.001
"#;

fn parse(text: &str) -> Result<Config, ConfigError> {
    Config::from_toml_str(text, Path::new("/lab/rig.toml"))
}

/// Replaces the first occurrence of `from` in the good config.
fn bad(from: &str, to: &str) -> ConfigError {
    assert!(GOOD.contains(from), "test setup: {from:?} not in the config");
    parse(&GOOD.replacen(from, to, 1)).expect_err("must be rejected")
}

fn line_of(text: &str, needle: &str) -> usize {
    text[..text.find(needle).expect("needle")].lines().count() + if needle.starts_with('\n') { 1 } else { 0 }
}

#[test]
fn good_config_parses_with_defaults_and_normalised_up() {
    let c = parse(GOOD).unwrap();
    assert_eq!(c.world.up, [0.0, 0.0, 1.0]);
    assert_eq!(c.sync.tolerance_ms, 8.0);
    assert_eq!(c.cameras[0].dist, [-0.1, 0.01, 0.0, 0.0, 0.0]);
    assert_eq!(c.role_of(7), Some(TagRole::Midspan));
    assert_eq!(c.role_of(8), None);
    let u = c.utm.as_ref().unwrap();
    assert_eq!((u.unit, u.poll_hz), (1, 50.0));
    assert_eq!(u.load.value_type, ValueType::I32);
    assert_eq!(u.load.word_order, WordOrder::Cdab);
    assert!(u.stroke.is_none());
}

#[test]
fn config_round_trips_through_toml() {
    let c = parse(GOOD).unwrap();
    let text = c.to_toml_string();
    let again = parse(&text).unwrap_or_else(|e| panic!("{e}\n{text}"));
    assert_eq!(c, again);
}

#[test]
fn example_configs_are_valid() {
    for name in ["one-camera.toml", "three-camera.toml"] {
        let c = Config::load(&root().join("config").join(name)).unwrap_or_else(|e| panic!("{e}"));
        assert!(!c.cameras.is_empty());
    }
    let three = Config::load(&root().join("config/three-camera.toml")).unwrap();
    assert_eq!(three.cameras.len(), 3);
    assert_eq!(three.cameras[1].fx, 2400.0, "intrinsics imported from the calibration file");
}

#[test]
fn unknown_key_names_file_line_and_key() {
    let e = bad("fx = 500.0", "fx = 500.0\nfocal = 3");
    let s = e.to_string();
    assert!(s.starts_with("/lab/rig.toml:"), "{s}");
    assert_eq!(e.key.as_deref(), Some("focal"), "{s}");
    assert!(e.line.is_some(), "{s}");
    assert!(s.contains("unknown field"), "{s}");
}

#[test]
fn wrong_type_names_the_line() {
    let text = GOOD.replacen("width = 640", "width = \"wide\"", 1);
    let e = parse(&text).unwrap_err();
    assert_eq!(e.line, Some(line_of(&text, "width = \"wide\"") + 1), "{e}");
    assert!(e.to_string().contains("invalid type"), "{e}");
}

#[test]
fn duplicate_camera_name() {
    let text = GOOD.replacen(
        "[background]",
        "[[camera]]\nname = \"left\"\nwidth = 10\nheight = 10\nfx = 1.0\nfy = 1.0\ncx = 0.0\ncy = 0.0\n\n[background]",
        1,
    );
    let e = parse(&text).unwrap_err();
    assert_eq!(e.key.as_deref(), Some("camera[1].name"));
    assert!(e.message.contains("duplicate camera name"), "{e}");
    assert!(e.line.is_some());
}

#[test]
fn duplicate_tag_ids_within_a_family() {
    let e = bad("id = 8", "id = 7");
    assert_eq!(e.key.as_deref(), Some("specimen.tag[2].id"), "{e}");
    assert!(e.message.contains("duplicate specimen tag id 7"), "{e}");
    let text = GOOD.replacen(
        "\n[specimen]",
        "\n[[background.tag]]\nid = 3\ncorners_mm = [[0.0, 0.0, 0.0], [60.0, 0.0, 0.0], [60.0, 0.0, 60.0], [0.0, 0.0, 60.0]]\n\n[specimen]",
        1,
    );
    let e = parse(&text).unwrap_err();
    assert_eq!(e.key.as_deref(), Some("background.tag[1].id"), "{e}");
}

#[test]
fn background_corners_must_be_four_and_a_square_of_the_configured_size() {
    let three = bad("[60.0, 0.0, 60.0], [0.0, 0.0, 60.0]]", "[60.0, 0.0, 60.0]]");
    assert!(three.message.contains("expected 4 corners"), "{three}");
    assert_eq!(three.key.as_deref(), Some("background.tag[0].corners_mm"));
    let skew = bad("[60.0, 0.0, 60.0], [0.0, 0.0, 60.0]]", "[90.0, 0.0, 60.0], [0.0, 0.0, 60.0]]");
    assert!(skew.message.contains("not a square"), "{skew}");
    let degenerate = bad("[60.0, 0.0, 0.0], [60.0, 0.0, 60.0]", "[0.0, 0.0, 0.0], [60.0, 0.0, 60.0]");
    assert!(degenerate.message.contains("degenerate"), "{degenerate}");
    let size = bad("size_mm = 60.0", "size_mm = 100.0");
    assert!(size.message.contains("does not match background.size_mm"), "{size}");
    let line = line_of(GOOD, "corners_mm") + 1;
    assert_eq!(size.line, Some(line), "{size}");
}

#[test]
fn one_family_for_both_sets_needs_distinct_ids() {
    let text = GOOD.replacen("family = \"tag25h9\"", "family = \"tag36h11\"", 1).replacen("id = 3\ncorners_mm", "id = 7\ncorners_mm", 1);
    let e = parse(&text).unwrap_err();
    assert!(e.message.contains("id 7 is both a background and a specimen tag of tag36h11"), "{e}");
    assert!(e.line.is_some());
    // Distinct ids in one family are fine.
    let ok = GOOD.replacen("family = \"tag25h9\"", "family = \"tag36h11\"", 1);
    parse(&ok).unwrap();
}

#[test]
fn role_must_be_support_or_midspan() {
    let e = bad("role = \"midspan\"", "role = \"centre\"");
    assert!(e.message.contains("unknown variant"), "{e}");
    assert!(e.message.contains("support") && e.message.contains("midspan"), "{e}");
    assert!(e.line.is_some());
}

#[test]
fn tolerance_must_be_positive() {
    for v in ["0.0", "-3.0"] {
        let e = bad("tolerance_ms = 8.0", &format!("tolerance_ms = {v}"));
        assert_eq!(e.key.as_deref(), Some("sync.tolerance_ms"));
        assert_eq!(e.line, Some(line_of(GOOD, "tolerance_ms") + 1), "{e}");
    }
}

#[test]
fn other_checks_name_their_key() {
    let cases = [
        ("family = \"tag36h11\"", "family = \"tag99\"", "specimen.family", "unknown tag family"),
        ("fx = 500.0", "fx = -5.0", "camera[0].fx", "positive"),
        ("source = \"sim\"", "source = \"usb0\"", "camera[0].source", "not a camera source"),
        ("dist = [-0.1, 0.01, 0.0, 0.0]", "dist = [-0.1]", "camera[0].dist", "4 or 5"),
        ("id = 3", "id = 35", "background.tag[0].id", "tag25h9 has ids 0..34"),
        ("word_order = \"little\"", "word_order = \"MIXED\"", "word_order", "unknown variant"),
        ("up = [0.0, 0.0, 2.0]", "up = [0.0, 0.0, 0.0]", "world.up", "non-zero"),
        ("size_mm = 30.0", "size_mm = 0.0", "specimen.size_mm", "positive"),
    ];
    for (from, to, key, msg) in cases {
        let e = bad(from, to);
        assert!(e.key.as_deref().is_some_and(|k| k.ends_with(key)), "{from} -> {to}: key {:?} ({e})", e.key);
        assert!(e.message.contains(msg), "{from} -> {to}: {e}");
        assert!(e.line.is_some(), "{from} -> {to}: no line ({e})");
    }
}

#[test]
fn missing_sections_are_named() {
    let e = parse(&GOOD.replace("[[camera]]", "[[kamera]]")).unwrap_err();
    assert!(e.to_string().contains("kamera"), "{e}");
    let no_bg = GOOD.split("[background]").next().unwrap().to_string()
        + "[specimen]\nfamily = \"tag36h11\"\nsize_mm = 30.0\n[[specimen.tag]]\nid = 0\n";
    let e = parse(&no_bg).unwrap_err();
    assert_eq!(e.key.as_deref(), Some("background"), "{e}");
}

#[test]
fn opencv_yaml_calibration_imports_the_reference_values() {
    let c = load_calibration(&realdata().join("opencv-samples-data/left_intrinsics.yml")).unwrap();
    assert_eq!((c.width, c.height), (640, 480));
    assert!((c.fx - 535.9157).abs() < 1e-3 && (c.fy - 535.9157).abs() < 1e-3, "{c:?}");
    assert!((c.cx - 342.2832).abs() < 1e-3 && (c.cy - 235.5708).abs() < 1e-3, "{c:?}");
    let want = [-0.26637, -0.03859, 0.00178, -0.00028, 0.23839];
    for (a, b) in c.dist.iter().zip(want) {
        assert!((a - b).abs() < 1e-5, "{:?}", c.dist);
    }
}

#[test]
fn json_calibration_and_config_reference() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(
        dir.path().join("cam.json"),
        r#"{"image_width": 800, "image_height": 600,
            "camera_matrix": [[700.0, 0, 399.5], [0, 701.0, 299.5], [0, 0, 1]],
            "distortion_coefficients": {"rows": 1, "cols": 5, "data": [-0.2, 0.05, 0.001, 0.002, 0.0]}}"#,
    )
    .unwrap();
    let text = GOOD.replacen(
        "width = 640\nheight = 480\nfx = 500.0\nfy = 500.0\ncx = 319.5\ncy = 239.5\ndist = [-0.1, 0.01, 0.0, 0.0]",
        "calibration = \"cam.json\"",
        1,
    );
    let cfg_path = dir.path().join("rig.toml");
    std::fs::write(&cfg_path, &text).unwrap();
    let c = Config::load(&cfg_path).unwrap_or_else(|e| panic!("{e}"));
    let cam = &c.cameras[0];
    assert_eq!((cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy), (800, 600, 700.0, 701.0, 399.5, 299.5));
    assert_eq!(cam.dist, [-0.2, 0.05, 0.001, 0.002, 0.0]);
    // A broken calibration file is named in the error.
    std::fs::write(dir.path().join("cam.json"), "{\"camera_matrix\": [1, 2]}").unwrap();
    let e = Config::load(&cfg_path).unwrap_err();
    assert!(e.message.contains("cam.json") && e.message.contains("9 numbers"), "{e}");
    assert_eq!(e.key.as_deref(), Some("camera[0].calibration"));
}

#[test]
fn unreadable_file_is_named() {
    let e = Config::load(Path::new("/nonexistent/rig.toml")).unwrap_err();
    assert!(e.to_string().contains("/nonexistent/rig.toml") && e.message.contains("cannot read"), "{e}");
}

#[test]
fn every_limit_a_component_has_is_checked_when_the_config_is_read() {
    // The detector's own range (it used to pass here and fail only when `run` built the
    // detector, after READY=1).
    let text = format!("{GOOD}\n[measure]\nquad_decimate = 20.0\n");
    let e = parse(&text).unwrap_err();
    assert_eq!(e.key.as_deref(), Some("measure.quad_decimate"), "{e}");
    assert!(e.message.contains("16"), "{e}");
    assert!(e.line.is_some(), "{e}");
    let e = parse(&format!("{GOOD}\n[measure]\ndetector_threads = 1000\n")).unwrap_err();
    assert_eq!(e.key.as_deref(), Some("measure.detector_threads"), "{e}");
    // `[sim]` is validated like every other table.
    let e = parse(&format!("{GOOD}\n[sim]\ncameras = 7\n")).unwrap_err();
    assert_eq!(e.key.as_deref(), Some("sim.cameras"), "{e}");
    assert!(e.line.is_some(), "{e}");
    // Simulated cameras are the rig's cameras, by name and in order.
    let e = bad("name = \"left\"", "name = \"front\"");
    assert_eq!(e.key.as_deref(), Some("camera[0].name"), "{e}");
    assert!(e.message.contains("simulated rig") && e.message.contains("left"), "{e}");
    assert_eq!(e.line, Some(line_of(GOOD, "name = \"left\"") + 1), "{e}");
}

#[test]
fn camera_sources_are_parsed_once_and_written_back_as_given() {
    use tagdeflect::config::CameraSource;
    for (text, want) in [
        ("v4l2:/dev/v4l/by-id/usb-cam-video-index0", CameraSource::V4l2 { path: "/dev/v4l/by-id/usb-cam-video-index0".into() }),
        ("aravis:Basler-1234", CameraSource::Aravis { device: "Basler-1234".into() }),
        ("sim", CameraSource::Sim),
        ("recording:/data/rec", CameraSource::Recording { dir: "/data/rec".into() }),
    ] {
        let got = CameraSource::parse(text).unwrap();
        assert_eq!(got, want);
        assert_eq!(got.to_string(), text);
    }
    for bad_source in ["v4l2:", "aravis:  ", "usb0", "recording:"] {
        let e = CameraSource::parse(bad_source).unwrap_err().to_string();
        assert!(e.contains("expected"), "{bad_source}: {e}");
    }
    // A recording folder is relative to the config's folder.
    let c = parse(&GOOD.replacen("source = \"sim\"", "source = \"recording:runs/r1\"", 1)).unwrap();
    assert_eq!(c.cameras[0].source, CameraSource::Recording { dir: "/lab/runs/r1".into() });
    // A config written back (recordings carry it) reads the same.
    let again = Config::from_toml_str(&c.to_toml_string(), Path::new("/lab/rig.toml")).unwrap();
    assert_eq!(again.cameras[0].source, c.cameras[0].source);
}
