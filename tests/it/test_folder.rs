//! A lab test's folder against crashes and bad state files: nothing lost, nothing
//! silently wrong.

use std::fs;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::time::{Duration, Instant};

use tagdeflect_sim::SimParams;

use crate::faults::{tagdeflect_test, whole_feed_lines, LoggedDaemon};

/// A rig of two small simulated cameras at 5 fps with the demo's simulated UTM and a beam for
/// the report, under `dir`, its feed into `feed` if given; the daemon's arguments with
/// `--tests dir/tests`.
fn rig(dir: &Path, feed: Option<&Path>) -> Vec<String> {
    let params =
        SimParams { cameras: 2, width: 480, height: 360, fps: 5.0, frame_sets: 60, rest_frames: 5, subsamples: 4, ..SimParams::default() };
    let mut cfg = crate::common::beam_rig_config(&params);
    cfg.output.feed = feed.map(|f| f.display().to_string());
    let rig = dir.join("rig.toml");
    fs::write(&rig, cfg.to_toml_string()).unwrap();
    let tests = dir.join("tests");
    ["demo", "--config", rig.to_str().unwrap(), "--http", "127.0.0.1:0", "--tests", tests.to_str().unwrap()]
        .iter()
        .map(|s| s.to_string())
        .collect()
}

