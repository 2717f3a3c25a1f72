//! The tests' unit tests: a test from start to stop, and one resumed after a restart.

use std::path::{Path, PathBuf};

use sha2::Digest;
use tagdeflect_core::feed::FeedLine;

use super::folder::hex;
use super::{LabTests, TestError, TestMeta, TestRecord, ZERO_SETS};
use tagdeflect_core::feed::FeedTag;

fn line(t_ns: i64, z: f64, net: f64) -> FeedLine {
    let tag = FeedTag { id: 1, pos_mm: [10.0, 0.0, z], disp_mm: [0.0, 0.0, z], views: 2, sigma_mm: Some([0.01; 3]), reproj_px: None };
    FeedLine { seq: t_ns as u64, t_ns, tags: vec![tag], net_deflection_mm: Some(net), ..FeedLine::default() }
}

#[test]
fn a_test_counts_from_the_mean_of_its_first_sets_and_keeps_its_folder() {
    let dir = tempfile::tempdir().unwrap();
    let tests = LabTests::new(dir.path(), "[world]\n".into(), Vec::new(), None).unwrap();
    assert!(matches!(tests.stop(), Err(TestError::Conflict(_))));
    tests.start(TestMeta { specimen: "B12".into(), ..TestMeta::default() }).unwrap();
    assert!(matches!(tests.start(TestMeta { specimen: "B13".into(), ..TestMeta::default() }), Err(TestError::Conflict(_))));
    // Five sets at rest around z = 5 ± 0.01, then the beam deflects by 1 mm.
    let rest = [5.01, 4.99, 5.0, 5.02, 4.98];
    let mut out = Vec::new();
    for (k, z) in rest.iter().enumerate() {
        let mut l = line(k as i64, *z, *z * 0.1);
        tests.apply(&mut l);
        tests.on_line(&l);
        out.push(l);
    }
    let mut l = line(10, 4.0, 0.4);
    tests.apply(&mut l);
    tests.on_line(&l);
    assert!(out.iter().all(|l| l.test.as_ref().unwrap().zeroing));
    assert_eq!(out[0].events.iter().map(|e| e.kind.as_str()).collect::<Vec<_>>(), vec!["start"]);
    let t = l.test.as_ref().unwrap();
    assert!(!t.zeroing && t.specimen == "B12");
    assert!((l.tags[0].disp_mm[2] + 1.0).abs() < 1e-9, "{:?}", l.tags[0].disp_mm);
    assert!((l.net_deflection_mm.unwrap() + 0.1).abs() < 1e-9);
    tests.mark(Some("first crack seen".into())).unwrap();
    let stopped = tests.stop().unwrap();
    let mut after = line(11, 4.0, 0.4);
    tests.apply(&mut after);
    assert!(after.test.is_none());
    assert_eq!(after.events.iter().map(|e| e.kind.as_str()).collect::<Vec<_>>(), vec!["mark", "stop"]);
    let record: TestRecord = serde_json::from_str(&std::fs::read_to_string(stopped.folder.join("test.json")).unwrap()).unwrap();
    assert_eq!(record.lines, 6);
    assert_eq!(record.events.iter().map(|e| e.kind.as_str()).collect::<Vec<_>>(), vec!["start", "mark", "stop"]);
    for f in ["feed.jsonl", "utm.jsonl", "tagdeflect.toml"] {
        let want = hex(&sha2::Sha256::digest(std::fs::read(stopped.folder.join(f)).unwrap()));
        assert_eq!(record.sha256.get(f), Some(&want), "{f}");
    }
    assert!(!dir.path().join(".running.json").exists(), "a stopped test leaves no state behind");
    assert!(TestMeta { specimen: "<b>".into(), ..TestMeta::default() }.validate().is_err());
    assert!(TestMeta { specimen: "B1".into(), standard: Some("iso".into()), ..TestMeta::default() }.validate().is_err());
}

