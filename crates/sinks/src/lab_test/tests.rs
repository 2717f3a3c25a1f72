//! The tests' unit tests: a test from start to stop, and one resumed after a restart.

use std::path::{Path, PathBuf};

use sha2::Digest;
use tagdeflect_core::feed::FeedLine;

use super::folder::hex;
use super::{LabTests, TestError, TestMeta, TestRecord, ZERO_SETS};
use tagdeflect_core::feed::FeedTag;

/// The time of the `k`-th line: an hour after the tests began, so after every start here.
pub(super) fn t(k: i64) -> i64 {
    static BASE: std::sync::OnceLock<i64> = std::sync::OnceLock::new();
    *BASE.get_or_init(|| tagdeflect_core::clock::now_epoch_ns() + 3_600_000_000_000) + k
}

pub(super) fn line(k: i64, z: f64, net: f64) -> FeedLine {
    let tag = FeedTag {
        id: 1,
        pos_mm: [10.0, 0.0, z],
        disp_mm: [0.0, 0.0, z],
        views: 2,
        sigma_mm: Some([0.01; 3]),
        disp_sigma_mm: None,
        reproj_px: None,
    };
    FeedLine { seq: k as u64, t_ns: t(k), tags: vec![tag], net_deflection_mm: Some(net), ..FeedLine::default() }
}

/// Stops the running test while lines `from..` keep coming (the stop's line is the next one,
/// as in a running daemon); the stop and the lines given.
pub(super) fn stop_fed(tests: &std::sync::Arc<LabTests>, from: i64) -> (super::Stopped, Vec<FeedLine>) {
    let me = tests.clone();
    let stop = std::thread::spawn(move || me.stop());
    while !stop.is_finished() && !tests.lock().running.as_ref().is_some_and(|r| r.ends.stop.is_some()) {
        std::thread::sleep(std::time::Duration::from_millis(1));
    }
    let mut lines = Vec::new();
    for k in from.. {
        if stop.is_finished() {
            break;
        }
        let mut l = line(k, 4.0, 0.4);
        tests.apply(&mut l);
        tests.on_line(&l);
        lines.push(l);
        std::thread::sleep(std::time::Duration::from_millis(5));
    }
    (stop.join().unwrap().unwrap(), lines)
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
    let (stopped, after) = stop_fed(&tests, 11);
    // The mark and the stop go onto the next line, the test's last; later lines are no test's.
    assert_eq!(after[0].events.iter().map(|e| e.kind.as_str()).collect::<Vec<_>>(), vec!["mark", "stop"]);
    assert!(after[0].test.is_some() && after[1..].iter().all(|l| l.test.is_none() && l.events.is_empty()));
    let record: TestRecord = serde_json::from_str(&std::fs::read_to_string(stopped.folder.join("test.json")).unwrap()).unwrap();
    assert_eq!(record.lines, 7);
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
    let (stopped, _) = stop_fed(&tests, 101);
    let record: TestRecord = serde_json::from_str(&std::fs::read_to_string(stopped.folder.join("test.json")).unwrap()).unwrap();
    assert_eq!(record.events.iter().map(|e| e.kind.as_str()).collect::<Vec<_>>(), vec!["start", "resume", "stop"]);
    assert_eq!(std::fs::read_to_string(stopped.folder.join("feed.jsonl")).unwrap().lines().count(), ZERO_SETS + 2);
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
    let (stopped, _) = stop_fed(&tests, 10);
    let record: TestRecord = serde_json::from_str(&std::fs::read_to_string(stopped.folder.join("test.json")).unwrap()).unwrap();
    let v = record.verification.expect("test.json names the verification");
    assert_eq!(v.stale, vec![format!("camera left bumped at {}", t(1))], "one bump, said once");
    // The next test starts under the stale verification and says so from its start.
    tests.start(TestMeta { specimen: "B2".into(), ..TestMeta::default() }).unwrap();
    assert_eq!(tests.status()["verification"]["stale"][0], format!("camera left bumped at {}", t(1)).as_str());
    stop_fed(&tests, 100);
}

