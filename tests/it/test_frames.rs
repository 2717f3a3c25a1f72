//! A test's own frames in its folder (`[output] record_tests`): recorded
//! from its start to its stop, hashed in `test.json` and checked by `report verify`, and
//! replayable as a recording.

use std::collections::{BTreeMap, BTreeSet};
use std::fs;
use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

use tagdeflect_sim::SimParams;

use crate::faults::{tagdeflect_test, whole_feed_lines, LoggedDaemon};

/// The demo rig of `test_folder` (two small simulated cameras at 5 fps, the simulated UTM, a
/// beam) with each test's frames recorded; the daemon's arguments with `--tests dir/tests`.
fn rig(dir: &Path) -> Vec<String> {
    rig_reserve(dir, None)
}

/// [`rig`] with `[output] record_tests_reserve_mb` given.
fn rig_reserve(dir: &Path, reserve_mb: Option<f64>) -> Vec<String> {
    rig_with(dir, reserve_mb, true, 60)
}

/// The rig of [`rig`] with the reserve, `[output] record_tests` and the simulated frame sets
/// (at 5 fps) given.
fn rig_with(dir: &Path, reserve_mb: Option<f64>, record_tests: bool, frame_sets: u32) -> Vec<String> {
    let params =
        SimParams { cameras: 2, width: 480, height: 360, fps: 5.0, frame_sets, rest_frames: 5, subsamples: 4, ..SimParams::default() };
    let mut cfg = crate::common::beam_rig_config(&params);
    cfg.output.record_tests = record_tests;
    cfg.output.record_tests_reserve_mb = reserve_mb;
    let rig = dir.join("rig.toml");
    fs::write(&rig, cfg.to_toml_string()).unwrap();
    let tests = dir.join("tests");
    ["demo", "--config", rig.to_str().unwrap(), "--http", "127.0.0.1:0", "--tests", tests.to_str().unwrap()]
        .iter()
        .map(|s| s.to_string())
        .collect()
}