#[test]
fn a_test_running_when_the_daemon_stops_resumes_from_its_zero() {
    let dir = tempfile::tempdir().unwrap();
    let id = {
        let tests = LabTests::new(dir.path(), String::new(), Vec::new(), None).unwrap();
        tests.start(TestMeta { specimen: "B7".into(), ..TestMeta::default() }).unwrap();
        for k in 0..ZERO_SETS {
            let mut l = line(k as i64, 5.0 + 0.01 * k as f64, 0.5);
            tests.apply(&mut l);
            tests.on_line(&l);
        }
        tests.status()["id"].as_str().unwrap().to_string()
        // Dropped without a stop: the daemon died.
    };
    let tests = LabTests::new(dir.path(), String::new(), Vec::new(), None).unwrap();
    let st = tests.status();
    assert_eq!(st["state"], "running");
    assert_eq!(st["id"], id.as_str());
    let mut l = line(100, 4.02, 0.4);
    tests.apply(&mut l);
    assert_eq!(l.events.iter().map(|e| e.kind.as_str()).collect::<Vec<_>>(), vec!["resume"]);
    assert!(!l.test.as_ref().unwrap().zeroing, "the zero is kept, not taken again");
    // The zero was the mean of 5.00 .. 5.04 = 5.02.
    assert!((l.tags[0].disp_mm[2] + 1.0).abs() < 1e-9, "{:?}", l.tags[0].disp_mm);
    tests.on_line(&l);
    let stopped = tests.stop().unwrap();
    let record: TestRecord = serde_json::from_str(&std::fs::read_to_string(stopped.folder.join("test.json")).unwrap()).unwrap();
    assert_eq!(record.events.iter().map(|e| e.kind.as_str()).collect::<Vec<_>>(), vec!["start", "resume", "stop"]);
    assert_eq!(std::fs::read_to_string(stopped.folder.join("feed.jsonl")).unwrap().lines().count(), ZERO_SETS + 1);
}

#[test]
fn a_stale_running_state_is_moved_aside_and_the_daemon_starts() {
    let dir = tempfile::tempdir().unwrap();
    let folder = {
        let tests = LabTests::new(dir.path(), String::new(), Vec::new(), None).unwrap();
        tests.start(TestMeta { specimen: "B8".into(), ..TestMeta::default() }).unwrap();
        PathBuf::from(tests.status()["folder"].as_str().unwrap())
        // Dropped without a stop: the daemon died.
    };
    let aside = |d: &Path| -> Vec<String> {
        std::fs::read_dir(d)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .filter(|n| n.starts_with(".running.json.stale-"))
            .collect()
    };
    // Its folder deleted meanwhile, then a state that is not JSON: each moved aside, each start idle.
    std::fs::remove_dir_all(&folder).unwrap();
    let tests = LabTests::new(dir.path(), String::new(), Vec::new(), None).expect("a stale state does not stop the start");
    assert_eq!(tests.status()["state"], "idle");
    assert!(!dir.path().join(".running.json").exists());
    assert_eq!(aside(dir.path()).len(), 1, "kept, under another name");
    tests.start(TestMeta { specimen: "B9".into(), ..TestMeta::default() }).unwrap();
    drop(tests);
    std::fs::write(dir.path().join(".running.json"), "{\"rec").unwrap();
    let tests = LabTests::new(dir.path(), String::new(), Vec::new(), None).expect("an unreadable state does not stop the start");
    assert_eq!(tests.status()["state"], "idle");
    assert_eq!(aside(dir.path()).len(), 2);
}

