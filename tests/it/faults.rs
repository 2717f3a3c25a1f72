//! Faults found by trying the release binary as a user would, each with the test that failed
//! before its fix (docs/operations.md, fault table).

use std::fs;
use std::process::{Command, Output};
use std::time::{Duration, Instant};

use crate::common;
use tagdeflect::feed::FeedLine;
use tagdeflect::sim::SimParams;

fn tagdeflect(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_tagdeflect")).args(args).env("TAGDEFLECT_LOG", "info").output().unwrap()
}

fn lines_of(o: &Output) -> Vec<FeedLine> {
    String::from_utf8_lossy(&o.stdout).lines().map(|l| serde_json::from_str(l).unwrap_or_else(|e| panic!("{l}: {e}"))).collect()
}

/// Runs `tagdeflect args` and waits at most `limit` for it (a hang fails the test instead of
/// the suite); returns its output.
fn tagdeflect_within(args: &[&str], limit: Duration) -> Output {
    let child = Command::new(env!("CARGO_BIN_EXE_tagdeflect"))
        .args(args)
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let pid = child.id();
    let waiter = std::thread::spawn(move || child.wait_with_output().unwrap());
    let deadline = Instant::now() + limit;
    while !waiter.is_finished() {
        if Instant::now() > deadline {
            // SAFETY: kill(2) on the pid of a child this test started and has not reaped.
            unsafe { libc::kill(pid as i32, libc::SIGKILL) };
            let _ = waiter.join();
            panic!("tagdeflect {args:?} still ran after {limit:?}");
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    waiter.join().unwrap()
}

/// A recording whose config has no `[utm]` but whose folder holds `utm.jsonl` (what
/// `simulate` writes): `replay --realtime` must carry the load on every line, the same load as
/// the plain replay (70–106 of ~120 lines came without it).
#[test]
fn a_realtime_replay_carries_the_recorded_load_on_every_line() {
    let dir = tempfile::tempdir().unwrap();
    let params = SimParams { cameras: 2, width: 320, height: 240, frame_sets: 40, fps: 10.0, ..SimParams::default() };
    let rec = common::simulate(dir.path(), "rec", &params);
    let cfg = fs::read_to_string(rec.join("tagdeflect.toml")).unwrap();
    assert!(!cfg.lines().any(|l| l.trim() == "[utm]"), "the case is a config without [utm]");
    assert!(fs::read_to_string(rec.join("utm.jsonl")).unwrap().lines().count() > 40);
    let plain = tagdeflect(&["replay", rec.to_str().unwrap()]);
    assert!(plain.status.success(), "{}", String::from_utf8_lossy(&plain.stderr));
    let plain = lines_of(&plain);
    let paced = tagdeflect_within(&["replay", "--realtime", rec.to_str().unwrap()], Duration::from_secs(120));
    assert!(paced.status.success(), "{}", String::from_utf8_lossy(&paced.stderr));
    let paced = lines_of(&paced);
    assert!(paced.len() >= 30, "{} of 40 sets", paced.len());
    let without: Vec<u64> = paced.iter().filter(|l| l.load_kn.is_none()).map(|l| l.seq).collect();
    assert!(without.is_empty(), "lines without load_kN: {without:?}");
    for l in &paced {
        let p = plain.iter().find(|p| p.t_ns == l.t_ns).expect("the same frame set in the plain replay");
        let (a, b) = (l.load_kn.unwrap(), p.load_kn.unwrap());
        assert!((a - b).abs() <= 1e-9 * b.abs().max(1.0), "set at t_ns {}: paced {a} kN, plain {b} kN", l.t_ns);
    }
}

/// A frame stamped 10^18 ns after the others: `replay --realtime` plays it next (the pause is
/// capped and logged) instead of sleeping for 31 years.
#[test]
fn a_realtime_replay_does_not_wait_for_a_frame_stamped_far_ahead() {
    let dir = tempfile::tempdir().unwrap();
    let rec = dir.path().join("rec");
    common::copy_dir(&common::root().join("replay/one-cam"), &rec);
    let frames = fs::read_to_string(rec.join("frames.jsonl")).unwrap();
    let last: serde_json::Value = serde_json::from_str(frames.lines().last().unwrap()).unwrap();
    let mut far = last.clone();
    far["seq"] = serde_json::json!(last["seq"].as_u64().unwrap() + 1);
    far["t_ns"] = serde_json::json!(last["t_ns"].as_i64().unwrap() + 1_000_000_000_000_000_000);
    fs::write(rec.join("frames.jsonl"), format!("{frames}{far}\n")).unwrap();
    let o = tagdeflect_within(&["replay", "--realtime", rec.to_str().unwrap()], Duration::from_secs(90));
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let lines = lines_of(&o);
    assert_eq!(lines.last().map(|l| l.t_ns), far["t_ns"].as_i64(), "the far frame was played");
    assert!(String::from_utf8_lossy(&o.stderr).contains("played as 5 s"), "{}", String::from_utf8_lossy(&o.stderr));
}

/// `[output] feed = "/proc/version"` opens, then fails every write: refused at start (exit 2,
/// naming it) instead of a run that exits 0 having written nothing; so is a folder. (A
/// character device such as `/dev/full` is taken: the disk-full tests write to it.)
#[test]
fn a_feed_that_takes_no_writes_is_refused_at_start() {
    let dir = tempfile::tempdir().unwrap();
    let params = SimParams { cameras: 1, width: 320, height: 240, ..SimParams::default() };
    let mut cfg = tagdeflect::config::Config::from_sim(&tagdeflect::sim::SimRig::new(&params).unwrap());
    for target in ["/proc/version", "/proc"] {
        cfg.output.feed = Some(target.to_string());
        let path = dir.path().join("rig.toml");
        fs::write(&path, cfg.to_toml_string()).unwrap();
        let o = tagdeflect_within(&["run", "--config", path.to_str().unwrap(), "--duration-s", "1"], Duration::from_secs(60));
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{target}: {err}");
        assert!(err.contains("cannot open the feed output") && err.contains(target), "{target}: {err}");
    }
}

/// A camera name is text on the live page, a folder and a topic level: markup in it is
/// refused when the config is loaded (stored XSS through a shared recording).
#[test]
fn a_camera_name_with_markup_is_refused_at_load() {
    let dir = tempfile::tempdir().unwrap();
    let params = SimParams { cameras: 1, width: 320, height: 240, ..SimParams::default() };
    let mut cfg = tagdeflect::config::Config::from_sim(&tagdeflect::sim::SimRig::new(&params).unwrap());
    cfg.cameras[0].source = tagdeflect::config::CameraSource::V4l2 { path: "/dev/video0".into() };
    for bad in ["<img src=x onerror=alert(1)>", "a\"b", "left/../x", "cam#1", ".hidden", "a b"] {
        cfg.cameras[0].name = bad.to_string();
        let path = dir.path().join("rig.toml");
        fs::write(&path, cfg.to_toml_string()).unwrap();
        let o = tagdeflect(&["check", "--config", path.to_str().unwrap()]);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{bad}: {err}");
        assert!(err.contains("camera[0].name") && err.contains("is not a camera name"), "{bad}: {err}");
    }
}

/// Under systemd (`JOURNAL_STREAM` set) every log line carries the journal's priority
/// prefix, so `journalctl -p warning` finds the warnings; a camera's pose lines name it.
#[test]
fn under_the_journal_every_log_line_has_its_priority() {
    let dir = tempfile::tempdir().unwrap();
    let rec = dir.path().join("rec");
    common::copy_dir(&common::root().join("replay/three-cam"), &rec);
    // One unreadable frame: a warning.
    fs::write(rec.join("left/000001.png"), b"not a png").unwrap();
    let o = Command::new(env!("CARGO_BIN_EXE_tagdeflect"))
        .args(["replay", rec.to_str().unwrap()])
        .env("JOURNAL_STREAM", "8:12345")
        .env("TAGDEFLECT_LOG", "info")
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let err = String::from_utf8_lossy(&o.stderr);
    let lines: Vec<&str> = err.lines().collect();
    assert!(!lines.is_empty());
    for l in &lines {
        assert!(l.starts_with("<3>") || l.starts_with("<4>") || l.starts_with("<6>") || l.starts_with("<7>"), "no priority: {l}");
    }
    assert!(lines.iter().any(|l| l.starts_with("<4>") && l.contains("frame skipped")), "{err}");
    let posed: Vec<&&str> = lines.iter().filter(|l| l.contains("camera posed from background tags")).collect();
    assert_eq!(posed.len(), 3, "{err}");
    for name in ["left", "centre", "right"] {
        assert!(posed.iter().any(|l| l.contains(&format!("camera={name}"))), "{name}: {err}");
    }
}

/// A FIFO where a file is expected (a frame of a recording, the calibration file of a
/// config) is refused with its name instead of blocking for ever.
#[test]
fn a_fifo_as_a_frame_or_calibration_file_is_refused_not_waited_on() {
    let dir = tempfile::tempdir().unwrap();
    let rec = dir.path().join("rec");
    common::copy_dir(&common::root().join("replay/one-cam"), &rec);
    let frames = fs::read_to_string(rec.join("frames.jsonl")).unwrap();
    let first: serde_json::Value = serde_json::from_str(frames.lines().next().unwrap()).unwrap();
    let frame = rec.join(first["file"].as_str().unwrap());
    fs::remove_file(&frame).unwrap();
    let status = Command::new("mkfifo").arg(&frame).status().unwrap();
    assert!(status.success());
    let o = tagdeflect_within(&["replay", rec.to_str().unwrap()], Duration::from_secs(60));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "a bad frame is skipped: {err}");
    assert!(err.contains("not a regular file") && err.contains(first["file"].as_str().unwrap()), "{err}");
    assert_eq!(lines_of(&o).len(), frames.lines().count() - 1, "every other frame set solved");

    // The calibration file of a config.
    let cal = dir.path().join("cam.yaml");
    assert!(Command::new("mkfifo").arg(&cal).status().unwrap().success());
    let cfg = fs::read_to_string(rec.join("tagdeflect.toml")).unwrap();
    let cfg: String = cfg
        .lines()
        .filter(|l| !["fx =", "fy =", "cx =", "cy =", "dist ="].iter().any(|k| l.starts_with(k)))
        .map(|l| format!("{l}\n"))
        .collect();
    let cfg = cfg.replacen("[[camera]]\n", &format!("[[camera]]\ncalibration = \"{}\"\n", cal.display()), 1);
    let cfg_path = dir.path().join("rig.toml");
    fs::write(&cfg_path, cfg).unwrap();
    let o = tagdeflect_within(&["check", "--config", cfg_path.to_str().unwrap()], Duration::from_secs(60));
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("cam.yaml") && err.contains("not a regular file"), "{err}");
}

