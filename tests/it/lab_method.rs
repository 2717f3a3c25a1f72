//! Test methods and specimens on a running daemon (issue "the test a lab signs", items 1–2):
//! `tagdeflect method list|show|review`, a specimen table imported through `tagdeflect test
//! specimens import` (a bad row refused by row and column), a start refused for missing
//! geometry (the config has no `[specimen.beam]`, as the documented day's), a start with a
//! method on the next specimen, the crack entry, the stop; `test.json` carries the method with
//! its review, the specimen's row, the readings' means, the preload and the crack.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use crate::http::{browser, demo_with_tests, get, post, tagdeflect_test, Daemon};
use tagdeflect::config::Config;
use tagdeflect_sim::SimRig;

/// `tagdeflect ARGS`: exit code, stdout, stderr.
fn tagdeflect(args: &[&str]) -> (i32, String, String) {
    let o = Command::new(env!("CARGO_BIN_EXE_tagdeflect")).args(args).output().unwrap();
    (o.status.code().unwrap_or(-1), String::from_utf8_lossy(&o.stdout).into(), String::from_utf8_lossy(&o.stderr).into())
}

/// `tagdeflect test --url ... --token-file ... ARGS`: exit code, stdout, stderr.
fn test_cli(addr: std::net::SocketAddr, token_file: &Path, args: &[&str]) -> (i32, String, String) {
    let url = format!("http://{addr}");
    let mut all = vec!["test", "--url", url.as_str(), "--token-file", token_file.to_str().unwrap()];
    all.extend_from_slice(args);
    tagdeflect(&all)
}

/// The demo's rig with its specimen seated: loaded at 0.5 mm/min to 0.1 mm (1 kN) in its first
/// seconds and held there — the method's 0.5 kN preload reached (its zero is taken there, a
/// start waits for it), under its 2 kN start limit (a start is not refused for the load).
fn seated() -> tagdeflect_sim::SimParams {
    tagdeflect_sim::SimParams {
        frame_sets: 3000,
        rest_frames: 5,
        rates: "0.5".into(),
        max_deflection_mm: 0.1,
        ..tagdeflect_sim::live_rig::demo_params()
    }
}