/// `tagdeflect report verify DIR`: (success, what it printed).
fn report_verify(dir: &Path) -> (bool, String) {
    let o = Command::new(env!("CARGO_BIN_EXE_tagdeflect")).args(["report", "verify"]).arg(dir).output().unwrap();
    (o.status.success(), format!("{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr)))
}

/// A lab test with its frames recorded: the folder's `frames/` is a recording of the frames
/// from the test's start (none older) with the test's UTM samples, every frame file listed in
/// `test.json` and checked by `report verify` (a frame changed afterwards is named); `replay`
/// of it gives every line of a whole live set at its time with its tags, and a line of a
/// partial set (a camera's frame late, SPEC's drop policy) has its frames in the recording.
/// Without the option a test folder holds no frames.
#[test]
fn a_test_with_its_frames_recorded_replays_to_its_lines_and_verifies() {
    let dir = tempfile::tempdir().unwrap();
    let args = rig(dir.path());
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let tests_dir = dir.path().join("tests");
    let token = tests_dir.join(".token");
    let deadline = Instant::now() + Duration::from_secs(300);
    let mut d = LoggedDaemon::start(&args);
    let addr = d.addr(deadline);
    d.wait_for("the control token", deadline, |d| d.log().contains("control token: "));
    let st = tagdeflect_test(&addr, &token, &["start", "--specimen", "FR1", "--standard", "astm-c1609"]);
    let id = st["id"].as_str().unwrap().to_string();
    let folder = tests_dir.join(&id);
    d.wait_for("15 lines of the test", deadline, |_| whole_feed_lines(&folder.join("feed.jsonl")).len() >= 15);
    tagdeflect_test(&addr, &token, &["stop"]);
    assert_eq!(d.terminate(), Some(0), "{}", d.log());

    let record: serde_json::Value = serde_json::from_str(&fs::read_to_string(folder.join("test.json")).unwrap()).unwrap();
    let started_t_ns = record["started_t_ns"].as_i64().unwrap();
    let hashed: Vec<&String> = record["sha256"].as_object().unwrap().keys().filter(|k| k.starts_with("frames/")).collect();
    let index = fs::read_to_string(folder.join("frames/frames.jsonl")).unwrap();
    let frames: Vec<serde_json::Value> = index.lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    // Every frame the test's lines were made of is recorded (a loaded machine renders the
    // simulated cameras late and skips frames, a line then made of fewer: counted by line).
    let used: usize = whole_feed_lines(&folder.join("feed.jsonl")).iter().map(|l| l.cameras.iter().filter(|c| c.frame).count()).sum();
    assert!(used >= 15 && frames.len() >= used, "{} frames recorded, {used} in the test's lines", frames.len());
    assert!(frames.iter().all(|f| f["t_ns"].as_i64().unwrap() >= started_t_ns), "no frame before the test's start");
    for f in &frames {
        let file = format!("frames/{}", f["file"].as_str().unwrap());
        assert!(hashed.contains(&&file), "{file} is hashed in test.json");
    }
    for name in ["frames/frames.jsonl", "frames/tagdeflect.toml"] {
        assert!(hashed.contains(&&name.to_string()), "{name} in test.json: {hashed:?}");
    }
    let (ok, said) = report_verify(&folder);
    assert!(ok, "report verify: {said}");

    // Replayed, the frames give the test's lines: same times, same tags.
    let o = Command::new(env!("CARGO_BIN_EXE_tagdeflect")).arg("replay").arg(folder.join("frames")).output().unwrap();
    assert!(o.status.success(), "replay: {}", String::from_utf8_lossy(&o.stderr));
    let tags =
        |l: &serde_json::Value| -> BTreeSet<u64> { l["tags"].as_array().unwrap().iter().map(|t| t["id"].as_u64().unwrap()).collect() };
    let replayed: BTreeMap<i64, BTreeSet<u64>> = String::from_utf8_lossy(&o.stdout)
        .lines()
        .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap())
        .map(|v| (v["t_ns"].as_i64().unwrap(), tags(&v)))
        .collect();
    let text = fs::read_to_string(folder.join("feed.jsonl")).unwrap();
    let live: Vec<serde_json::Value> = text.lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    // A live set waits a frame period for a missing camera and is then measured without it
    // (`partial_set`, SPEC's drop policy; on a loaded machine the simulated cameras render
    // late); the replay, as fast as it reads, waits for every camera, so the same frames make
    // one whole set at another time. Such a line is checked by its frames, all recorded. The
    // first line's set may hold a frame exposed just before the start, which is not recorded.
    let (whole, partial): (Vec<&serde_json::Value>, Vec<&serde_json::Value>) =
        live.iter().filter(|l| l["t_ns"].as_i64().unwrap() - started_t_ns > 10_000_000).partition(|l| l["partial_set"] != true);
    let differ: Vec<i64> =
        whole.iter().filter(|l| replayed.get(&l["t_ns"].as_i64().unwrap()) != Some(&tags(l))).map(|l| l["seq"].as_i64().unwrap()).collect();
    assert!(
        !whole.is_empty() && differ.is_empty(),
        "of the test's {} lines of whole sets these seq differ replayed: {differ:?}",
        whole.len()
    );
    for l in &partial {
        assert!(partial_set_recorded(l, &frames), "the frames of a partial set, seq {}, are recorded: {l}", l["seq"]);
    }

    // A frame changed after the stop is named.
    let first = folder.join("frames").join(frames[0]["file"].as_str().unwrap());
    let mut bytes = fs::read(&first).unwrap();
    let last = bytes.len() - 1;
    bytes[last] ^= 0xff;
    fs::write(&first, bytes).unwrap();
    let (ok, said) = report_verify(&folder);
    assert!(!ok && said.contains(frames[0]["file"].as_str().unwrap()), "{said}");
}

/// Whether the frames a live line of a partial set was made of are in the recording `frames`
/// (its index lines): for each camera with a frame in the line, that camera's recorded frame
/// nearest the line's time; their mean time (a set's time) is the line's.
fn partial_set_recorded(line: &serde_json::Value, frames: &[serde_json::Value]) -> bool {
    let t_ns = line["t_ns"].as_i64().unwrap();
    let cameras = line["cameras"].as_array().unwrap().iter().filter(|c| c["frame"] == true).map(|c| c["name"].as_str().unwrap());
    let nearest: Option<Vec<i64>> = cameras
        .map(|name| frames.iter().filter(|f| f["camera"] == name).map(|f| f["t_ns"].as_i64().unwrap()).min_by_key(|t| (t - t_ns).abs()))
        .collect();
    let Some(times) = nearest.filter(|t| !t.is_empty()) else { return false };
    let mean = times[0] + times.iter().map(|t| t - times[0]).sum::<i64>() / times.len() as i64;
    (mean - t_ns).abs() <= 1
}

/// The frames index of a test's recording `sub` (`frames`, `frames-2`): each frame's `t_ns`
/// (a daemon killed mid-test may leave a partial last line: left out).
fn frame_times(folder: &Path, sub: &str) -> Vec<i64> {
    let text = fs::read_to_string(folder.join(sub).join("frames.jsonl")).unwrap_or_default();
    text.lines().filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok()).map(|f| f["t_ns"].as_i64().unwrap()).collect()
}