/// A daemon killed (SIGKILL) while a test's stop is in progress — the test taken off, its
/// report being made — leaves `TESTS/.running.json` saying "stopping" and no `test.json`; the
/// next daemon on the folder completes the stop (report, `test.json` with the stop event) and
/// says so, and tests start again. The kill is made while the daemon holds the report on a
/// file (`TAGDEFLECT_HOLD_REPORT`), so it lands inside the stop every time. Without the
/// "stopping" state (the state removed before the folder was complete) the folder stays
/// without `test.json` and nothing says so.
#[test]
fn a_daemon_killed_during_a_stop_completes_the_folder_at_its_next_start() {
    let dir = tempfile::tempdir().unwrap();
    let args = rig(dir.path(), None);
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let tests_dir = dir.path().join("tests");
    let token_file = tests_dir.join(".token");
    let state = tests_dir.join(".running.json");
    let hold = dir.path().join("never-made");
    let deadline = Instant::now() + Duration::from_secs(240);

    let mut first = LoggedDaemon::start_with(&args, &[("TAGDEFLECT_HOLD_REPORT", hold.as_path())]);
    let addr = first.addr(deadline);
    first.wait_for("the control token", deadline, |d| d.log().contains("control token: "));
    let st = tagdeflect_test(&addr, &token_file, &["start", "--specimen", "K1", "--standard", "astm-c1609"]);
    let id = st["id"].as_str().unwrap().to_string();
    let folder = tests_dir.join(&id);
    first.wait_for("12 lines of the test", deadline, |_| whole_feed_lines(&folder.join("feed.jsonl")).len() >= 12);
    // The stop, from a client that will see the daemon die under it.
    let url = format!("http://{addr}");
    let stop = Command::new(env!("CARGO_BIN_EXE_tagdeflect"))
        .args(["test", "--url", &url, "--token-file", token_file.to_str().unwrap(), "stop"])
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let stop = crate::common::ChildGuard(stop);
    first.wait_for("the stop to reach the report", deadline, |d| d.log().contains("the report waits until"));
    let on_disk = fs::read_to_string(&state).expect("the state is kept while the test stops");
    assert!(on_disk.contains(r#""state":"stopping""#), "{on_disk}");
    first.child.0.kill().unwrap();
    first.child.0.wait().unwrap();
    drop(stop);
    assert!(!folder.join("test.json").exists(), "killed before test.json");
    assert!(!folder.join("report/report.json").exists(), "killed before the report");
    let stopping: serde_json::Value = serde_json::from_str(&fs::read_to_string(&state).unwrap()).unwrap();
    let stop_t_ns = stopping["record"]["stopped_t_ns"].as_i64().expect("the stop's time in the state");

    // The next daemon completes the stop, says so, and tests start again.
    let mut second = LoggedDaemon::start(&args);
    let addr = second.addr(deadline);
    second.wait_for("the control token", deadline, |d| d.log().contains("control token: "));
    second.wait_for("the stopped test's folder completed", deadline, |d| d.log().contains("the stopped test's folder is complete"));
    let log = second.log();
    assert!(log.contains("the daemon stopped while this test was being stopped"), "{log}");
    assert!(!log.contains("resumed from its zero"), "a stopping test is completed, not resumed:\n{log}");
    assert!(!state.exists(), "the state goes once the folder is complete");
    let record: serde_json::Value = serde_json::from_str(&fs::read_to_string(folder.join("test.json")).unwrap()).unwrap();
    assert_eq!(record["stopped_t_ns"].as_i64(), Some(stop_t_ns), "{record}");
    let kinds: Vec<&str> = record["events"].as_array().unwrap().iter().map(|e| e["kind"].as_str().unwrap()).collect();
    assert_eq!(kinds, ["start", "stop"], "{record}");
    assert_eq!(record["lines"].as_u64(), Some(whole_feed_lines(&folder.join("feed.jsonl")).len() as u64), "{record}");
    assert!(record["sha256"]["report/report.json"].is_string(), "the report is there and hashed: {record}");
    let report: serde_json::Value = serde_json::from_str(&fs::read_to_string(folder.join("report/report.json")).unwrap()).unwrap();
    assert!(report.is_object());
    let next = tagdeflect_test(&addr, &token_file, &["start", "--specimen", "K2"]);
    assert_eq!(next["state"], "running", "{next}");
    tagdeflect_test(&addr, &token_file, &["stop"]);
    assert_eq!(second.terminate(), Some(0), "{}", second.log());
}

/// `tagdeflect test ARGS` against the daemon at `addr`, its output whatever it is.
fn test_command(addr: &str, token_file: &Path, args: &[&str]) -> Output {
    let url = format!("http://{addr}");
    Command::new(env!("CARGO_BIN_EXE_tagdeflect"))
        .args(["test", "--url", &url, "--token-file", token_file.to_str().unwrap()])
        .args(args)
        .output()
        .unwrap()
}

/// Fills the filesystem of `dir` (a file `dir/filler`, written until ENOSPC, the last bytes
/// one by one).
fn fill(dir: &Path) -> PathBuf {
    use std::io::Write;
    let filler = dir.join("filler");
    let mut f = fs::File::create(&filler).unwrap();
    for chunk in [65536, 4096, 1] {
        let block = vec![b'x'; chunk];
        while f.write_all(&block).is_ok() {}
    }
    filler
}

/// A full disk under the tests folder (a real filesystem: a 4 MiB tmpfs mounted in a user and
/// mount namespace of the daemon's own, `unshare -rm`, filled by the test through
/// `/proc/PID/root`): the test's lines and UTM samples are held back, not dropped; no partial
/// line is left in a file (each cut back to its last whole line); one error per file and
/// outage; a mark answers 500 naming the state that could not be written; the stop answers
/// 500 saying what is held back and keeps it; once space is free the next stop writes
/// everything, the report included, and the test's feed holds every line of the main feed's
/// (on another disk) that belongs to the test.
#[test]
fn a_full_disk_under_the_tests_folder_holds_the_lines_back_and_the_stop_says_so() {
    let dir = tempfile::tempdir().unwrap();
    let main_feed = dir.path().join("feed.jsonl");
    let args = rig(dir.path(), Some(&main_feed));
    let tests_dir = dir.path().join("tests");
    fs::create_dir_all(&tests_dir).unwrap();
    let mut cmd = Command::new("unshare");
    cmd.args(["-rm", "sh", "-c", r#"mount -t tmpfs -o size=4m tmpfs "$0" && exec "$@""#, tests_dir.to_str().unwrap()]);
    cmd.arg(env!("CARGO_BIN_EXE_tagdeflect")).args(&args);
    let deadline = Instant::now() + Duration::from_secs(240);
    let mut d = LoggedDaemon::spawn(cmd);
    let addr = d.addr(deadline);
    d.wait_for("the control token", deadline, |d| d.log().contains("control token: "));
    // The tests folder as the daemon sees it (its own mount).
    let view = PathBuf::from(format!("/proc/{}/root{}", d.child.0.id(), tests_dir.display()));
    let token_file = view.join(".token");
    let st = tagdeflect_test(&addr, &token_file, &["start", "--specimen", "F1", "--standard", "astm-c1609"]);
    let id = st["id"].as_str().unwrap().to_string();
    let folder = view.join(&id);
    d.wait_for("10 lines of the test", deadline, |_| whole_feed_lines(&folder.join("feed.jsonl")).len() >= 10);

    let filler = fill(&view);
    d.wait_for("the test's feed to fail", deadline, |d| d.log().contains("the test's feed: "));
    let held_from = whole_feed_lines(&folder.join("feed.jsonl")).len();
    let mark = test_command(&addr, &token_file, &["mark", "while the disk is full"]);
    let said = String::from_utf8_lossy(&mark.stderr).to_string();
    assert!(!mark.status.success() && said.contains("500") && said.contains(".running.json"), "{said}");
    let stop = test_command(&addr, &token_file, &["stop"]);
    let said = String::from_utf8_lossy(&stop.stderr).to_string();
    assert!(!stop.status.success() && said.contains("held back"), "the stop says what is held back: {said}");
    for name in ["feed.jsonl", "utm.jsonl"] {
        let text = fs::read_to_string(folder.join(name)).unwrap();
        assert!(text.is_empty() || text.ends_with('\n'), "{name}: no partial line");
        assert!(text.lines().all(|l| serde_json::from_str::<serde_json::Value>(l).is_ok()), "{name}: only whole lines");
    }
    assert!(!folder.join("test.json").exists(), "not complete while lines are held back");
    let refused = test_command(&addr, &token_file, &["start", "--specimen", "F2"]);
    assert!(!refused.status.success(), "no test starts over an unfinished one");

    fs::remove_file(&filler).unwrap();
    let stopped = tagdeflect_test(&addr, &token_file, &["stop"]);
    assert_eq!(stopped["id"], id.as_str());
    let log = d.log();
    assert_eq!(log.matches("the test's feed: ").count(), 1, "one error per outage:\n{log}");
    assert!(log.matches("the test's UTM samples: ").count() <= 1, "one error per outage:\n{log}");
    let lines = whole_feed_lines(&folder.join("feed.jsonl"));
    assert!(lines.len() > held_from, "the held-back lines are written: {} after {held_from}", lines.len());
    let record: serde_json::Value = serde_json::from_str(&fs::read_to_string(folder.join("test.json")).unwrap()).unwrap();
    assert_eq!(record["lines"].as_u64(), Some(lines.len() as u64), "{record}");
    let utm = fs::read_to_string(folder.join("utm.jsonl")).unwrap();
    assert_eq!(record["utm_samples"].as_u64(), Some(utm.lines().count() as u64), "{record}");
    let kinds: Vec<&str> = record["events"].as_array().unwrap().iter().map(|e| e["kind"].as_str().unwrap()).collect();
    assert_eq!(kinds, ["start", "mark", "stop"], "the mark is kept: {record}");
    assert!(folder.join("report/report.json").is_file(), "the report is made once space is free:\n{log}");
    assert!(!view.join(".running.json").exists());
    // Every line of the main feed that belongs to the test, up to the test's last line, is in
    // its feed: none lost while the disk was full.
    let seqs: std::collections::BTreeSet<u64> = lines.iter().map(|l| l.seq).collect();
    let last_t_ns = lines.last().unwrap().t_ns;
    let main: Vec<u64> = whole_feed_lines(&main_feed)
        .iter()
        .filter(|l| l.test.as_ref().is_some_and(|t| t.id == id) && l.t_ns <= last_t_ns)
        .map(|l| l.seq)
        .collect();
    let lost: Vec<&u64> = main.iter().filter(|s| !seqs.contains(s)).collect();
    assert!(lost.is_empty(), "lines of the test lost from its folder: {lost:?}");
    assert_eq!(d.terminate(), Some(0), "{}", d.log());
}

/// A stale `TESTS/.running.json` — its test folder deleted, or not a state at all — does not
/// keep the daemon down (exit 2 under `RestartPreventExitStatus=2` kept the rig down): one
/// WARN naming the file and where it was moved, the daemon up, idle, and tests start.
#[test]
fn a_stale_running_state_is_moved_aside_and_the_daemon_starts_and_tests_run() {
    let dir = tempfile::tempdir().unwrap();
    let args = rig(dir.path(), None);
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let tests_dir = dir.path().join("tests");
    fs::create_dir_all(&tests_dir).unwrap();
    let state = tests_dir.join(".running.json");
    let gone = tests_dir.join("20261201T000000Z-GONE").display().to_string();
    let deleted = format!(
        r#"{{"record":{{"id":"x","specimen":"GONE","started_t_ns":1,"events":[],"lines":0,"utm_samples":0,"sha256":{{}}}},"folder":"{gone}","zero_n":0,"tags":{{}},"net":[0,[],[]],"gauges":{{}},"last_line_t_ns":0}}"#
    );
    let deadline = Instant::now() + Duration::from_secs(240);
    for (k, text) in [deleted.as_str(), "{\"rec\u{0}garbage"].into_iter().enumerate() {
        fs::write(&state, text).unwrap();
        let mut d = LoggedDaemon::start(&args);
        let addr = d.addr(deadline);
        d.wait_for("the control token", deadline, |d| d.log().contains("control token: "));
        let log = d.log();
        assert!(log.contains(&format!("{} cannot be resumed", state.display())) && log.contains(".running.json.stale-"), "{log}");
        assert!(!state.exists());
        assert!(k == 1 || log.contains("is gone"), "the deleted folder named:\n{log}");
        let aside = fs::read_dir(&tests_dir)
            .unwrap()
            .filter(|e| e.as_ref().unwrap().file_name().to_string_lossy().starts_with(".running.json.stale-"))
            .count();
        assert_eq!(aside, k + 1, "kept under another name");
        let st = tagdeflect_test(&addr, &tests_dir.join(".token"), &["start", "--specimen", &format!("S{k}")]);
        assert_eq!(st["state"], "running", "{st}");
        tagdeflect_test(&addr, &tests_dir.join(".token"), &["stop"]);
        assert_eq!(d.terminate(), Some(0), "{}", d.log());
    }
}