#[test]
fn methods_reviewed_specimens_imported_and_a_start_refused_without_geometry() {
    let dir = tempfile::tempdir().unwrap();
    let tests_dir = dir.path().join("tests");
    let t = tests_dir.to_str().unwrap();

    // The methods: shipped, not reviewed; a review names the file's hash; a lab's bad file is
    // located file:line:key.
    let (code, out, err) = tagdeflect(&["method", "list", "--tests", t]);
    assert_eq!(code, 0, "{err}");
    for name in ["C1609-19 v2 astm-c1609", "C1856-17 v3 astm-c1856", "EN14651-05 v1 en-14651"] {
        assert!(out.lines().any(|l| l.starts_with(name) && l.contains("(built-in) not reviewed")), "{name}: {out}");
    }
    let (code, out, err) =
        tagdeflect(&["method", "review", "C1609-19", "--tests", t, "--by", "R. Viewer", "--meaning", "checked against the standard"]);
    assert_eq!(code, 0, "{err}");
    let review: serde_json::Value = serde_json::from_str(&out).unwrap();
    let sha = tagdeflect_core::method::library::sha256_hex(tagdeflect_core::method::SHIPPED[0].1.as_bytes());
    assert_eq!(review["sha256"], sha.as_str());
    // The review is in the folder's audit log, its chain whole.
    let audit = tests_dir.join("audit.jsonl");
    assert_eq!(tagdeflect_core::audit::verify_chain(&audit).unwrap().entries, 1);
    let entry: serde_json::Value = serde_json::from_str(std::fs::read_to_string(&audit).unwrap().lines().next().unwrap()).unwrap();
    assert_eq!((entry["action"].as_str(), entry["user"].as_str()), (Some("method"), Some("R. Viewer")), "{entry}");
    assert_eq!(entry["detail"]["sha256"], sha.as_str());
    let (_, out, _) = tagdeflect(&["method", "show", "C1609-19", "--tests", t]);
    assert!(out.contains("reviewed by R. Viewer on ") && out.contains(&format!("# sha256 {sha}")), "{out}");
    let bad = tagdeflect_core::method::SHIPPED[2].1.replace("EN14651-05", "EN-LAB").replace("[0.04, 0.06]", "[0.06, 0.04]");
    std::fs::write(tests_dir.join("methods/EN-LAB.toml"), &bad).unwrap();
    let line = bad.lines().position(|l| l.contains("[0.06, 0.04]")).unwrap() + 1;
    let (code, _, err) = tagdeflect(&["method", "show", "EN-LAB", "--tests", t]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains(&format!("EN-LAB.toml:{line}: `phase[0].rate_mm_per_min`")), "{err}");

    // The daemon: the demo's rig, its specimen seated under the start limit ([`seated`]), and no
    // [specimen.beam], as the documented day's config.
    let params = seated();
    let mut cfg = Config::from_sim(&SimRig::new(&params).unwrap());
    cfg.utm = Config::demo().utm;
    cfg.specimen.beam = None;
    let cfg_path = dir.path().join("rig.toml");
    std::fs::write(&cfg_path, cfg.to_toml_string()).unwrap();
    let mut d = Daemon::start(&["demo", "--config", cfg_path.to_str().unwrap(), "--http", "127.0.0.1:0", "--tests", t]);
    let addr = d.addr();
    let token_file = tests_dir.join(".token");
    let deadline = Instant::now() + Duration::from_secs(60);
    // The token is written before the control API is served: wait for the API itself.
    while !token_file.is_file() || serde_json::from_slice::<serde_json::Value>(&get(addr, "/api/test").2).unwrap()["state"] != "idle" {
        assert!(Instant::now() < deadline, "no control API within 60 s");
        std::thread::sleep(Duration::from_millis(100));
    }

    // The specimen table: a bad row refused naming row and column (nothing imported), then the table.
    let csv = dir.path().join("specimens.csv");
    std::fs::write(&csv, "id,width_mm,depth_mm,span_mm\nS1,150,150,450\nS2,150,15O,450\n").unwrap();
    let (code, _, err) = test_cli(addr, &token_file, &["specimens", "import", csv.to_str().unwrap()]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("row 2, column depth_mm") && err.contains("15O"), "{err}");
    let table = "id,width_mm,width_mm,depth_mm,depth_mm,span_mm,cast_date,fibre,dosage_kg_m3,client\n\
                 S1,150.2,150.6,149.8,150.0,450,2026-11-01,hooked steel,40,ACME\n\
                 S2,150,,150,,,2026-11-01,hooked steel,40,ACME\n\
                 S3,150,,150,,450,2026-11-02,hooked steel,40,ACME\n";
    std::fs::write(&csv, table).unwrap();
    let (code, out, err) = test_cli(addr, &token_file, &["specimens", "import", csv.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    let answer: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert_eq!((answer["imported"].as_u64(), answer["next"].as_str()), (Some(3), Some("S1")), "{answer}");
    assert_eq!(post(addr, "/api/specimens", &[("Content-Type", "text/csv")], table.as_bytes()).0, 401, "token-guarded");

    // Refused: a start whose report could not be made, naming what is missing.
    let (code, _, err) = test_cli(addr, &token_file, &["start", "--method", "C1609-19", "--specimen", "S2"]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("(400)") && err.contains("method C1609-19 needs span_mm for its report"), "{err}");
    let (code, _, err) = test_cli(addr, &token_file, &["start", "--standard", "astm-c1609", "--specimen", "X1"]);
    assert!(code == 2 && err.contains("standard astm-c1609 needs width_mm, depth_mm, span_mm"), "{err}");

    // The next specimen with the method: its means measured, the method with its review.
    let st = tagdeflect_test(addr, &token_file, &["start", "--method", "C1609-19", "--specimen", "next", "--operator", "A. Tester"]);
    assert_eq!(st["specimen"], "S1", "{st}");
    assert_eq!(st["method"]["review"]["by"], "R. Viewer", "{st}");
    let id = st["id"].as_str().unwrap().to_string();
    let with_test = |d: &Daemon| d.lines().iter().filter(|(_, l)| l.test.as_ref().is_some_and(|t| t.id == id)).count();
    while with_test(&d) < 8 {
        assert!(Instant::now() < deadline + Duration::from_secs(60), "the test's lines did not come");
        std::thread::sleep(Duration::from_millis(100));
    }
    let st = tagdeflect_test(addr, &token_file, &["crack", "100"]);
    assert_eq!(st["events"].as_array().unwrap().last().unwrap()["kind"], "crack", "{st}");
    let (code, out, err) = test_cli(addr, &token_file, &["stop", "--crack-mm", "-30"]);
    let stopped: serde_json::Value = serde_json::from_str(&out).unwrap_or_else(|e| panic!("{e}: {out} {err}"));
    let folder = PathBuf::from(stopped["folder"].as_str().unwrap());
    // The report from the row's means (the config has no beam); had it failed, the stop says so and exits 3.
    println!("STOP {code} {stopped} {err}");
    match stopped["report_error"].as_str() {
        Some(why) => assert!(code == 3 && err.contains(why), "{code} {err}"),
        None => assert!(code == 0 && folder.join("report/report.json").is_file(), "{code} {err}"),
    }
    let record: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(folder.join("test.json")).unwrap()).unwrap();
    assert_eq!(record["method"]["name"], "C1609-19");
    assert_eq!(record["method"]["sha256"], sha.as_str());
    assert_eq!(record["method"]["review"]["meaning"], "checked against the standard");
    assert_eq!(record["standard"], "astm-c1609");
    assert_eq!(record["specimen_info"]["id"], "S1");
    assert_eq!(record["specimen_info"]["readings"]["width_mm"], serde_json::json!([150.2, 150.6]));
    assert_eq!(record["specimen_info"]["client"], "ACME");
    assert!(record["specimen_info"]["age_days"].as_u64().is_some(), "{record}");
    let m = &record["measured"];
    assert!((m["width_mm"].as_f64().unwrap() - 150.4).abs() < 1e-9 && (m["depth_mm"].as_f64().unwrap() - 149.9).abs() < 1e-9, "{m}");
    assert_eq!(m["span_mm"], 450.0);
    assert_eq!(record["crack"]["position_mm"], -30.0, "the stop's entry replaced the first");
    assert_eq!(record["crack"]["inside_middle_third"], true);
    assert!(record["preload"]["load_kn"].as_f64().is_some_and(|l| l.abs() < 2.0), "{record}");
    let kinds: Vec<&str> = record["events"].as_array().unwrap().iter().map(|e| e["kind"].as_str().unwrap()).collect();
    assert_eq!(kinds, ["start", "preload", "crack", "crack", "stop"], "{record}");
    let table: serde_json::Value = serde_json::from_slice(&get(addr, "/api/specimens").2).unwrap();
    assert_eq!(table["next"], "S2");
    assert_eq!(table["specimens"][0]["test"], id.as_str());
    assert_eq!(d.stop(), Some(0));
}

/// The page's start form in Chromium: the method chosen (its standard taken), the table's next
/// specimen offered, a start refused for missing geometry (the form and the answer name the
/// span), a start on the next specimen with the rate window from its span (the config has no
/// `[specimen.beam]`), a mark, a stop with a crack entry.
#[test]
fn the_start_form_takes_a_method_and_the_next_specimen_in_chromium() {
    let dir = tempfile::tempdir().unwrap();
    let tests_dir = dir.path().join("tests");
    let params = seated();
    let mut cfg = Config::from_sim(&SimRig::new(&params).unwrap());
    cfg.utm = Config::demo().utm;
    cfg.specimen.beam = None;
    let cfg_path = dir.path().join("rig.toml");
    std::fs::write(&cfg_path, cfg.to_toml_string()).unwrap();
    let mut d =
        Daemon::start(&["demo", "--config", cfg_path.to_str().unwrap(), "--http", "127.0.0.1:0", "--tests", tests_dir.to_str().unwrap()]);
    let addr = d.addr();
    let token_file = tests_dir.join(".token");
    let deadline = Instant::now() + Duration::from_secs(60);
    // The token is written before the control API is served: wait for the API itself.
    while !token_file.is_file() || serde_json::from_slice::<serde_json::Value>(&get(addr, "/api/test").2).unwrap()["state"] != "idle" {
        assert!(Instant::now() < deadline, "no control API within 60 s");
        std::thread::sleep(Duration::from_millis(100));
    }
    let token = std::fs::read_to_string(&token_file).unwrap().trim().to_string();
    let table = "id,width_mm,depth_mm,depth_mm,span_mm,cast_date\nS1,150.2,149.8,150.2,450,2026-11-01\nS2,150,150,,,2026-11-01\n";
    let bearer = format!("Bearer {token}");
    let (code, answer) = post(addr, "/api/specimens", &[("Content-Type", "text/csv"), ("Authorization", &bearer)], table.as_bytes());
    assert_eq!(code, 200, "{answer}");
    let seen = browser("start_form_page.py", [format!("http://{addr}/"), token]);
    assert!(seen.get("error").is_none() && seen.get("timeout").is_none(), "{seen}\n{}", d.stderr.lock().unwrap());
    assert_eq!(seen["specimen_default"], "next", "{seen}");
    assert_eq!(seen["standard_taken"], "astm-c1609", "{seen}");
    assert!(
        seen["requires_s2"].as_str().unwrap().contains("C1609-19 v2, not reviewed needs width_mm, depth_mm, span_mm — missing: span_mm"),
        "{seen}"
    );
    let refused = seen["refused"].as_str().unwrap();
    assert!(refused.starts_with("start refused (400)") && refused.contains("needs span_mm"), "{refused}");
    assert!(seen["requires_next"].as_str().unwrap().ends_with("all given"), "{seen}");
    assert_eq!(seen["specimen_typed_across_a_refresh"], "next", "the table's refresh wrote into a field being typed in: {seen}");
    assert_eq!(seen["specimen"], "S1");
    // C1609 for a 150 mm deep beam: 0.035–0.10 mm/min up to L/900 = 0.5 mm of the row's span.
    assert_eq!(seen["rate_window"], "window 0.035–0.1 mm/min (up to 0.500 mm)", "{seen}");
    assert_eq!(seen["prompts"], 3, "the token, the note, the confirmation: {seen}");
    // The refused start's 400 is the one error the browser logs.
    let errors: Vec<&str> = seen["console_errors"].as_array().unwrap().iter().filter_map(|e| e.as_str()).collect();
    assert!(errors.iter().all(|e| e.contains("/api/test/start") && e.contains("400")), "{seen}");
    let folder = PathBuf::from(seen["folder"].as_str().unwrap());
    let record: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(folder.join("test.json")).unwrap()).unwrap();
    assert_eq!(record["method"]["name"], "C1609-19");
    assert_eq!(record["specimen"], "S1");
    assert_eq!(record["operator"], "A. Tester");
    assert_eq!(record["measured"]["depth_mm"], 150.0);
    assert_eq!(record["crack"], serde_json::json!({"position_mm": -30.0, "inside_middle_third": true, "t_ns": record["crack"]["t_ns"]}));
    let kinds: Vec<&str> = record["events"].as_array().unwrap().iter().map(|e| e["kind"].as_str().unwrap()).collect();
    assert_eq!(kinds, ["start", "preload", "mark", "crack", "stop"], "{record}");
    // The page says when the report could not be made (the seated beam has no first peak).
    let report_made = folder.join("report/report.json").is_file();
    assert_eq!(seen["report"].as_str().unwrap().starts_with("no report: "), !report_made, "{seen}");
    assert_eq!(d.stop(), Some(0));
}