/// What the control API takes, the archive takes (one set of limits, `core::limits`): marks
/// until the record is full are refused with 400 naming the note, never published beyond what
/// the archive reads; a specimen of 64 four-byte letters or a NUL in a measured key is a 400,
/// not a 500 or a record the archive refuses; the blanks around an id are not kept.
#[test]
fn what_the_api_takes_the_archive_takes_and_ids_are_trimmed() {
    use tagdeflect_wire::LabTestMessage;
    let dir = tempfile::tempdir().unwrap();
    let tests = LabTests::new(dir.path(), String::new(), Vec::new(), None).unwrap();
    let published = std::sync::Arc::new(std::sync::Mutex::new(Vec::<TestRecord>::new()));
    let p = published.clone();
    tests.set_on_record(Box::new(move |r: &TestRecord| p.lock().unwrap().push(r.clone())));
    let bad = |m: TestMeta| match tests.start(m) {
        Err(TestError::Bad(e)) => e,
        other => panic!("not a 400: {other:?}"),
    };
    let wide = "𝐁".repeat(64);
    assert!(bad(TestMeta { specimen: wide, ..TestMeta::default() }).contains("specimen"));
    let mut nul = TestMeta { specimen: "B1".into(), ..TestMeta::default() };
    nul.measured.insert("a\u{0}b".into(), 1.0);
    assert!(bad(nul).contains("measured"));
    tests.start(TestMeta { specimen: " B12 ".into(), operator: Some(" Ann ".into()), ..TestMeta::default() }).unwrap();
    let st = tests.status();
    assert_eq!((st["specimen"].as_str(), st["operator"].as_str()), (Some("B12"), Some("Ann")));
    assert!(st["id"].as_str().unwrap().ends_with("Z-B12"), "{st}");
    // Marks of 4 KB notes (quotes: twice that in JSON) until the record is full.
    let note = "\"".repeat(4000);
    let mut marks = 0;
    let refusal = loop {
        match tests.mark(Some(note.clone())) {
            Ok(_) => marks += 1,
            Err(e) => break e,
        }
        assert!(marks < 1000, "never refused");
    };
    assert!(matches!(&refusal, TestError::Bad(m) if m.starts_with("note:")), "{refusal}");
    assert!(marks > 20, "{marks} marks");
    let (_, _) = stop_fed(&tests, 0);
    let records = published.lock().unwrap().clone();
    let last = records.last().unwrap();
    assert!(last.stopped_t_ns.is_some());
    for r in [&records[records.len() - 2], last] {
        let bytes = serde_json::to_vec(&LabTestMessage::from_record("rig1", "run1", r)).unwrap();
        LabTestMessage::parse(&bytes, "rig1", "run1", &r.id).expect("the archive takes what the API accepted");
    }
}

/// A test's feed holds its own lines only: none exposed before its start, its own stop event
/// on its last line and the previous test's stop not at all; after a resume the counts are the
/// files' and the resume's gap runs from the last line before to the first line after.
#[test]
fn a_tests_feed_holds_its_own_lines_and_events_and_a_resume_says_the_real_gap() {
    let dir = tempfile::tempdir().unwrap();
    let read = |folder: &Path| -> Vec<serde_json::Value> {
        std::fs::read_to_string(folder.join("feed.jsonl")).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect()
    };
    let kinds = |l: &serde_json::Value| -> Vec<String> {
        l["events"].as_array().map_or(Vec::new(), |a| a.iter().map(|e| e["kind"].as_str().unwrap().to_string()).collect())
    };
    let tests = LabTests::new(dir.path(), String::new(), Vec::new(), None).unwrap();
    tests.start(TestMeta { specimen: "A1".into(), ..TestMeta::default() }).unwrap();
    // A line exposed 120 ms before the start (solved late) is no line of the test. (Counted
    // from the start's own time: from the clock after `start` returned, a start slowed by a
    // busy disk made it a line after the start.)
    let mut early = line(0, 5.0, 0.5);
    early.t_ns = tests.status()["started_t_ns"].as_i64().unwrap() - 120_000_000;
    tests.apply(&mut early);
    tests.on_line(&early);
    assert!(early.test.is_none() && early.events.is_empty());
    for k in 1..=6 {
        let mut l = line(k, 5.0, 0.5);
        tests.apply(&mut l);
        tests.on_line(&l);
    }
    let (first, _) = stop_fed(&tests, 7);
    tests.start(TestMeta { specimen: "A2".into(), ..TestMeta::default() }).unwrap();
    // The second test's lines a second apart (k in ns: 1000 s to 1005 s after the base), so
    // a gap counted from another line than the last written differs in its printed tenth.
    const S: i64 = 1_000_000_000;
    for k in 1000..1006 {
        let mut l = line(k * S, 5.0, 0.5);
        tests.apply(&mut l);
        tests.on_line(&l);
    }
    drop(tests);
    // The daemon died; the state was kept when the zero formed, a line before the last.
    let tests = LabTests::new(dir.path(), String::new(), Vec::new(), None).unwrap();
    assert_eq!(tests.status()["lines"], 6, "counted from the file");
    let mut l = line(3000 * S, 5.0, 0.5);
    tests.apply(&mut l);
    tests.on_line(&l);
    let (second, _) = stop_fed(&tests, 3000 * S + 1);
    let a = read(&first.folder);
    assert_eq!(a.len(), 7, "six lines and the stop's");
    assert!(a.iter().all(|l| l["t_ns"].as_i64().unwrap() >= t(1)));
    assert_eq!(kinds(&a[0]), ["start"]);
    assert_eq!(kinds(a.last().unwrap()), ["stop"], "its own stop on its last line");
    let b = read(&second.folder);
    assert_eq!(kinds(&b[0]), ["start"], "not the previous test's stop");
    assert_eq!(b.iter().filter(|l| kinds(l).contains(&"stop".to_string())).count(), 1);
    assert_eq!(kinds(b.last().unwrap()), ["stop"]);
    let resume = b.iter().find(|l| kinds(l) == ["resume"]).unwrap();
    let gap_s = (t(3000 * S) - t(1005 * S)) as f64 * 1e-9;
    assert!((gap_s - 1995.0).abs() < 1e-6);
    assert!(resume["events"][0]["note"].as_str().unwrap().ends_with(&format!("(no lines for {gap_s:.1} s)")), "{resume}");
    let record: TestRecord = serde_json::from_str(&std::fs::read_to_string(second.folder.join("test.json")).unwrap()).unwrap();
    assert_eq!(record.lines as usize, b.len());
    assert_eq!(record.events.iter().find(|e| e.kind == "resume").unwrap().note, resume["events"][0]["note"].as_str().map(String::from));
}

