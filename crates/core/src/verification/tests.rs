use super::*;

fn rig() -> (BackgroundConfig, SpecimenConfig, Vec<CameraConfig>) {
    let bg: BackgroundConfig = toml::from_str(
        r#"family = "tag25h9"
size_mm = 40.0
[[tag]]
id = 0
corners_mm = [[0, 0, 0], [40, 0, 0], [40, 0, 40], [0, 0, 40]]"#,
    )
    .unwrap();
    let sp = SpecimenConfig { family: "tag36h11".parse().unwrap(), size_mm: 20.0, tags: vec![], beam: None };
    let cam: CameraConfig =
        toml::from_str("name = \"left\"\nwidth = 1280\nheight = 960\nfx = 1500.0\nfy = 1500.0\ncx = 640.0\ncy = 480.0").unwrap();
    (bg, sp, vec![cam])
}

/// A certificate file as `tagdeflect verify` writes it (the keys read here).
fn certificate(dir: &Path, name: &str, geometry: Option<&str>, calibration_sha: &str) -> PathBuf {
    let mut rig = serde_json::json!({ "calibration_files": [{ "path": "/lab/left.yaml", "sha256": calibration_sha }] });
    if let Some(g) = geometry {
        rig["geometry_sha256"] = g.into();
    }
    let doc = serde_json::json!({
        "format": "tagdeflect-verification/1", "class_iso9513": "0.5", "date": "2026-12-01",
        "issued_utc": "2026-12-01T10:00:00Z", "u_k2_mm": 0.0021, "rig": rig, "steps": [],
    });
    let path = dir.join(name);
    std::fs::write(&path, doc.to_string()).unwrap();
    path
}

fn ns(rfc3339: &str) -> i64 {
    parse_rfc3339_ns(rfc3339).unwrap()
}