/// The state of a test whose stop was under way when the daemon died says "stopping": the
/// next start completes its folder (`test.json` with the stop) on a thread, does not resume it,
/// refuses a start meanwhile only, and removes the state once the folder is complete.
#[test]
fn a_test_stopping_when_the_daemon_dies_is_completed_at_the_next_start() {
    let dir = tempfile::tempdir().unwrap();
    let folder = {
        let tests = LabTests::new(dir.path(), String::new(), Vec::new(), None).unwrap();
        tests.start(TestMeta { specimen: "B5".into(), ..TestMeta::default() }).unwrap();
        for k in 0..ZERO_SETS + 2 {
            let mut l = line(k as i64, 5.0, 0.5);
            tests.apply(&mut l);
            tests.on_line(&l);
        }
        // The stop's first half: the test taken off and its state saying "stopping".
        let mut r = tests.lock().running.take().unwrap();
        r.record.events.push(tagdeflect_core::feed::FeedEvent { kind: "stop".into(), t_ns: 99, note: None, user: None });
        r.record.stopped_t_ns = Some(99);
        tests.persist_as(&r, super::folder::Phase::Stopping).unwrap();
        r.folder.clone()
        // Dropped before the folder was complete: the daemon died.
    };
    assert!(std::fs::read_to_string(dir.path().join(".running.json")).unwrap().contains(r#""state":"stopping""#));
    let tests = LabTests::new(dir.path(), String::new(), Vec::new(), None).unwrap();
    assert_eq!(tests.status()["state"], "idle", "completed, not resumed");
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(60);
    while dir.path().join(".running.json").exists() {
        assert!(std::time::Instant::now() < deadline, "the folder was not completed");
        std::thread::sleep(std::time::Duration::from_millis(10));
    }
    let record: TestRecord = serde_json::from_str(&std::fs::read_to_string(folder.join("test.json")).unwrap()).unwrap();
    assert_eq!(record.stopped_t_ns, Some(99));
    assert_eq!(record.events.iter().map(|e| e.kind.as_str()).collect::<Vec<_>>(), vec!["start", "stop"]);
    assert_eq!(record.lines as usize, ZERO_SETS + 2, "counted from the file");
    assert_eq!(tests.status()["last"]["id"], record.id.as_str());
    tests.start(TestMeta { specimen: "B6".into(), ..TestMeta::default() }).expect("tests start again");
}

#[test]
fn a_test_names_the_verification_in_force_and_a_bump_seen_makes_it_stale() {
    use tagdeflect_core::feed::CameraHealth;
    use tagdeflect_core::verification::InForce;
    let dir = tempfile::tempdir().unwrap();
    let tests = LabTests::new(dir.path(), "[world]\n".into(), Vec::new(), None).unwrap();
    tests.set_verification(Box::new(|bumps: &[(String, i64)]| {
        Some(InForce {
            id: "ab".repeat(32),
            file: "verification.json".into(),
            class_iso9513: "0.5".into(),
            date: "2026-12-01".into(),
            valid_until: "2027-11-30".into(),
            u_k2_mm: 0.002,
            stale: bumps.iter().map(|(c, t)| format!("camera {c} bumped at {t}")).collect(),
        })
    }));
    tests.start(TestMeta { specimen: "B1".into(), ..TestMeta::default() }).unwrap();
    assert_eq!(tests.status()["verification"]["class_iso9513"], "0.5");
    assert!(tests.status()["verification"].get("stale").is_none(), "in force at the start");
    // A camera bumped during the test: flagged on three lines, one bump.
    for t in 1..=3 {
        let mut l = line(t, 5.0, 0.5);
        l.cameras = vec![CameraHealth { name: "left".into(), bumped: true, ..CameraHealth::default() }];
        tests.apply(&mut l);
        tests.on_line(&l);
    }
    let stopped = tests.stop().unwrap();
    let record: TestRecord = serde_json::from_str(&std::fs::read_to_string(stopped.folder.join("test.json")).unwrap()).unwrap();
    let v = record.verification.expect("test.json names the verification");
    assert_eq!(v.stale, vec!["camera left bumped at 1".to_string()], "one bump, said once");
    // The next test starts under the stale verification and says so from its start.
    tests.start(TestMeta { specimen: "B2".into(), ..TestMeta::default() }).unwrap();
    assert_eq!(tests.status()["verification"]["stale"][0], "camera left bumped at 1");
    tests.stop().unwrap();
}