/// A mid-test `zero` re-zeroes the lines after it: the beam deflected by 1 mm (net 1 mm) from
/// the start's zero, then `zero`; the next five sets form the new zero (flagged `zeroing`) and
/// the set after them, 0.1 mm further, reads 0.1 mm from the new zero — not 1.1 mm from the
/// start's, as a `zero` that only logged its event would leave it.
#[test]
fn a_mid_test_zero_counts_the_lines_after_it_from_the_new_zero() {
    let dir = tempfile::tempdir().unwrap();
    let tests = LabTests::new(dir.path(), String::new(), Vec::new(), None).unwrap();
    tests.start(TestMeta { specimen: "Z1".into(), ..TestMeta::default() }).unwrap();
    let mut fed = Vec::new();
    let mut feed = |k: i64, z: f64, net: f64| {
        let mut l = line(k, z, net);
        tests.apply(&mut l);
        tests.on_line(&l);
        fed.push(l);
    };
    for k in 0..ZERO_SETS as i64 {
        feed(k, 5.0, 0.5);
    }
    // Deflected: 1 mm down, the net deflection 1 mm.
    for k in 5..8 {
        feed(k, 4.0, -0.5);
    }
    tests.zero().unwrap();
    for k in 8..8 + ZERO_SETS as i64 {
        feed(k, 4.0, -0.5);
    }
    feed(20, 3.9, -0.6);
    let disp = |l: &FeedLine| (l.tags[0].disp_mm[2], l.net_deflection_mm.unwrap());
    let before = disp(&fed[7]);
    assert!((before.0 + 1.0).abs() < 1e-9 && (before.1 + 1.0).abs() < 1e-9, "before the zero, from the start's: {before:?}");
    let after = disp(fed.last().unwrap());
    assert!(
        (after.0 + 0.1).abs() < 1e-9 && (after.1 + 0.1).abs() < 1e-9,
        "after the zero, from the new zero: {after:?} (a zero that only logged: -1.1 mm)"
    );
    // The zero's own sets read ~0 and are flagged; the zero's event is on the first of them.
    assert_eq!(fed[8].events.iter().map(|e| e.kind.as_str()).collect::<Vec<_>>(), vec!["zero"]);
    for l in &fed[8..8 + ZERO_SETS] {
        assert!(l.test.as_ref().unwrap().zeroing, "the new zero's sets flagged");
        assert!(disp(l).0.abs() < 1e-9 && disp(l).1.abs() < 1e-9, "{:?}", disp(l));
    }
    assert!(!fed[7].test.as_ref().unwrap().zeroing && !fed.last().unwrap().test.as_ref().unwrap().zeroing);
    let (stopped, _) = stop_fed(&tests, 21);
    let record: TestRecord = serde_json::from_str(&std::fs::read_to_string(stopped.folder.join("test.json")).unwrap()).unwrap();
    assert_eq!(record.events.iter().map(|e| e.kind.as_str()).collect::<Vec<_>>(), vec!["start", "zero", "stop"]);
}