/// `check DIR` on a recording whose frame times are not epoch times (`t_ns: 12`): exit 2,
/// naming the file and the frame.
#[test]
fn check_refuses_a_recording_whose_times_are_not_epoch_times() {
    let dir = tempfile::tempdir().unwrap();
    let rec = dir.path().join("rec");
    common::copy_dir(&common::root().join("replay/one-cam"), &rec);
    let frames = fs::read_to_string(rec.join("frames.jsonl")).unwrap();
    let mut lines: Vec<serde_json::Value> = frames.lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    lines[0]["t_ns"] = serde_json::json!(12);
    fs::write(rec.join("frames.jsonl"), lines.iter().map(|l| format!("{l}\n")).collect::<String>()).unwrap();
    let o = tagdeflect(&["check", rec.to_str().unwrap()]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("frames.jsonl") && err.contains("t_ns 12") && err.contains("Unix epoch"), "{err}");
}

/// A taken address is said once, with the address (the cause was printed twice).
#[test]
fn a_taken_address_is_said_once_with_the_address() {
    let taken = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = taken.local_addr().unwrap().to_string();
    let rec = common::root().join("replay/one-cam");
    let o = tagdeflect_within(&["replay", rec.to_str().unwrap(), "--http", &addr], Duration::from_secs(60));
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert_eq!(err.matches("Address already in use").count(), 1, "{err}");
    assert!(err.contains(&addr), "{err}");
}

/// A config with a NUL byte: a message naming the file and what is wrong, never an empty one.
#[test]
fn a_config_with_a_nul_byte_gets_a_message() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("rig.toml");
    fs::write(&path, b"[world]\nup = [0.0, 0.0, 1.0]\n\0\n").unwrap();
    let o = tagdeflect(&["check", "--config", path.to_str().unwrap()]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    let msg = err.lines().find(|l| l.contains("error:")).unwrap_or_default();
    assert!(msg.contains("rig.toml") && msg.len() > msg.find("rig.toml").unwrap() + 12, "{err}");
}
