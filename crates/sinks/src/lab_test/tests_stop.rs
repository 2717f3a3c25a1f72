//! The tests' unit tests around a stop: a start pressed while the previous test is being
//! stopped, a stop completed before anyone listens for records, the verification named while
//! no test runs.

use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use super::tests::{line, stop_fed};
use super::{LabTests, TestError, TestMeta, TestRecord, ZERO_SETS};

/// A report hook held closed until opened: how many reports it entered, and the gate.
struct Gate {
    entered: AtomicUsize,
    open: AtomicBool,
}

fn gated(dir: &std::path::Path) -> (Arc<LabTests>, Arc<Gate>) {
    let gate = Arc::new(Gate { entered: AtomicUsize::new(0), open: AtomicBool::new(false) });
    let g = gate.clone();
    let hook: super::ReportHook = Box::new(move |_, _| {
        g.entered.fetch_add(1, Ordering::SeqCst);
        while !g.open.load(Ordering::SeqCst) {
            std::thread::sleep(Duration::from_millis(5));
        }
        Ok(())
    });
    (LabTests::new(dir, String::new(), Vec::new(), Some(hook)).unwrap(), gate)
}

fn meta(specimen: &str) -> TestMeta {
    TestMeta { specimen: specimen.into(), standard: Some("astm-c1609".into()), ..TestMeta::default() }
}

/// Feeds lines (the daemon's frame sets) from `from` on a thread until `until` is set.
fn feed(tests: &Arc<LabTests>, from: i64, until: Arc<AtomicBool>) -> std::thread::JoinHandle<()> {
    let tests = tests.clone();
    std::thread::spawn(move || {
        for k in from.. {
            if until.load(Ordering::SeqCst) {
                return;
            }
            let mut l = line(k, 4.0, 0.4);
            tests.apply(&mut l);
            tests.on_line(&l);
            std::thread::sleep(Duration::from_millis(5));
        }
    })
}

fn wait_until(what: &str, cond: impl Fn() -> bool) {
    let deadline = Instant::now() + Duration::from_secs(60);
    while !cond() {
        assert!(Instant::now() < deadline, "{what}: not within 60 s");
        std::thread::sleep(Duration::from_millis(2));
    }
}

/// While a stopped test's report is made the status names it as `stopping`. A start pressed then (the
/// stop's answer not given yet: another client, an automatic stop, a client that gave up
/// waiting) waits for that stop
/// and then starts: 200, not 409; the stopped test's folder is complete by then and the new
/// test's state on disk is not removed by the old one's completion. A stop still not through
/// after the start's wait is a [`TestError::Stopping`] (409 with `Retry-After`), naming it.
/// Without the wait the start is refused at once ("its folder is being completed").
#[test]
fn a_start_during_a_stop_waits_for_it_and_one_past_the_wait_is_told_to_retry() {
    let dir = tempfile::tempdir().unwrap();
    let (tests, gate) = gated(dir.path());
    let done = Arc::new(AtomicBool::new(false));
    tests.start(meta("S1")).unwrap();
    let lines = feed(&tests, 0, done.clone());
    let t = tests.clone();
    let stop = std::thread::spawn(move || t.stop());
    wait_until("the stop's report", || gate.entered.load(Ordering::SeqCst) == 1);
    // Meanwhile the status says so: not idle, its last test not complete yet.
    let st = tests.status();
    assert_eq!(st["state"], "idle", "{st}");
    assert!(st["stopping"].as_str().unwrap().ends_with("-S1"), "{st}");
    let t = tests.clone();
    let start = std::thread::spawn(move || t.start(meta("S2")));
    std::thread::sleep(Duration::from_millis(300));
    assert!(!start.is_finished(), "the start waits while the report is made: {:?}", start.join());
    gate.open.store(true, Ordering::SeqCst);
    let stopped = stop.join().unwrap().expect("the stop");
    let st = start.join().unwrap().expect("the start after the stop");
    assert_eq!(st["state"], "running");
    assert!(st["id"].as_str().unwrap().ends_with("-S2"), "{st}");
    assert!(stopped.folder.join("test.json").is_file(), "the first test's folder is complete before the second starts");
    let state = std::fs::read_to_string(dir.path().join(".running.json")).expect("the running test's state is kept");
    assert!(state.contains("-S2"), "{state}");

    // A report that outlasts the start's wait: the start is told to try again.
    gate.open.store(false, Ordering::SeqCst);
    let t = tests.clone();
    let stop = std::thread::spawn(move || t.stop());
    wait_until("the second stop's report", || gate.entered.load(Ordering::SeqCst) == 2);
    let refused = tests.after_stop(tests.lock(), Duration::from_millis(200)).map(|_| ());
    match refused {
        Err(TestError::Stopping(why)) => assert!(why.contains("-S2 is still being stopped"), "{why}"),
        other => panic!("expected Stopping, got {other:?}"),
    }
    gate.open.store(true, Ordering::SeqCst);
    stop.join().unwrap().expect("the second stop");
    done.store(true, Ordering::SeqCst);
    lines.join().unwrap();
    // A start while a test runs (not stopping) is refused at once, as before.
    tests.start(meta("S3")).unwrap();
    assert!(matches!(tests.start(meta("S4")), Err(TestError::Conflict(_))));
}

