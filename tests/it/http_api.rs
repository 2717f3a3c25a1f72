//! The page's control API driving tests on a running daemon (helpers in `http.rs`): two tests
//! through `tagdeflect test` with the API's refusals, the operator's page in Chromium, the
//! calibration's hash in each test's record, automatic start and stop, a start right after a
//! stop.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use crate::http::{browser, demo_with_tests, get, post, rig_config, small_rig, tagdeflect_test, Daemon};
use tagdeflect_core::feed::FeedLine;
use tagdeflect_sim::SimParams;

/// Two tests on a running daemon without restarting it, through `tagdeflect test` (the API's
/// client): start (zero at its first sets), mark, zero, stop; each test's folder complete with
/// its hashes; the daemon's feed carries the events. The API refuses a POST without the token,
/// with a wrong one, from another origin, with an oversized or non-JSON body; no GET changes
/// anything.
#[test]
fn two_tests_through_the_control_api_with_its_refusals() {
    let dir = tempfile::tempdir().unwrap();
    let tests_dir = dir.path().join("tests");
    // The demo's rig with its beam at rest through the whole test: the zero is checked on a
    // still beam. (A zero formed while the beam moves averages the running mean over the sets
    // so far, so its lines' mean displacement is about one set's motion: ~0.05-0.17 mm at the
    // demo's 5 fps once its ramp has started, which a slow start up on a busy machine reached.)
    let params = SimParams { frame_sets: 3000, rest_frames: 2500, ..tagdeflect_sim::live_rig::demo_params() };
    let cfg = crate::common::sim_rig_config(&params);
    let cfg_path = dir.path().join("rest.toml");
    std::fs::write(&cfg_path, cfg.to_toml_string()).unwrap();
    let mut d =
        Daemon::start(&["demo", "--config", cfg_path.to_str().unwrap(), "--http", "127.0.0.1:0", "--tests", tests_dir.to_str().unwrap()]);
    let addr = d.addr();
    let token_file = tests_dir.join(".token");
    let token = std::fs::read_to_string(&token_file).unwrap().trim().to_string();
    d.wait_stderr(&format!("control token: {token}"), Duration::from_secs(10), "the token printed");
    use std::os::unix::fs::PermissionsExt;
    assert_eq!(std::fs::metadata(&token_file).unwrap().permissions().mode() & 0o777, 0o600);
    assert_eq!(serde_json::from_slice::<serde_json::Value>(&get(addr, "/api/test").2).unwrap()["state"], "idle");

    // Refusals: no token, a wrong token, another origin, a huge body, a form body, a GET.
    let json = ("Content-Type", "application/json");
    let bearer = format!("Bearer {token}");
    let start = br#"{"specimen": "B1"}"#;
    assert_eq!(post(addr, "/api/test/start", &[json], start).0, 401);
    assert_eq!(post(addr, "/api/test/start", &[json, ("Authorization", "Bearer 0123456789abcdef")], start).0, 401);
    assert_eq!(post(addr, "/api/test/start", &[json, ("Authorization", &bearer), ("Origin", "http://evil.example")], start).0, 403);
    let huge = vec![b' '; 64 * 1024];
    assert_eq!(post(addr, "/api/test/start", &[json, ("Authorization", &bearer)], &huge).0, 413);
    assert_eq!(post(addr, "/api/test/start", &[("Content-Type", "text/plain"), ("Authorization", &bearer)], start).0, 415);
    assert_eq!(get(addr, "/api/test/start").0, 405, "no state change on a GET");
    // Measured dimensions out of any beam's range: 400 naming the field and its range.
    for (body, field) in [
        (&br#"{"specimen": "B1", "measured": {"span_mm": 0.001}}"#[..], "measured.span_mm = 0.001"),
        (br#"{"specimen": "B1", "measured": {"width_mm": 1e308}}"#, "measured.width_mm = 1e308"),
        (br#"{"specimen": "B1", "measured": {"depth_mm": 150, "notch_mm": 150}}"#, "measured.notch_mm = 150"),
    ] {
        let (code, answer) = post(addr, "/api/test/start", &[json, ("Authorization", &bearer)], body);
        assert_eq!(code, 400, "{answer}");
        assert!(answer.contains(field) && answer.contains("mm"), "{answer}");
    }
    assert_eq!(serde_json::from_slice::<serde_json::Value>(&get(addr, "/api/test").2).unwrap()["state"], "idle");
    d.wait_stderr("control API: a POST with a wrong token refused", Duration::from_secs(10), "logged with the peer");
    assert!(d.stderr.lock().unwrap().lines().any(|l| l.contains("wrong token refused") && l.contains("peer=127.0.0.1")), "the peer named");

    // Test 1: start, mark, zero, stop.
    let st = tagdeflect_test(addr, &token_file, &["start", "--specimen", "B1", "--operator", "A. Tester"]);
    assert_eq!(st["state"], "running");
    let id1 = st["id"].as_str().unwrap().to_string();
    assert!(id1.ends_with("-B1"), "{id1}");
    assert_eq!(post(addr, "/api/test/start", &[json, ("Authorization", &bearer)], br#"{"specimen": "B9"}"#).0, 409, "one test at a time");
    let with_test = |d: &Daemon, id: &str| d.lines().iter().filter(|(_, l)| l.test.as_ref().is_some_and(|t| t.id == id)).count();
    let deadline = Instant::now() + Duration::from_secs(60);
    while with_test(&d, &id1) < 8 {
        assert!(Instant::now() < deadline, "the test's lines did not come");
        std::thread::sleep(Duration::from_millis(100));
    }
    tagdeflect_test(addr, &token_file, &["mark", "first crack seen"]);
    tagdeflect_test(addr, &token_file, &["zero"]);
    let n = with_test(&d, &id1);
    while with_test(&d, &id1) < n + 8 {
        assert!(Instant::now() < deadline, "lines after the zero did not come");
        std::thread::sleep(Duration::from_millis(100));
    }
    let stopped = tagdeflect_test(addr, &token_file, &["stop"]);
    assert_eq!(stopped["id"], id1.as_str());
    let folder = PathBuf::from(stopped["folder"].as_str().unwrap());
    let record: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(folder.join("test.json")).unwrap()).unwrap();
    assert_eq!(record["specimen"], "B1");
    assert_eq!(record["operator"], "A. Tester");
    let kinds: Vec<&str> = record["events"].as_array().unwrap().iter().map(|e| e["kind"].as_str().unwrap()).collect();
    assert_eq!(kinds, ["start", "mark", "zero", "stop"]);
    assert_eq!(record["events"][1]["note"], "first crack seen");
    let test_lines: Vec<FeedLine> =
        std::fs::read_to_string(folder.join("feed.jsonl")).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert_eq!(record["lines"].as_u64(), Some(test_lines.len() as u64));
    assert!(test_lines.len() >= 16 && test_lines.iter().all(|l| l.test.as_ref().unwrap().id == id1));
    assert!(test_lines[..5].iter().all(|l| l.test.as_ref().unwrap().zeroing) && !test_lines[5].test.as_ref().unwrap().zeroing);
    // The test's zero: its first sets average to zero displacement.
    let first_disp: f64 = test_lines[..5].iter().map(|l| l.tags[0].disp_mm[2]).sum::<f64>() / 5.0;
    assert!(first_disp.abs() < 0.05, "mean displacement over the zero's sets {first_disp}");
    // The mid-test zero is taken again from the next sets: the line carrying its event and
    // the four after it form the new zero (a `zero` that only logged would leave them
    // unflagged), the one after is counted from it, and they average to zero displacement.
    let z = test_lines.iter().position(|l| l.events.iter().any(|e| e.kind == "zero")).expect("the zero's event in the test's feed");
    assert!(test_lines.len() >= z + 6, "{} lines, the zero at {z}", test_lines.len());
    assert!(!test_lines[z - 1].test.as_ref().unwrap().zeroing, "the line before the zero counts from the first");
    assert!(test_lines[z..z + 5].iter().all(|l| l.test.as_ref().unwrap().zeroing), "the zero's sets flagged");
    assert!(!test_lines[z + 5].test.as_ref().unwrap().zeroing, "counted from the new zero after it");
    let zero_disp: f64 = test_lines[z..z + 5].iter().map(|l| l.tags[0].disp_mm[2]).sum::<f64>() / 5.0;
    assert!(zero_disp.abs() < 0.01, "mean displacement over the new zero's sets {zero_disp}");
    let utm = std::fs::read_to_string(folder.join("utm.jsonl")).unwrap();
    assert!(
        utm.lines().count() > test_lines.len(),
        "every UTM sample at its own rate: {} samples, {} lines",
        utm.lines().count(),
        test_lines.len()
    );
    for f in ["feed.jsonl", "utm.jsonl", "tagdeflect.toml"] {
        use sha2::Digest;
        let want: String = sha2::Sha256::digest(std::fs::read(folder.join(f)).unwrap()).iter().map(|b| format!("{b:02x}")).collect();
        assert_eq!(record["sha256"][f], want.as_str(), "{f}");
    }
    assert_eq!(serde_json::from_slice::<serde_json::Value>(&get(addr, "/api/test").2).unwrap()["state"], "idle");

    // Test 2, the next specimen, without a restart.
    let st = tagdeflect_test(addr, &token_file, &["start", "--specimen", "B2"]);
    let id2 = st["id"].as_str().unwrap().to_string();
    while with_test(&d, &id2) < 6 {
        assert!(Instant::now() < deadline, "the second test's lines did not come");
        std::thread::sleep(Duration::from_millis(100));
    }
    let stopped = tagdeflect_test(addr, &token_file, &["stop"]);
    assert!(PathBuf::from(stopped["folder"].as_str().unwrap()).join("test.json").is_file());
    assert_ne!(id1, id2);
    // The daemon's own feed carries every event (the stop on the test's last line).
    let events = |d: &Daemon| -> Vec<String> { d.lines().iter().flat_map(|(_, l)| l.events.iter().map(|e| e.kind.clone())).collect() };
    while events(&d).len() < 6 {
        assert!(Instant::now() < deadline, "the events did not reach the feed: {:?}", events(&d));
        std::thread::sleep(Duration::from_millis(100));
    }
    let events = events(&d);
    assert_eq!(events, ["start", "mark", "zero", "stop", "start", "stop"]);
    assert_eq!(d.stop(), Some(0));
}

/// The operator's page in Chromium drives two whole tests (specimen form, start, mark, zero,
/// stop; the token asked once per browser session); each folder is complete.
#[test]
fn the_operator_page_drives_two_tests_in_chromium() {
    let dir = tempfile::tempdir().unwrap();
    let tests_dir = dir.path().join("tests");
    let cfg = rig_config(dir.path(), None);
    let (mut d, addr, token) = demo_with_tests(Some(&cfg), &tests_dir, &[]);
    let shot = dir.path().join("operator-page.png");
    let seen = browser("operator_page.py", [format!("http://{addr}/"), token, shot.display().to_string()]);
    assert!(seen.get("error").is_none() && seen.get("timeout").is_none(), "{seen}\n{}", d.stderr.lock().unwrap());
    assert_eq!(seen["prompts"].as_u64(), Some(1 + 2 * 2), "the token once, then a note and a confirmation per test: {seen}");
    let tests = seen["tests"].as_array().unwrap();
    assert_eq!(tests.len(), 2);
    for (t, specimen) in tests.iter().zip(["B1", "B2"]) {
        assert!(t["state"].as_str().unwrap().contains(&format!("-{specimen}")), "{t}");
        let folder = PathBuf::from(t["folder"].as_str().unwrap());
        let record: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(folder.join("test.json")).unwrap()).unwrap();
        assert_eq!(record["specimen"], specimen);
        assert_eq!(record["operator"], "A. Tester");
        let kinds: Vec<&str> = record["events"].as_array().unwrap().iter().map(|e| e["kind"].as_str().unwrap()).collect();
        assert_eq!(kinds, ["start", "mark", "zero", "stop"], "{record}");
        assert_eq!(record["events"][1]["note"], "first crack seen");
        assert!(record["lines"].as_u64().unwrap() >= 5, "{record}");
        let gauges: Vec<&str> = t["gauges"].as_array().unwrap().iter().filter_map(|g| g.as_str()).collect();
        assert!(gauges.iter().any(|g| g.starts_with("net deflection") && g.contains("± ")), "{gauges:?}");
    }
    // The second test: the first one's curve in grey, the rate judged against C1609's window for
    // this beam, the deflected shape fitted, the report made at the stop.
    let second = &tests[1];
    assert_eq!(second["earlier"], "1", "{second}");
    assert!(second["rate_window"][1].as_str().unwrap().starts_with("window "), "{second}");
    assert_eq!(second["profile"][0], "ok", "{second}");
    let folder = PathBuf::from(second["folder"].as_str().unwrap());
    assert!(folder.join("report").is_dir(), "the C1609 test's report: {:?}", std::fs::read_dir(&folder).unwrap().collect::<Vec<_>>());
    let record: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(folder.join("test.json")).unwrap()).unwrap();
    assert_eq!(record["standard"], "astm-c1609");
    assert!(record["sha256"].as_object().unwrap().keys().any(|k| k.starts_with("report/")), "the report is hashed: {record}");
    // The measured dimensions typed into the form: recorded, and the report computes with them.
    assert_eq!(record["measured"], serde_json::json!({"width_mm": 151.5, "depth_mm": 149.2}), "{record}");
    let report: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(folder.join("report/report.json")).unwrap()).unwrap();
    let text = report.to_string();
    assert_eq!(
        (report["specimen"]["dimension_sources"]["width_mm"].as_str(), report["specimen"]["dimension_sources"]["depth_mm"].as_str()),
        (Some("test.json"), Some("test.json")),
        "the report says it used them: {text}"
    );
    assert_eq!((report["specimen"]["width_mm"].as_f64(), report["specimen"]["depth_mm"].as_f64()), (Some(151.5), Some(149.2)), "{text}");
    assert!(seen["console_errors"].as_array().unwrap().is_empty(), "{seen}");
    assert_eq!(&std::fs::read(&shot).unwrap()[1..4], b"PNG");
    if let Some(to) = std::env::var_os("TAGDEFLECT_OPERATOR_SCREENSHOT") {
        std::fs::copy(&shot, to).unwrap();
    }
    assert_eq!(d.stop(), Some(0));
}

/// A camera whose intrinsics come from a calibration file: every test's `test.json` carries
/// that file's SHA-256 as it was when the daemon read it (the file is changed during the test:
/// the hash is still the one of the calibration in force).
#[test]
fn a_tests_record_carries_the_hash_of_the_calibration_in_force() {
    use sha2::Digest;
    let dir = tempfile::tempdir().unwrap();
    let rig = rig_config(dir.path(), None);
    let mut table: toml::Table = std::fs::read_to_string(&rig).unwrap().parse().unwrap();
    let cam = table["camera"].as_array_mut().unwrap()[0].as_table_mut().unwrap();
    let num = |v: &toml::Value| v.as_float().or(v.as_integer().map(|i| i as f64)).unwrap();
    let (fx, fy, cx, cy) = (num(&cam["fx"]), num(&cam["fy"]), num(&cam["cx"]), num(&cam["cy"]));
    let dist: Vec<f64> = cam.get("dist").map_or(vec![0.0; 5], |d| d.as_array().unwrap().iter().map(num).collect());
    for k in ["fx", "fy", "cx", "cy", "dist"] {
        cam.remove(k);
    }
    let cal = dir.path().join("cam0.json");
    let cal_text = serde_json::json!({
        "image_width": cam["width"].as_integer(), "image_height": cam["height"].as_integer(),
        "camera_matrix": {"rows": 3, "cols": 3, "data": [fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0]},
        "distortion_coefficients": {"rows": 1, "cols": 5, "data": dist},
    })
    .to_string();
    std::fs::write(&cal, &cal_text).unwrap();
    cam.insert("calibration".into(), toml::Value::String("cam0.json".into()));
    std::fs::write(&rig, toml::to_string(&table).unwrap()).unwrap();
    let want: String = sha2::Sha256::digest(cal_text.as_bytes()).iter().map(|b| format!("{b:02x}")).collect();

    let tests_dir = dir.path().join("tests");
    let mut d =
        Daemon::start(&["demo", "--config", rig.to_str().unwrap(), "--http", "127.0.0.1:0", "--tests", tests_dir.to_str().unwrap()]);
    let addr = d.addr();
    let token_file = tests_dir.join(".token");
    let st = tagdeflect_test(addr, &token_file, &["start", "--specimen", "C1"]);
    let id = st["id"].as_str().unwrap().to_string();
    std::fs::write(&cal, "recalibrated during the test\n").unwrap();
    d.wait_lines(3, Duration::from_secs(60));
    let stopped = tagdeflect_test(addr, &token_file, &["stop"]);
    assert_eq!(stopped["id"], id.as_str());
    let folder = PathBuf::from(stopped["folder"].as_str().unwrap());
    let record: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(folder.join("test.json")).unwrap()).unwrap();
    assert_eq!(record["sha256"][cal.display().to_string()], want.as_str(), "{record}");
    assert_eq!(d.stop(), Some(0));

    // A calibration file that is gone: the config is refused, naming the file.
    std::fs::remove_file(&cal).unwrap();
    let o = Command::new(env!("CARGO_BIN_EXE_tagdeflect")).args(["check", "--config", rig.to_str().unwrap()]).output().unwrap();
    assert_eq!(o.status.code(), Some(2), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(String::from_utf8_lossy(&o.stderr).contains("cam0.json"), "{}", String::from_utf8_lossy(&o.stderr));
}

/// Automatic start and stop on a simulated test (`[output.auto_test]`): the simulated machine
/// loads the beam to 60 kN and back, again and again. The daemon arms at a low load, starts a
/// test when the load passes 5 kN (its zero there, as a machine's preload), stops it at ASTM
/// C1609's end (net deflection L/150 + 0.5 mm = 3.5 mm from the zero) with the report, and
/// starts the next one only after the beam was unloaded; the page's API says what it waits for.
#[test]
fn tests_start_at_the_preload_and_stop_at_the_standards_end_by_themselves() {
    let dir = tempfile::tempdir().unwrap();
    let params = SimParams { frame_sets: 30, ..small_rig() };
    let cfg = crate::common::beam_rig_config(&params);
    let span = params.span_mm;
    let mut text = cfg.to_toml_string();
    text.push_str("\n[output.auto_test]\nstart_load_kn = 5.0\nstandard = \"astm-c1609\"\n");
    let path = dir.path().join("rig.toml");
    std::fs::write(&path, text).unwrap();
    let tests_dir = dir.path().join("tests");
    let mut d =
        Daemon::start(&["demo", "--config", path.to_str().unwrap(), "--http", "127.0.0.1:0", "--tests", tests_dir.to_str().unwrap()]);
    let addr = d.addr();
    let test_status = || serde_json::from_slice::<serde_json::Value>(&get(addr, "/api/test").2).unwrap();

    let deadline = Instant::now() + Duration::from_secs(120);
    let mut seen_waiting = std::collections::BTreeSet::new();
    let mut ids: Vec<String> = Vec::new();
    let mut stopped: Option<String> = None;
    while ids.len() < 2 {
        assert!(
            Instant::now() < deadline,
            "two automatic tests did not start within 120 s; waited for {seen_waiting:?}\n{}",
            d.stderr.lock().unwrap()
        );
        let st = test_status();
        if let Some(a) = st.get("auto") {
            seen_waiting.insert(format!(
                "{}: {}",
                a["state"].as_str().unwrap(),
                a["waiting_for"].as_str().unwrap().split(" (").next().unwrap()
            ));
        }
        match st["state"].as_str().unwrap() {
            "running" => {
                let id = st["id"].as_str().unwrap().to_string();
                if !ids.contains(&id) {
                    ids.push(id);
                }
            }
            _ => {
                if let Some(last) = st["last"]["id"].as_str() {
                    stopped = Some(last.to_string());
                }
            }
        }
        std::thread::sleep(Duration::from_millis(200));
    }
    assert_eq!(stopped.as_deref(), Some(ids[0].as_str()), "the first test stopped before the second started");
    assert!(ids.iter().all(|id| id.ends_with("-auto")), "{ids:?}");
    let waits = format!("{seen_waiting:?}");
    println!("AUTO waited for {waits}");
    assert!(waits.contains("armed: the load to reach 5.00 kN to start a test"), "{waits}");
    assert!(waits.contains("disarmed: the load to fall below 2.50 kN"), "after a stop, while the beam is loaded: {waits}");
    assert!(waits.contains(&format!("running: net deflection {:.3} mm", span / 150.0 + 0.5)), "{waits}");

    // The first test's folder: started at the preload, stopped at the end, with its report.
    let folder = tests_dir.join(&ids[0]);
    let record: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(folder.join("test.json")).unwrap()).unwrap();
    assert_eq!(record["standard"], "astm-c1609");
    let events = record["events"].as_array().unwrap();
    assert_eq!(events.iter().map(|e| e["kind"].as_str().unwrap()).collect::<Vec<_>>(), ["start", "stop"], "{record}");
    assert!(events[0]["note"].as_str().unwrap().starts_with("auto: the load reached"), "{record}");
    assert!(events[1]["note"].as_str().unwrap().contains("L/150"), "{record}");
    let lines: Vec<FeedLine> =
        std::fs::read_to_string(folder.join("feed.jsonl")).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    // The line that reached 5 kN was exposed before the start and belongs to no test; the
    // test's first line with a load comes after the zero's sets: a few steps of the demo's
    // fast ramp above it (measured: 15.0 kN, 4 steps of 2.5 kN).
    let loads: Vec<f64> = lines.iter().filter_map(|l| l.load_kn).collect();
    let step_kn = (loads[2] - loads[1]).abs().max(0.5);
    assert!((4.5..5.0 + 5.0 * step_kn).contains(&loads[0]), "the test begins at the preload: {} kN (steps of {step_kn} kN)", loads[0]);
    let end = span / 150.0 + 0.5;
    let past: Vec<f64> = lines.iter().filter_map(|l| l.net_deflection_mm).filter(|v| *v >= end).collect();
    assert!(past.len() >= 3, "three lines past the end {end} mm before the stop: {past:?}");
    let max_net = lines.iter().filter_map(|l| l.net_deflection_mm).fold(f64::MIN, f64::max);
    assert!(max_net < end + 1.5, "stopped soon after the end: {max_net} mm");
    assert!(folder.join("report").is_dir(), "the report of the standard is made at the automatic stop");
    assert_eq!(d.stop(), Some(0));
}