/// The disk's reserve for the lines: the tests folder on a 40 MiB tmpfs of the daemon's own
/// (`unshare -rm`) with `record_tests_reserve_mb = 30`: the test's frames stop once less than
/// 30 MB is free — one WARN, `test.json` `frames_stopped` (the reserve, the free space, the
/// time) — while its lines go on to the stop; no frame after that time; the folder verifies.
/// Read while the daemon lives (its tmpfs goes with it). Without the guard the frames went on
/// until the disk was full and the test's lines were held back.
#[test]
fn a_tests_frames_stop_at_the_disks_reserve_and_its_lines_go_on() {
    let dir = tempfile::tempdir().unwrap();
    let args = rig_reserve(dir.path(), Some(30.0));
    let tests_dir = dir.path().join("tests");
    fs::create_dir_all(&tests_dir).unwrap();
    let mut cmd = Command::new("unshare");
    cmd.args(["-rm", "sh", "-c", r#"mount -t tmpfs -o size=40m tmpfs "$0" && exec "$@""#, tests_dir.to_str().unwrap()]);
    cmd.arg(env!("CARGO_BIN_EXE_tagdeflect")).args(&args);
    let deadline = Instant::now() + Duration::from_secs(300);
    let mut d = LoggedDaemon::spawn(cmd);
    let addr = d.addr(deadline);
    d.wait_for("the control token", deadline, |d| d.log().contains("control token: "));
    let view = std::path::PathBuf::from(format!("/proc/{}/root{}", d.child.0.id(), tests_dir.display()));
    let token = view.join(".token");
    let st = tagdeflect_test(&addr, &token, &["start", "--specimen", "FR2", "--standard", "astm-c1609"]);
    let folder = view.join(st["id"].as_str().unwrap());
    d.wait_for("the frames to stop at the reserve", deadline, |d| d.log().contains("the test's frames stop"));
    let lines_then = whole_feed_lines(&folder.join("feed.jsonl")).len();
    d.wait_for("ten lines of the test after", deadline, |_| whole_feed_lines(&folder.join("feed.jsonl")).len() >= lines_then + 10);
    tagdeflect_test(&addr, &token, &["stop"]);
    let record: serde_json::Value = serde_json::from_str(&fs::read_to_string(folder.join("test.json")).unwrap()).unwrap();
    let (ok, said) = report_verify(&folder);
    let frames = frame_times(&folder, "frames");
    let lines = whole_feed_lines(&folder.join("feed.jsonl"));
    assert_eq!(d.terminate(), Some(0), "{}", d.log());
    let log = d.log();
    assert_eq!(log.matches("the test's frames stop").count(), 1, "said once:\n{log}");
    let stopped = &record["frames_stopped"];
    assert_eq!(stopped["folder"], "frames", "{record}");
    assert_eq!(stopped["reserve_mb"].as_f64(), Some(30.0), "{record}");
    assert!(stopped["free_mb"].as_f64().unwrap() < 30.0, "{record}");
    let at = stopped["t_ns"].as_i64().unwrap();
    assert!(!frames.is_empty() && frames.iter().all(|&t| t < at), "no frame from the stop on: {} frames", frames.len());
    assert!(lines.iter().filter(|l| l.t_ns > at).count() >= 10, "the test's lines go on after its frames stopped");
    assert_eq!(record["lines"].as_u64(), Some(lines.len() as u64));
    assert!(ok, "report verify: {said}");
}

/// A test resumed after its daemon was killed (SIGKILL) records its frames anew into
/// `frames-2/` (a recording is never appended to by another process): the frames before the
/// kill stay in `frames/`, those after the resume are in `frames-2/` and later; `test.json`
/// hashes the files of both and `report verify` passes.
#[test]
fn a_resumed_tests_frames_go_on_in_frames_2() {
    let dir = tempfile::tempdir().unwrap();
    let args = rig(dir.path());
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let tests_dir = dir.path().join("tests");
    let token = tests_dir.join(".token");
    let deadline = Instant::now() + Duration::from_secs(400);
    let mut first = LoggedDaemon::start(&args);
    let addr = first.addr(deadline);
    let st = tagdeflect_test(&addr, &token, &["start", "--specimen", "FR3", "--standard", "astm-c1609"]);
    let folder = tests_dir.join(st["id"].as_str().unwrap());
    first.wait_for("10 frames of the test", deadline, |_| frame_times(&folder, "frames").len() >= 10);
    first.child.0.kill().unwrap();
    first.child.0.wait().unwrap();
    let before = frame_times(&folder, "frames");

    let mut second = LoggedDaemon::start(&args);
    let addr = second.addr(deadline);
    second.wait_for("10 frames after the resume", deadline, |_| frame_times(&folder, "frames-2").len() >= 10);
    tagdeflect_test(&addr, &token, &["stop"]);
    assert_eq!(second.terminate(), Some(0), "{}", second.log());
    assert!(second.log().contains("resumed") || second.log().contains("resume"), "{}", second.log());

    let after = frame_times(&folder, "frames-2");
    assert!(frame_times(&folder, "frames").starts_with(&before), "the first recording is left as it was");
    assert!(after.len() >= 10 && after[0] > *before.last().unwrap(), "frames-2 goes on after the kill");
    let record: serde_json::Value = serde_json::from_str(&fs::read_to_string(folder.join("test.json")).unwrap()).unwrap();
    let hashed: Vec<&String> = record["sha256"].as_object().unwrap().keys().collect();
    for sub in ["frames", "frames-2"] {
        let index = format!("{sub}/frames.jsonl");
        assert!(hashed.contains(&&index), "{index} in test.json: {hashed:?}");
        let n = hashed.iter().filter(|k| k.starts_with(&format!("{sub}/")) && !k.ends_with(".jsonl") && !k.ends_with(".toml")).count();
        assert!(n >= frame_times(&folder, sub).len(), "{sub}: every frame file hashed ({n})");
    }
    assert!(!folder.join("frames-3").exists());
    let (ok, said) = report_verify(&folder);
    assert!(ok, "report verify: {said}");
}

/// The test's `test.json` as JSON.
fn test_json(folder: &Path) -> serde_json::Value {
    serde_json::from_str(&fs::read_to_string(folder.join("test.json")).unwrap()).unwrap()
}

/// A lab's method in `tests/methods/NAME.toml`: the shipped C1609-19 renamed, any start load
/// allowed (the simulated beam may be loaded already), with `extra` keys first.
fn lab_method(tests_dir: &Path, name: &str, extra: &str) {
    let shipped = tagdeflect_core::method::SHIPPED[0].1;
    let text = shipped.replacen("name = \"C1609-19\"", &format!("name = \"{name}\""), 1).replacen(
        "max_start_load_kn = 2.0",
        "max_start_load_kn = 1000.0",
        1,
    );
    assert_ne!(text, shipped);
    fs::create_dir_all(tests_dir.join("methods")).unwrap();
    fs::write(tests_dir.join("methods").join(format!("{name}.toml")), format!("{extra}{text}")).unwrap();
}

/// A method's `record_frames` wins over the rig's `[output] record_tests` (here `false`), test
/// by test in one daemon run: a test of a method with `record_frames = true` records its
/// frames (`frames/`, hashed, verified), the next test, of a method that does not say, records
/// none (the rig's default); each `test.json` says which (`record_frames`).
#[test]
fn a_methods_record_frames_decides_for_its_tests_over_the_rigs_default() {
    let dir = tempfile::tempdir().unwrap();
    let args = rig_with(dir.path(), None, false, 400);
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let tests_dir = dir.path().join("tests");
    lab_method(&tests_dir, "C1609-FRAMES", "record_frames = true\n");
    lab_method(&tests_dir, "C1609-PLAIN", "");
    let token = tests_dir.join(".token");
    let deadline = Instant::now() + Duration::from_secs(300);
    let mut d = LoggedDaemon::start(&args);
    let addr = d.addr(deadline);
    d.wait_for("the control token", deadline, |d| d.log().contains("control token: "));
    let mut folders = Vec::new();
    for (specimen, method) in [("FR6", "C1609-FRAMES"), ("FR7", "C1609-PLAIN")] {
        let st = tagdeflect_test(&addr, &token, &["start", "--specimen", specimen, "--method", method]);
        let folder = tests_dir.join(st["id"].as_str().unwrap());
        d.wait_for("10 lines of the test", deadline, |_| whole_feed_lines(&folder.join("feed.jsonl")).len() >= 10);
        tagdeflect_test(&addr, &token, &["stop"]);
        folders.push(folder);
    }
    assert_eq!(d.terminate(), Some(0), "{}", d.log());

    let (with, without) = (test_json(&folders[0]), test_json(&folders[1]));
    assert_eq!(with["method"]["name"], "C1609-FRAMES");
    assert_eq!(with["record_frames"], true, "{with}");
    let frames = frame_times(&folders[0], "frames");
    assert!(frames.len() >= 10, "{} frames recorded for the method with record_frames", frames.len());
    let hashed = with["sha256"].as_object().unwrap().keys().filter(|k| k.starts_with("frames/")).count();
    assert!(hashed >= frames.len() + 2, "every frame file hashed: {hashed}");
    assert_eq!(without["method"]["name"], "C1609-PLAIN");
    assert_eq!(without["record_frames"], false, "{without}");
    assert!(!folders[1].join("frames").exists(), "no frames for the method that leaves it to the rig");
    assert!(without["sha256"].as_object().unwrap().keys().all(|k| !k.starts_with("frames")), "{without}");
    for f in &folders {
        let (ok, said) = report_verify(f);
        assert!(ok, "report verify {}: {said}", f.display());
    }
}

/// A test whose frames stopped at the disk's reserve records no frames again when it is
/// resumed after its daemon was killed (SIGKILL): the stop is in the running test's state at
/// once, the resumed test's `test.json` keeps it (`frames_stopped`: the first daemon's time,
/// `frames`, its reserve) and no `frames-2/` is made — though the second daemon has no reserve
/// at all; the lines go on after the resume and the folder verifies. The first daemon's
/// reserve (10⁹ MB) is above any disk's free space: its frames stop at the first frame.
#[test]
fn a_frames_stop_before_a_restart_holds_for_the_resumed_test() {
    let dir = tempfile::tempdir().unwrap();
    let tests_dir = dir.path().join("tests");
    let token = tests_dir.join(".token");
    let deadline = Instant::now() + Duration::from_secs(400);
    let args = rig_with(dir.path(), Some(1e9), true, 300);
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let mut first = LoggedDaemon::start(&args);
    let addr = first.addr(deadline);
    let st = tagdeflect_test(&addr, &token, &["start", "--specimen", "FR8", "--standard", "astm-c1609"]);
    let folder = tests_dir.join(st["id"].as_str().unwrap());
    first.wait_for("the frames to stop at the reserve", deadline, |d| d.log().contains("the test's frames stop"));
    let state = tests_dir.join(".running.json");
    let kept = Instant::now() + Duration::from_secs(30);
    first
        .wait_for("the stop in the running test's state", kept, |_| fs::read_to_string(&state).is_ok_and(|s| s.contains("frames_stopped")));
    first.child.0.kill().unwrap();
    first.child.0.wait().unwrap();
    let killed_t_ns = tagdeflect_core::clock::now_epoch_ns();
    let lines_before = whole_feed_lines(&folder.join("feed.jsonl")).len();

    let args = rig_with(dir.path(), Some(0.0), true, 300);
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let mut second = LoggedDaemon::start(&args);
    let addr = second.addr(deadline);
    second.wait_for("10 lines after the resume", deadline, |_| whole_feed_lines(&folder.join("feed.jsonl")).len() >= lines_before + 10);
    tagdeflect_test(&addr, &token, &["stop"]);
    assert_eq!(second.terminate(), Some(0), "{}", second.log());
    let log = second.log();
    assert!(log.contains("resumed"), "{log}");
    assert!(!log.contains("the test's frames are recorded"), "the resumed test records no frames:\n{log}");

    assert!(!folder.join("frames-2").exists(), "no frames-2 after a stop at the reserve");
    let record = test_json(&folder);
    let stopped = &record["frames_stopped"];
    assert_eq!(stopped["folder"], "frames", "{record}");
    assert_eq!(stopped["reserve_mb"].as_f64(), Some(1e9), "{record}");
    assert!(stopped["t_ns"].as_i64().unwrap() < killed_t_ns, "the first daemon's stop: {record}");
    assert!(frame_times(&folder, "frames").is_empty(), "no frame past the reserve");
    let lines = whole_feed_lines(&folder.join("feed.jsonl"));
    assert!(lines.iter().filter(|l| l.t_ns > killed_t_ns).count() >= 10, "the lines go on after the resume");
    assert_eq!(record["lines"].as_u64(), Some(lines.len() as u64));
    let (ok, said) = report_verify(&folder);
    assert!(ok, "report verify: {said}");
}