/// `tagdeflect test start` sent while the previous test's stop is still being completed (its
/// report held back by the daemon's fault-injection hold): the daemon waits 20 s for the
/// stop, then answers 409 with `Retry-After: 5`; the command says it waits and sends the
/// start again, a bounded number of times. With `--retries 1` and the report still held it
/// gives up with the daemon's reason (exit 2); by default it starts once the stop is through
/// (the hold released only after it said it waits: no timing decides the outcome).
#[test]
fn test_start_follows_retry_after_while_a_stop_is_completed() {
    use std::io::BufRead;
    let dir = tempfile::tempdir().unwrap();
    let tests_dir = dir.path().join("tests");
    let hold = dir.path().join("the-report-may-go");
    let (mut d, addr, token) = demo_with_tests(None, &tests_dir, &[("TAGDEFLECT_HOLD_REPORT", hold.as_os_str())]);
    let token_file = tests_dir.join(".token");
    let start = |specimen: &str, extra: &[&str]| -> Vec<String> {
        let mut a = vec!["start", "--specimen", specimen, "--standard", "astm-c1609"];
        a.extend(["--measured", "width_mm=150", "--measured", "depth_mm=150", "--measured", "span_mm=450"]);
        a.extend(extra);
        a.into_iter().map(str::to_string).collect()
    };
    let cli = |a: &[String]| test_cli(addr, &token_file, &a.iter().map(String::as_str).collect::<Vec<_>>());
    let (code, _, err) = cli(&start("R1", &[]));
    assert_eq!(code, 0, "{err}");
    // The stop, from another client: its report waits for the hold.
    let stop = std::thread::spawn(move || {
        let bearer = format!("Bearer {token}");
        post(addr, "/api/test/stop", &[("Content-Type", "application/json"), ("Authorization", bearer.as_str())], b"{}")
    });
    d.wait_stderr("the report waits until", Duration::from_secs(60), "the stop reached its report");

    // Bounded: one retry, the stop still being completed after it: the daemon's reason, exit 2.
    let (code, out, err) = cli(&start("R2", &["--retries", "1"]));
    assert_eq!(code, 2, "{out}{err}");
    assert!(err.contains("sending it again in 5 s (retry 1 of 1)"), "says it waits: {err}");
    assert_eq!(err.matches("sending it again").count(), 1, "one retry only: {err}");
    assert!(err.contains("the daemon refused (409)") && err.contains("still being stopped"), "{err}");

    // By default: it waits as told and starts once the stop is through.
    let url = format!("http://{addr}");
    let mut child = Command::new(env!("CARGO_BIN_EXE_tagdeflect"))
        .args(["test", "--url", url.as_str(), "--token-file", token_file.to_str().unwrap()])
        .args(start("R3", &[]))
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    let stderr = child.stderr.take().unwrap();
    let reader = std::thread::spawn(move || {
        let mut all = String::new();
        for line in std::io::BufReader::new(stderr).lines().map_while(Result::ok) {
            if line.contains("sending it again") {
                let _ = tx.send(());
            }
            all += &line;
            all.push('\n');
        }
        all
    });
    rx.recv_timeout(Duration::from_secs(120)).expect("the start says it waits to send again");
    std::fs::write(&hold, "").unwrap();
    let out = child.wait_with_output().unwrap();
    let err = reader.join().unwrap();
    assert_eq!(out.status.code(), Some(0), "{err}");
    assert!(err.contains("sending it again in 5 s (retry 1 of 3)"), "{err}");
    let st: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap_or_else(|e| panic!("{e}: {err}"));
    assert_eq!(st["state"], "running", "{st}");
    assert!(st["id"].as_str().unwrap().ends_with("-R3"), "{st}");
    let _ = stop.join();
    // Stopped at once (its report, of a curve of a point or two, is not the point here).
    let bearer = format!("Bearer {}", std::fs::read_to_string(&token_file).unwrap().trim());
    let (code, text) = post(addr, "/api/test/stop", &[("Content-Type", "application/json"), ("Authorization", bearer.as_str())], b"{}");
    assert_eq!(code, 200, "{text}");
    assert_eq!(d.stop(), Some(0));
}