/// A stop the last daemon left unfinished is completed when the tests are made — before the
/// binary has handed them the MQTT publisher: its record (stopped, with the folder's hashes)
/// is kept and handed on when the publisher is set, like any other stop's.
#[test]
fn a_stop_completed_before_the_publisher_is_set_is_handed_to_it() {
    let dir = tempfile::tempdir().unwrap();
    let id = {
        let tests = LabTests::new(dir.path(), String::new(), Vec::new(), None).unwrap();
        tests.start(TestMeta { specimen: "P1".into(), ..TestMeta::default() }).unwrap();
        for k in 0..ZERO_SETS + 2 {
            let mut l = line(k as i64, 5.0, 0.5);
            tests.apply(&mut l);
            tests.on_line(&l);
        }
        let mut r = tests.lock().running.take().unwrap();
        r.record.events.push(tagdeflect_core::feed::FeedEvent { kind: "stop".into(), t_ns: 99, note: None, user: None });
        r.record.stopped_t_ns = Some(99);
        tests.persist_as(&r, super::folder::Phase::Stopping).unwrap();
        r.record.id.clone()
        // Dropped before the folder was complete: the daemon died.
    };
    let tests = LabTests::new(dir.path(), String::new(), Vec::new(), None).unwrap();
    wait_until("the folder completed", || !dir.path().join(".running.json").exists());
    let published = Arc::new(Mutex::new(Vec::<TestRecord>::new()));
    let p = published.clone();
    tests.set_on_record(Box::new(move |r| p.lock().unwrap().push(r.clone())));
    let records = published.lock().unwrap().clone();
    assert_eq!(records.len(), 1, "{records:?}");
    assert_eq!(records[0].id, id);
    assert_eq!(records[0].stopped_t_ns, Some(99));
    assert!(records[0].sha256.contains_key("feed.jsonl"), "the completed record, with its hashes: {:?}", records[0]);
    // Later records go straight on.
    tests.start(TestMeta { specimen: "P2".into(), ..TestMeta::default() }).unwrap();
    assert_eq!(published.lock().unwrap().len(), 2);
    stop_fed(&tests, 100);
    assert!(published.lock().unwrap().last().unwrap().stopped_t_ns.is_some(), "the stop handed on");
}

/// `GET /api/test` names the verification in force while no test runs (the page shows it
/// always), stale with its reasons after a bump; none when none is configured.
#[test]
fn the_idle_status_names_the_verification_in_force() {
    use tagdeflect_core::feed::CameraHealth;
    use tagdeflect_core::verification::InForce;
    let dir = tempfile::tempdir().unwrap();
    let tests = LabTests::new(dir.path(), String::new(), Vec::new(), None).unwrap();
    assert_eq!(tests.status()["state"], "idle");
    assert!(tests.status()["verification"].is_null(), "none configured: none named");
    tests.set_verification(Box::new(|bumps: &[(String, i64)]| {
        Some(InForce {
            id: "cd".repeat(32),
            file: "verification.json".into(),
            class_iso9513: "1".into(),
            date: "2026-12-01".into(),
            valid_until: "2027-11-30".into(),
            u_k2_mm: 0.004,
            stale: bumps.iter().map(|(c, _)| format!("camera {c} bumped")).collect(),
        })
    }));
    let st = tests.status();
    assert_eq!(st["verification"]["class_iso9513"], "1", "{st}");
    assert_eq!(st["verification"]["date"], "2026-12-01");
    assert!(st["verification"].get("stale").is_none(), "in force: {st}");
    let mut l = line(1, 5.0, 0.5);
    l.cameras = vec![CameraHealth { name: "left".into(), bumped: true, ..CameraHealth::default() }];
    tests.apply(&mut l);
    let st = tests.status();
    assert_eq!(st["state"], "idle");
    assert_eq!(st["verification"]["stale"][0], "camera left bumped", "a bump seen makes it stale at once: {st}");
}