/// The lab day's third start: a start pressed right after a stop — here while that
/// stop's report is held (`TAGDEFLECT_HOLD_REPORT`) and from another client, as after a stop
/// from the command line, an automatic stop or a client that gave up waiting — waits for that
/// stop and starts (200) instead of answering 409 ("its folder is being completed"); then
/// start, stop and start again at once, five times over: every answer 200, every stopped
/// folder complete.
#[test]
fn a_start_right_after_a_stop_starts_once_that_stop_is_through() {
    let dir = tempfile::tempdir().unwrap();
    let tests_dir = dir.path().join("tests");
    let hold = dir.path().join("the-report-may-go");
    let (mut d, addr, token) = demo_with_tests(None, &tests_dir, &[("TAGDEFLECT_HOLD_REPORT", hold.as_os_str())]);
    let command = move |cmd: &str, body: String| {
        let bearer = format!("Bearer {token}");
        let (code, text) = post(
            addr,
            &format!("/api/test/{cmd}"),
            &[("Content-Type", "application/json"), ("Authorization", bearer.as_str())],
            body.as_bytes(),
        );
        (code, serde_json::from_str::<serde_json::Value>(&text).unwrap_or_else(|e| panic!("{cmd}: {e}: {code} {text}")))
    };
    let start = |specimen: &str| {
        format!(
            r#"{{"specimen": "{specimen}", "standard": "astm-c1609", "measured": {{"width_mm": 150, "depth_mm": 150, "span_mm": 450}}}}"#
        )
    };
    let (code, st) = command("start", start("H1"));
    assert_eq!(code, 200, "{st}");
    let c = command.clone();
    let stop = std::thread::spawn(move || c("stop", "{}".into()));
    d.wait_stderr("the report waits until", Duration::from_secs(60), "the stop reached its report");
    let (c, body) = (command.clone(), start("H2"));
    let second = std::thread::spawn(move || c("start", body));
    std::thread::sleep(Duration::from_secs(1));
    assert!(!second.is_finished(), "the start waits while the stop's report is made: {:?}", second.join());
    std::fs::write(&hold, "").unwrap();
    let (code, stopped) = stop.join().unwrap();
    assert_eq!(code, 200, "{stopped}");
    let (code, st) = second.join().unwrap();
    assert_eq!((code, st["state"].as_str()), (200, Some("running")), "{st}");
    assert!(st["id"].as_str().unwrap().ends_with("-H2"), "{st}");
    assert!(Path::new(stopped["folder"].as_str().unwrap()).join("test.json").is_file(), "the first folder complete first");
    let (code, st) = command("stop", "{}".into());
    assert_eq!(code, 200, "{st}");
    // Start, stop, start at once, as the page's day does.
    for k in 0..5 {
        let (code, st) = command("start", start(&format!("R{k}")));
        assert_eq!(code, 200, "start {k} right after a stop: {st}");
        let (code, stopped) = command("stop", "{}".into());
        assert_eq!(code, 200, "stop {k}: {stopped}");
        assert!(Path::new(stopped["folder"].as_str().unwrap()).join("test.json").is_file(), "{stopped}");
    }
    assert!(!tests_dir.join(".running.json").exists(), "no test left running or stopping");
    assert_eq!(d.stop(), Some(0));
}