/// The page's start while the previous test's stop is still being completed (its report held
/// back): the daemon answers 409 with `Retry-After` after its 20-s wait; the page says it waits
/// and presses start again by itself, and the test runs once the stop is through (the hold
/// released by the browser's driver only after the page said it waits: no timing decides).
#[test]
fn the_page_presses_start_again_after_the_retry_after_of_a_stop_being_completed() {
    let dir = tempfile::tempdir().unwrap();
    let tests_dir = dir.path().join("tests");
    let hold = dir.path().join("the-report-may-go");
    let (mut d, addr, token) = demo_with_tests(None, &tests_dir, &[("TAGDEFLECT_HOLD_REPORT", hold.as_os_str())]);
    let token_file = tests_dir.join(".token");
    let start = ["start", "--specimen", "P1", "--standard", "astm-c1609", "--measured", "width_mm=150", "--measured", "depth_mm=150"];
    let (code, _, err) = test_cli(addr, &token_file, &[&start[..], &["--measured", "span_mm=450"]].concat());
    assert_eq!(code, 0, "{err}");
    let bearer = format!("Bearer {token}");
    let stop = std::thread::spawn(move || {
        post(addr, "/api/test/stop", &[("Content-Type", "application/json"), ("Authorization", bearer.as_str())], b"{}")
    });
    d.wait_stderr("the report waits until", Duration::from_secs(60), "the stop reached its report");
    let seen = browser("start_retry_page.py", [format!("http://{addr}/"), token, hold.display().to_string(), "P2".to_string()]);
    assert!(seen.get("error").is_none(), "{seen}\n{}", d.stderr.lock().unwrap());
    assert_eq!(seen["start_disabled"], true, "the page greys start while it knows of the stop: {seen}");
    let waits = seen["waits"].as_str().unwrap();
    assert!(waits.contains("still being stopped") && waits.ends_with("(again in 5 s)"), "{waits}");
    let running = seen["state_after"].as_str().unwrap();
    assert!(running.starts_with("running: ") && running.contains("-P2"), "{seen}");
    assert_eq!(seen["message_after"], "start done", "{seen}");
    // Chromium logs each 409 answer as a failed resource; nothing else is an error.
    let errors = seen["console_errors"].as_array().unwrap().iter().filter(|e| !e.as_str().unwrap().contains("409")).count();
    assert_eq!(errors, 0, "{seen}");
    let _ = stop.join();
    let (code, _, err) = test_cli(addr, &token_file, &["stop"]);
    assert_eq!(code, 0, "{err}");
    assert_eq!(d.stop(), Some(0));
}