fn scratch(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("tagdeflect-verification-{name}-{}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn calibration(path: &str, sha256: &str) -> Vec<HashedPath> {
    vec![HashedPath { path: path.into(), sha256: sha256.into() }]
}

#[test]
fn a_certificate_of_this_rig_within_its_period_is_in_force() {
    let (bg, sp, cams) = rig();
    let g = geometry_sha256([0.0, 0.0, 1.0], &bg, &sp, &cams);
    let dir = scratch("ok");
    let path = certificate(&dir, "verification.json", Some(&g), "aa");
    let now = RigNow { calibration_files: calibration("/other/place/left.yaml", "aa"), geometry_sha256: g, ..RigNow::default() };
    let f = assess(&path, 30, &now, ns("2026-12-30T23:00:00Z")).unwrap();
    assert!(f.stale.is_empty(), "{:?}", f.stale);
    assert_eq!((f.class_iso9513.as_str(), f.date.as_str(), f.valid_until.as_str()), ("0.5", "2026-12-01", "2026-12-30"));
    assert_eq!(f.id.len(), 64);
    assert!(f.describe().contains("in force"), "{}", f.describe());
    // A bump before the certificate was issued does not make it stale.
    let earlier = RigNow { bumps: vec![("left".into(), ns("2026-12-01T09:00:00Z"))], ..now };
    assert!(assess(&path, 30, &earlier, ns("2026-12-02T00:00:00Z")).unwrap().stale.is_empty());
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn each_change_since_the_verification_makes_it_stale_with_its_reason() {
    let (bg, sp, cams) = rig();
    let g = geometry_sha256([0.0, 0.0, 1.0], &bg, &sp, &cams);
    let dir = scratch("stale");
    let path = certificate(&dir, "verification.json", Some(&g), "aa");
    let now = RigNow { calibration_files: calibration("left.yaml", "aa"), geometry_sha256: g.clone(), ..RigNow::default() };
    let in_period = ns("2026-12-05T00:00:00Z");
    let reasons = |n: &RigNow, t: i64| assess(&path, 30, n, t).unwrap().stale;
    // Recalibrated.
    let recal = RigNow { calibration_files: calibration("left.yaml", "bb"), ..now.clone() };
    assert!(reasons(&recal, in_period).iter().any(|r| r.contains("left.yaml changed")));
    // A background tag moved in the config.
    let mut bg2 = bg.clone();
    bg2.tags[0].corners_mm[0][0] += 0.5;
    let moved = RigNow { geometry_sha256: geometry_sha256([0.0, 0.0, 1.0], &bg2, &sp, &cams), ..now.clone() };
    assert!(reasons(&moved, in_period).iter().any(|r| r.contains("geometry changed")));
    // A camera bumped after the certificate was issued.
    let bumped = RigNow { bumps: vec![("left".into(), ns("2026-12-03T08:00:00Z"))], ..now.clone() };
    assert!(reasons(&bumped, in_period).iter().any(|r| r.contains("camera left was bumped at 2026-12-03 08:00:00 UTC")));
    // Its period over: the 30th day is the last one.
    let late = reasons(&now, ns("2026-12-31T10:00:01Z"));
    assert!(late.iter().any(|r| r.contains("ended on 2026-12-30")), "{late:?}");
    // The beam's dimensions are not the rig's geometry.
    let mut sp2 = sp.clone();
    sp2.beam = Some(toml::from_str("span_mm = 450.0\nwidth_mm = 150.0\ndepth_mm = 150.0").unwrap());
    assert_eq!(geometry_sha256([0.0, 0.0, 1.0], &bg, &sp2, &cams), g);
    // A certificate that does not record the geometry cannot be matched: stale, said why.
    let old = certificate(&dir, "old.json", None, "aa");
    assert!(assess(&old, 30, &now, in_period).unwrap().stale.iter().any(|r| r.contains("does not record")));
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn a_camera_away_from_its_verified_pose_makes_it_stale_and_pose_noise_does_not() {
    let (bg, sp, cams) = rig();
    let g = geometry_sha256([0.0, 0.0, 1.0], &bg, &sp, &cams);
    let dir = scratch("moved");
    let path = certificate(&dir, "verification.json", Some(&g), "aa");
    let pose = Pose::from_rvec_tvec([0.1, -0.2, 0.05], [10.0, -40.0, 2000.0]);
    let placed = CameraPlacement::from_pose("left", &pose);
    let mut doc: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    doc["rig"]["camera_poses"] = serde_json::to_value(vec![placed.clone()]).unwrap();
    std::fs::write(&path, doc.to_string()).unwrap();
    let now = |p: &Pose| RigNow {
        calibration_files: calibration("left.yaml", "aa"),
        geometry_sha256: g.clone(),
        camera_poses: vec![CameraPlacement::from_pose("left", p)],
        ..RigNow::default()
    };
    let reasons = |p: &Pose| assess(&path, 30, &now(p), ns("2026-12-05T00:00:00Z")).unwrap().stale;
    // Posed again with the noise of a pose (0.01°, 0.1 mm): in force.
    let jitter = Pose::from_rvec_tvec([0.0, 0.01f64.to_radians(), 0.0], [0.1, 0.0, 0.0]).compose(&pose);
    assert!(reasons(&jitter).is_empty(), "{:?}", reasons(&jitter));
    // Turned 0.2° while no daemon ran: stale, with the figures.
    let turned = Pose::from_rvec_tvec([0.2f64.to_radians(), 0.0, 0.0], [0.0; 3]).compose(&pose);
    let r = reasons(&turned);
    assert!(r.iter().any(|r| r.contains("camera left is") && r.contains("0.200°")), "{r:?}");
    // Shifted 3 mm: stale.
    let shifted = Pose { translation: pose.translation + nalgebra::Vector3::new(3.0, 0.0, 0.0), ..pose };
    assert!(reasons(&shifted).iter().any(|r| r.contains("3.00 mm")), "{:?}", reasons(&shifted));
    // A camera not posed now is not compared.
    let unknown = RigNow { camera_poses: vec![], ..now(&turned) };
    assert!(assess(&path, 30, &unknown, ns("2026-12-05T00:00:00Z")).unwrap().stale.is_empty());
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn an_unreadable_certificate_is_named() {
    let dir = scratch("bad");
    let path = dir.join("verification.json");
    std::fs::write(&path, "{\"class_iso9513\": 1}").unwrap();
    let e = assess(&path, 30, &RigNow::default(), 0).unwrap_err();
    assert!(e.to_string().starts_with(&path.display().to_string()) && e.to_string().contains("verification.json"), "{e}");
    assert!(assess(&dir.join("missing.json"), 30, &RigNow::default(), 0).unwrap_err().to_string().contains("cannot read"));
    std::fs::remove_dir_all(dir).unwrap();
    assert!(VerificationConfig { certificate: "v.json".into(), valid_days: 0 }.validate().unwrap_err().key.contains("valid_days"));
}
