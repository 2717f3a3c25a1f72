//! A whole test, start to finish: bad input never panics or exhausts memory, a full disk
//! or a vanished folder is survived and reported, stale poses and dropped frames are said
//! in the feed, logs fit the journal, and every input that once crashed a fuzz target is
//! replayed (`tests/fixtures/fuzz-regressions/<target>/`).

use std::fs;
use std::io::{self, Write};
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use crate::common;
use tagdeflect_core::feed::FeedLine;
use tagdeflect_core::feed_file::{FeedWriter, SinkState};
use tagdeflect_core::linefile::LineTarget;

fn tagdeflect(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_tagdeflect")).args(args).env("TAGDEFLECT_LOG", "warn").output().expect("run tagdeflect")
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// Exit 2, one error line naming `what`, and no panic.
fn assert_clear_error(o: &Output, what: &[&str]) {
    let e = stderr(o);
    assert_eq!(o.status.code(), Some(2), "exit code; stderr: {e}");
    assert!(!e.contains("panicked"), "a panic: {e}");
    for w in what {
        assert!(e.contains(w), "error should name {w:?}: {e}");
    }
}

fn one_camera_config(dir: &Path, edit: impl Fn(String) -> String) -> PathBuf {
    let good = fs::read_to_string(common::root().join("config/one-camera.toml")).unwrap();
    let p = dir.join("rig.toml");
    fs::write(&p, edit(good)).unwrap();
    p
}

fn line_of(path: &Path, needle: &str) -> usize {
    fs::read_to_string(path).unwrap().lines().position(|l| l.trim_start().starts_with(needle)).expect(needle) + 1
}

// ---------------------------------------------------------------------------------------
// Finding 5: bad input.

#[test]
fn absurd_rates_and_durations_are_refused_naming_file_line_and_key() {
    let dir = tempfile::tempdir().unwrap();
    // Camera frame rate.
    let cfg = one_camera_config(dir.path(), |t| t.replacen("fps = 30.0", "fps = 1e-20", 1));
    let o = tagdeflect(&["check", "--config", cfg.to_str().unwrap()]);
    assert_clear_error(&o, &[&format!("rig.toml:{}", line_of(&cfg, "fps")), "camera[0].fps"]);
    // UTM polling rate and timeout.
    let cfg = one_camera_config(dir.path(), |t| t.replacen("poll_hz = 50.0", "poll_hz = 1e-20", 1));
    let o = tagdeflect(&["check", "--config", cfg.to_str().unwrap()]);
    assert_clear_error(&o, &[&format!("rig.toml:{}", line_of(&cfg, "poll_hz")), "utm.poll_hz"]);
    let cfg = one_camera_config(dir.path(), |t| t.replacen("poll_hz = 50.0", "poll_hz = 50.0\ntimeout_ms = 1e23", 1));
    let o = tagdeflect(&["run", "--config", cfg.to_str().unwrap()]);
    assert_clear_error(&o, &[&format!("rig.toml:{}", line_of(&cfg, "timeout_ms")), "utm.timeout_ms"]);
    let cfg = one_camera_config(dir.path(), |t| t.replacen("tolerance_ms = 10.0", "tolerance_ms = 1e300", 1));
    let o = tagdeflect(&["check", "--config", cfg.to_str().unwrap()]);
    assert_clear_error(&o, &[&format!("rig.toml:{}", line_of(&cfg, "tolerance_ms")), "sync.tolerance_ms"]);
    // Command-line durations (clap's own usage error, exit 2).
    for cmd in ["run", "record", "demo"] {
        let mut args = vec![cmd, "--duration-s", "1e20"];
        if cmd != "demo" {
            args.extend(["--config", cfg.to_str().unwrap()]);
        }
        if cmd == "record" {
            args.extend(["--out", "/nonexistent-out"]);
        }
        let o = tagdeflect(&args);
        assert_clear_error(&o, &["--duration-s", "1e20"]);
    }
    let o = tagdeflect(&["demo", "--duration-s", "NaN"]);
    assert_clear_error(&o, &["--duration-s"]);
}

#[test]
fn simulate_seed_beyond_toml_integers_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("sim");
    let o = tagdeflect(&["simulate", "--out", out.to_str().unwrap(), "--seed", "9223372036854775808"]);
    assert_clear_error(&o, &["--seed", "9223372036854775808"]);
    assert!(!out.exists(), "nothing written");
    // The same seed in a config's [sim] section: a toml error, not a panic.
    let cfg = one_camera_config(dir.path(), |t| format!("{t}\n[sim]\nfps = 1e-20\n"));
    let o = tagdeflect(&["check", "--config", cfg.to_str().unwrap()]);
    assert_clear_error(&o, &[&format!("rig.toml:{}", line_of(&cfg, "fps = 1e-20")), "sim.fps"]);
}

#[test]
fn camera_names_that_collide_with_recording_files_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    for name in ["frames.jsonl", "utm.jsonl", "tagdeflect.toml", "truth.jsonl", "TRUTH.JSONL", ".", "..", "a/b", "a\\\\b"] {
        let cfg = one_camera_config(dir.path(), |t| {
            let (head, rest) = t.split_once("name = \"").unwrap();
            let (_, tail) = rest.split_once('"').unwrap();
            format!("{head}name = \"{name}\"{tail}")
        });
        let o = tagdeflect(&["check", "--config", cfg.to_str().unwrap()]);
        assert_clear_error(&o, &[&format!("rig.toml:{}", line_of(&cfg, "name =")), "camera[0].name"]);
    }
}

fn small_recording(dir: &Path, format: &str) -> PathBuf {
    let out = dir.join("rec");
    let o = tagdeflect(&[
        "simulate",
        "--out",
        out.to_str().unwrap(),
        "--cameras",
        "1",
        "--width",
        "320",
        "--height",
        "240",
        "--frame-sets",
        "3",
        "--frame-format",
        format,
        "--subsamples",
        "1",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    out
}

#[test]
fn image_headers_claiming_huge_images_are_refused_before_allocating() {
    let dir = tempfile::tempdir().unwrap();
    let rec = small_recording(dir.path(), "pgm");
    let frames = fs::read_to_string(rec.join("frames.jsonl")).unwrap();
    let first: serde_json::Value = serde_json::from_str(frames.lines().next().unwrap()).unwrap();
    let file = rec.join(first["file"].as_str().unwrap());
    // 4e9 x 4e9 (1.6e19 bytes): a capacity overflow or an abort before the fix.
    fs::write(&file, b"P5 4000000000 4000000000 255\n\x00\x00\x00\x00").unwrap();
    let o = Command::new(env!("CARGO_BIN_EXE_tagdeflect"))
        .args(["replay", rec.to_str().unwrap()])
        .env("TAGDEFLECT_LOG", "warn")
        .output()
        .unwrap();
    let e = stderr(&o);
    assert!(o.status.success(), "the bad frame is skipped, the replay goes on: {e}");
    assert!(!e.contains("panicked"), "{e}");
    assert!(e.contains(first["file"].as_str().unwrap()) && e.contains("image is 4000000000x4000000000 but camera is 320x240"), "{e}");
    assert_eq!(String::from_utf8_lossy(&o.stdout).lines().count(), 2, "the other frame sets are solved");
    // A PNG whose IHDR claims 60000 x 60000 (3.6 GB) while the camera is 320x240.
    let mut png = b"\x89PNG\r\n\x1a\n\x00\x00\x00\x0dIHDR".to_vec();
    png.extend_from_slice(&60000u32.to_be_bytes());
    png.extend_from_slice(&60000u32.to_be_bytes());
    png.extend_from_slice(&[8, 0, 0, 0, 0, 0, 0, 0, 0]);
    fs::write(&file, &png).unwrap();
    let r = tagdeflect::config::Recording::open(&rec).unwrap();
    let err = r.load_image(&r.frames[0]).unwrap_err().to_string();
    assert!(err.contains("image is 60000x60000 but camera is 320x240"), "{err}");
    // A file far larger than any frame of the camera's size is not read.
    let f = fs::File::create(&file).unwrap();
    f.set_len(64 << 20).unwrap();
    let entry = r.frames.iter().find(|e| rec.join(&e.file) == file).unwrap();
    let err = r.load_image(entry).unwrap_err().to_string();
    assert!(err.contains("more than any frame of this size can be"), "{err}");
}

#[test]
fn overlong_index_lines_are_an_error_naming_file_and_line() {
    let dir = tempfile::tempdir().unwrap();
    let rec = small_recording(dir.path(), "pgm");
    let path = rec.join("frames.jsonl");
    let mut text = fs::read_to_string(&path).unwrap();
    // A 3 MB line in the middle (no newline for 3 MB: a corrupt or hostile file).
    let mut lines: Vec<String> = text.lines().map(String::from).collect();
    lines.insert(1, format!("{{\"camera\":\"{}\"}}", "x".repeat(3 << 20)));
    text = lines.join("\n") + "\n";
    fs::write(&path, text).unwrap();
    let o = tagdeflect(&["replay", rec.to_str().unwrap()]);
    assert_clear_error(&o, &["frames.jsonl:2", "longer than"]);
}

// ---------------------------------------------------------------------------------------
// Finding 6: disk full and crashes.

/// A real file whose writes fail on cue: `script[n]` says what the n-th write does.
struct FlakyFile {
    file: fs::File,
    script: Arc<Mutex<Vec<Fault>>>,
}

#[derive(Clone, Copy, Debug)]
enum Fault {
    /// Writes half the buffer, then reports success for that half (a short write).
    Half,
    /// Writes a third of the buffer, then fails with ENOSPC on the same call.
    PartThenEnospc,
    /// Fails with ENOSPC, writing nothing.
    Enospc,
    /// Works.
    Ok,
}

impl LineTarget for FlakyFile {
    fn write_once(&mut self, buf: &[u8]) -> io::Result<usize> {
        let fault = {
            let mut s = self.script.lock().unwrap();
            if s.is_empty() {
                Fault::Ok
            } else {
                s.remove(0)
            }
        };
        match fault {
            Fault::Ok => self.file.write(buf),
            Fault::Half => self.file.write(&buf[..buf.len() / 2]),
            Fault::PartThenEnospc => {
                self.file.write_all(&buf[..buf.len() / 3])?;
                Err(io::Error::from_raw_os_error(libc::ENOSPC))
            }
            Fault::Enospc => Err(io::Error::from_raw_os_error(libc::ENOSPC)),
        }
    }
    fn truncate(&mut self, len: u64) -> io::Result<()> {
        self.file.set_len(len)
    }
    fn sync_data(&mut self) -> io::Result<()> {
        self.file.sync_data()
    }
}

fn line(seq: u64) -> FeedLine {
    serde_json::from_str(&format!("{{\"seq\":{seq},\"t_ns\":{},\"tags\":[],\"net_deflection_mm\":0.5}}", 1_000 + seq)).unwrap()
}

fn assert_whole_lines(text: &str) -> Vec<u64> {
    assert!(text.is_empty() || text.ends_with('\n'), "partial last line: {text:?}");
    text.lines().map(|l| serde_json::from_str::<FeedLine>(l).unwrap_or_else(|e| panic!("corrupt line {l:?}: {e}")).seq).collect()
}

#[test]
fn feed_writer_survives_writes_that_fail_mid_line() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("feed.jsonl");
    let file = fs::OpenOptions::new().create(true).append(true).open(&path).unwrap();
    use Fault::*;
    // Two outages: lines 2..4 (a short write, then ENOSPC twice, once after part of the
    // line), and line 8 (part of the line, then ENOSPC).
    let script = Arc::new(Mutex::new(vec![Ok, Ok, Half, Enospc, PartThenEnospc, Ok, Ok, Ok, Ok, Ok, Ok, PartThenEnospc]));
    let mut w = FeedWriter::from_target("feed.jsonl", Box::new(FlakyFile { file, script: script.clone() }), 0)
        .with_backoff(Duration::from_millis(1), Duration::from_millis(4));
    let mut errors = 0;
    for seq in 0..12 {
        if w.write(&line(seq)).is_err() {
            errors += 1;
        }
        // After every call the file holds only whole lines.
        assert_whole_lines(&fs::read_to_string(&path).unwrap());
        std::thread::sleep(Duration::from_millis(5));
    }
    w.finish().unwrap();
    assert!(script.lock().unwrap().is_empty(), "every fault was injected");
    let seqs = assert_whole_lines(&fs::read_to_string(&path).unwrap());
    assert_eq!(seqs, (0..12).collect::<Vec<_>>(), "every line once, in order: held back while failing, written after");
    assert_eq!(w.state(), SinkState::Ok);
    assert_eq!(w.dropped(), 0);
    assert_eq!(errors, 2, "one error per outage, not per line");
}

#[test]
fn feed_writer_holds_lines_while_failing_and_reports_its_state() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("feed.jsonl");
    let file = fs::OpenOptions::new().create(true).append(true).open(&path).unwrap();
    let script = Arc::new(Mutex::new(vec![Fault::PartThenEnospc; 3]));
    let mut w = FeedWriter::from_target("feed.jsonl", Box::new(FlakyFile { file, script }), 0)
        .with_backoff(Duration::from_secs(3600), Duration::from_secs(3600));
    assert!(w.write(&line(0)).is_err());
    for seq in 1..5 {
        w.write(&line(seq)).unwrap();
    }
    assert_eq!((w.state(), w.pending()), (SinkState::Failing, 5), "held back during the backoff");
    assert_eq!(fs::read_to_string(&path).unwrap(), "", "the partial line was cut back");
}

#[test]
fn reopening_a_feed_repairs_a_partial_last_line() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("feed.jsonl");
    let a = line(0).to_json();
    let b = line(1).to_json();
    fs::write(&path, format!("{a}\n{}", &b[..b.len() / 2])).unwrap();
    {
        let mut w = FeedWriter::append(&path).unwrap();
        w.write(&line(2)).unwrap();
    }
    let seqs = assert_whole_lines(&fs::read_to_string(&path).unwrap());
    assert_eq!(seqs, vec![0, 2], "the fragment is gone, the new line is whole");
}

#[test]
fn dev_full_feed_is_reported_not_fatal() {
    if !Path::new("/dev/full").exists() {
        eprintln!("SKIP: no /dev/full");
        return;
    }
    let mut w = FeedWriter::append(Path::new("/dev/full")).unwrap().with_backoff(Duration::from_millis(1), Duration::from_millis(1));
    assert!(w.write(&line(0)).is_err());
    std::thread::sleep(Duration::from_millis(3));
    assert!(w.write(&line(1)).is_ok(), "still failing: no second error");
    assert_eq!(w.state(), SinkState::Failing);
}

#[test]
fn recorder_retries_after_its_folder_vanishes_and_counts_what_it_dropped() {
    use tagdeflect::config::Recording;
    use tagdeflect_core::frame::{Frame, GrayImage};
    use tagdeflect_io::recording::RecordingWriter;
    use tagdeflect_sinks::recorder::Recorder;
    let dir = tempfile::tempdir().unwrap();
    let cfg = tagdeflect::config::Config::load(&common::root().join("config/one-camera.toml")).unwrap();
    let out = dir.path().join("rec");
    let writer = RecordingWriter::create(&out, &cfg).unwrap();
    let name = cfg.cameras[0].name.clone();
    let rec = Recorder::start_with(writer, vec![name.clone()], 64, Duration::from_millis(20));
    let tx = rec.sender();
    let status = rec.status();
    let (w, h) = (cfg.cameras[0].width, cfg.cameras[0].height);
    let img = Arc::new(GrayImage::new(w.min(64), h.min(48)));
    let send = |seq: u64| tx.frame(Frame { camera: 0, seq, t_ns: 1_000_000 * seq as i64, image: img.clone() });
    let wait_until = |what: &str, f: &dyn Fn() -> bool| {
        for _ in 0..500 {
            if f() {
                return;
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        panic!("timed out waiting for {what}");
    };
    for seq in 0..3 {
        send(seq);
    }
    wait_until("3 frames", &|| status.written_frames() == 3);
    assert_eq!(status.state(), SinkState::Ok);
    // The camera's folder disappears (a USB disk unplugged, an operator's rm).
    let cam_dir = out.join(&name);
    let moved = dir.path().join("moved");
    fs::rename(&cam_dir, &moved).unwrap();
    for seq in 3..8 {
        send(seq);
        std::thread::sleep(Duration::from_millis(5));
    }
    wait_until("failing", &|| status.state() == SinkState::Failing);
    wait_until("drops counted", &|| status.dropped_frames() >= 5);
    // It comes back (remounted): the recorder picks up again on its own.
    fs::rename(&moved, &cam_dir).unwrap();
    for seq in 8..40 {
        send(seq);
        std::thread::sleep(Duration::from_millis(10));
        if status.state() == SinkState::Ok && status.written_frames() > 3 {
            break;
        }
    }
    wait_until("ok again", &|| status.state() == SinkState::Ok && status.written_frames() > 3);
    drop(tx);
    rec.finish();
    assert_eq!(status.state(), SinkState::Off);
    // What was recorded is a sound recording: every indexed image exists, no temporary file.
    let r = Recording::open(&out).unwrap();
    assert_eq!(r.frames.len() as u64, status.written_frames());
    for f in &r.frames {
        assert!(out.join(&f.file).is_file(), "{} indexed but missing", f.file);
    }
    let leftovers: Vec<_> =
        fs::read_dir(&cam_dir).unwrap().flatten().filter(|e| e.file_name().to_string_lossy().ends_with(".part")).collect();
    assert!(leftovers.is_empty(), "{leftovers:?}");
}

// ---------------------------------------------------------------------------------------
// Findings 6, 7, 8 through the real binary: a short live run that records.

#[test]
fn live_run_reports_recorder_drops_and_stale_state_and_logs_plain_text() {
    let dir = tempfile::tempdir().unwrap();
    let cfg_path = dir.path().join("demo.toml");
    fs::write(&cfg_path, tagdeflect::config::Config::demo().to_toml_string()).unwrap();
    let rec = dir.path().join("rec");
    let err_path = dir.path().join("stderr.log");
    // Stopped by SIGTERM once 15 frame sets are out, however slow the machine.
    let mut child = Command::new(env!("CARGO_BIN_EXE_tagdeflect"))
        .args(["run", "--config", cfg_path.to_str().unwrap(), "--record", rec.to_str().unwrap()])
        .env("TAGDEFLECT_LOG", "info")
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(fs::File::create(&err_path).unwrap())
        .spawn()
        .unwrap();
    let stdout = child.stdout.take().unwrap();
    let feed = Arc::new(Mutex::new(String::new()));
    let reader = {
        let feed = feed.clone();
        std::thread::spawn(move || {
            use std::io::BufRead;
            for l in io::BufReader::new(stdout).lines().map_while(Result::ok) {
                let mut f = feed.lock().unwrap();
                f.push_str(&l);
                f.push('\n');
            }
        })
    };
    let deadline = std::time::Instant::now() + Duration::from_secs(120);
    while feed.lock().unwrap().lines().count() < 15 {
        assert!(std::time::Instant::now() < deadline, "fewer than 15 feed lines within 120 s:\n{}", fs::read_to_string(&err_path).unwrap());
        std::thread::sleep(Duration::from_millis(100));
    }
    // SAFETY: kill(2) on the pid of a child this test started and still owns.
    unsafe { libc::kill(child.id() as i32, libc::SIGTERM) };
    let status = child.wait().unwrap();
    reader.join().unwrap();
    let o = Output { status, stdout: feed.lock().unwrap().clone().into_bytes(), stderr: Vec::new() };
    let log = fs::read_to_string(&err_path).unwrap();
    assert!(o.status.success(), "{log}");
    // Finding 8: no colour codes in a file; few INFO lines, none per frame.
    assert!(!log.contains("\x1b["), "ANSI escape codes in a log file:\n{log}");
    let info: Vec<&str> = log.lines().filter(|l| l.contains(" INFO ")).collect();
    // The bound is on messages per run, not per second: it means something only when the run
    // had many frame sets (a slow machine makes fewer; then the check says so, not passes).
    let sets = String::from_utf8_lossy(&o.stdout).lines().count();
    println!("INFO lines in a run of {sets} frame sets: {}\n{log}", info.len());
    assert!(sets >= 15, "only {sets} frame sets in the run: too few to tell per-run from per-frame messages");
    // Start, stop and once-per-camera events only: no message more often than once per camera.
    let mut counts = std::collections::HashMap::new();
    for l in &info {
        let msg = l.split(" INFO ").nth(1).unwrap_or("");
        let key: String = msg.split(|c: char| c == '=' || c.is_ascii_digit()).next().unwrap_or("").to_string();
        *counts.entry(key).or_insert(0) += 1;
    }
    assert!(counts.values().all(|&n| n <= 3), "an INFO message repeats: {counts:?}\n{log}");
    assert!(info.len() <= 20, "{} INFO lines in a run of {sets} frame sets:\n{log}", info.len());
    assert!(!log.lines().any(|l| l.contains(" INFO ") && l.contains("rejected as an outlier")), "{log}");
    // Findings 6 and 7: every line says the recorder's state and the cameras' drops.
    let lines: Vec<FeedLine> = String::from_utf8_lossy(&o.stdout).lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert!(lines.len() >= 15, "{} lines", lines.len());
    for l in &lines {
        assert_eq!(l.recording.as_deref(), Some("ok"), "seq {}", l.seq);
        assert!(l.recorder_dropped.is_some());
        assert_eq!(l.cameras.len(), 3);
        assert!(l.cameras.iter().all(|c| c.dropped_frames.is_some()), "seq {}", l.seq);
    }
    let r = tagdeflect::config::Recording::open(&rec).unwrap();
    assert!(!r.frames.is_empty() && !r.utm.is_empty(), "frames and UTM samples recorded");
}

#[test]
fn record_mode_keeps_utm_samples_and_exits_cleanly() {
    let dir = tempfile::tempdir().unwrap();
    let cfg_path = dir.path().join("demo.toml");
    let mut cfg = tagdeflect::config::Config::demo();
    cfg.cameras.truncate(1);
    fs::write(&cfg_path, cfg.to_toml_string()).unwrap();
    let out = dir.path().join("rec");
    let o = tagdeflect(&["record", "--config", cfg_path.to_str().unwrap(), "--out", out.to_str().unwrap(), "--duration-s", "2"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let r = tagdeflect::config::Recording::open(&out).unwrap();
    // The samples at the UTM's rate (50 Hz), whatever the machine's load did to the run's
    // length: their median spacing, not a count in a wall-clock window.
    assert!(r.utm.len() >= 10, "{} UTM samples", r.utm.len());
    let mut dt: Vec<i64> = r.utm.windows(2).map(|w| w[1].t_ns - w[0].t_ns).collect();
    dt.sort_unstable();
    let median_ms = dt[dt.len() / 2] as f64 / 1e6;
    assert!((15.0..=30.0).contains(&median_ms), "UTM samples {median_ms} ms apart (50 Hz: 20 ms)");
}

// ---------------------------------------------------------------------------------------
// Finding 7: a camera that sees no background tag holds its pose and says so.

#[test]
fn a_camera_without_background_tags_reports_a_stale_pose() {
    use tagdeflect_core::frame::{FrameSet, GrayImage};
    use tagdeflect_estimate::measure::Measurement;
    let rec = tagdeflect::config::Recording::open(&common::root().join("replay/three-cam")).unwrap();
    let mut m = Measurement::new(&rec.config.measurement(), true).unwrap();
    let mut asm = tagdeflect_io::sync::FrameSetAssembler::new(rec.config.cameras.len(), rec.config.sync.tolerance_ms);
    let mut sets: Vec<FrameSet> = Vec::new();
    for (i, e) in rec.frames.iter().enumerate() {
        let img = rec.load_image(e).unwrap();
        let f = tagdeflect_core::frame::Frame {
            camera: rec.config.camera_index(&e.camera).unwrap(),
            seq: i as u64,
            t_ns: e.t_ns,
            image: Arc::new(img),
        };
        sets.extend(asm.push(f));
    }
    sets.extend(asm.flush());
    assert!(sets.len() >= 6);
    let (w, h) = (rec.config.cameras[0].width, rec.config.cameras[0].height);
    let mut ages = Vec::new();
    for (k, set) in sets.iter_mut().enumerate() {
        if (3..6).contains(&k) {
            // Camera 0 looks at a grey wall: no background tag, no specimen tag.
            for f in set.frames.iter_mut().filter(|f| f.camera == 0) {
                f.image = Arc::new(GrayImage { width: w, height: h, data: vec![128; (w * h) as usize], deep: None });
            }
        }
        let (line, _) = m.process(set);
        let c = &line.cameras[0];
        if k < 3 {
            assert!(c.posed && !c.stale_pose, "set {k}: {c:?}");
        }
        if (3..6).contains(&k) {
            assert!(c.posed && c.stale_pose, "set {k}: the held pose is reported stale: {c:?}");
            ages.push(c.pose_age_sets);
            assert!(!line.cameras[1].stale_pose, "the other cameras are fine");
        }
        let json = line.to_json();
        assert_eq!(json.contains("\"stale_pose\":true"), c.stale_pose || line.cameras.iter().any(|c| c.stale_pose));
    }
    assert_eq!(ages, vec![Some(1), Some(2), Some(3)]);
}

/// The fault table's promise for a camera without background tags, read from the journal
/// of a real run: one WARN when its pose turns stale, one INFO when it is confirmed again.
#[test]
fn a_stale_pose_is_logged_once_when_it_starts_and_once_when_it_ends() {
    let dir = tempfile::tempdir().unwrap();
    let rec = dir.path().join("three-cam");
    common::copy_dir(&common::root().join("replay/three-cam"), &rec);
    // The left camera looks at a grey wall for its frames 3..6.
    let first = image::open(rec.join("left/000000.png")).unwrap().to_luma8();
    let grey = image::GrayImage::from_pixel(first.width(), first.height(), image::Luma([128]));
    for k in 3..6 {
        grey.save(rec.join(format!("left/{k:06}.png"))).unwrap();
    }
    let o = Command::new(env!("CARGO_BIN_EXE_tagdeflect"))
        .args(["replay", rec.to_str().unwrap()])
        .env("TAGDEFLECT_LOG", "info")
        .output()
        .expect("run tagdeflect");
    let log = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{log}");
    let lines: Vec<FeedLine> = String::from_utf8_lossy(&o.stdout).lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    let stale: Vec<u64> = lines.iter().filter(|l| l.cameras[0].stale_pose).map(|l| l.seq).collect();
    assert_eq!(stale.len(), 3, "three stale sets: {stale:?}");
    let warn: Vec<&str> = log.lines().filter(|l| l.contains("no background tag confirms this camera's pose")).collect();
    let info: Vec<&str> = log.lines().filter(|l| l.contains("camera pose confirmed by background tags again")).collect();
    assert_eq!(warn.len(), 1, "one WARN when the pose turns stale:\n{log}");
    assert_eq!(info.len(), 1, "one INFO when it is confirmed again:\n{log}");
    assert!(warn[0].contains("WARN") && warn[0].contains("left") && warn[0].contains(&format!("seq={}", stale[0])), "{}", warn[0]);
    assert!(info[0].contains("INFO") && info[0].contains("left") && info[0].contains(&format!("seq={}", stale[2] + 1)), "{}", info[0]);
}

#[test]
fn late_frames_are_counted_per_camera() {
    use tagdeflect_core::frame::{Frame, GrayImage};
    let img = Arc::new(GrayImage::new(1, 1));
    let f = |camera: usize, t: i64| Frame { camera, seq: 0, t_ns: t, image: img.clone() };
    let mut a = tagdeflect_io::sync::FrameSetAssembler::new(2, 1.0);
    a.push(f(0, 0));
    a.push(f(1, 0));
    a.push(f(0, 10_000_000));
    a.push(f(1, -5_000_000)); // camera 1, older than a closed set: late
    assert_eq!(a.late_by_camera(), &[0, 1]);
    let drops = tagdeflect::graph::journal::FrameDrops::new(2);
    drops.add_source(0, 4);
    drops.set_late(a.late_by_camera());
    let mut line = line(0);
    line.cameras = ["a", "b"]
        .iter()
        .map(|n| {
            serde_json::from_str(&format!("{{\"name\":\"{n}\",\"frame\":true,\"background_tags\":1,\"specimen_tags\":1,\"posed\":true}}"))
                .unwrap()
        })
        .collect();
    drops.apply(&mut line);
    assert_eq!(line.cameras.iter().map(|c| c.dropped_frames).collect::<Vec<_>>(), vec![Some(4), Some(1)]);
}

#[test]
fn journal_summary_counts_per_camera_and_logs_stale_changes_once() {
    use tagdeflect::graph::journal::JournalSummary;
    let mut j = JournalSummary::new(vec!["left".into()], Duration::from_secs(3600));
    let mut l = line(0);
    l.cameras = vec![serde_json::from_str("{\"name\":\"left\",\"frame\":true,\"background_tags\":0,\"specimen_tags\":3,\"posed\":true,\"stale_pose\":true,\"dropped_frames\":2}").unwrap()];
    for _ in 0..5 {
        assert!(j.observe(&l, &[1]).is_none(), "no summary before the interval");
    }
    let mut j2 = JournalSummary::new(vec!["left".into()], Duration::ZERO);
    let s = j2.observe(&l, &[7]).expect("summary due");
    assert!(s.contains("left: 1 frames, 2 dropped, 1 stale-pose sets") && s.contains("7 outlier views"), "{s}");
}

// ---------------------------------------------------------------------------------------
// Finding 10: every input that once crashed a fuzz target stays fixed.

#[test]
fn fuzz_regressions_replay_without_a_crash() {
    let root = common::root().join("tests/fixtures/fuzz-regressions");
    let mut n = 0;
    // Every folder names a target (a misspelt folder would otherwise be skipped in silence).
    for dir in fs::read_dir(&root).unwrap().flatten() {
        let target = dir.file_name().to_string_lossy().into_owned();
        assert!(tagdeflect::fuzzing::TARGETS.contains(&target.as_str()), "{}: not a fuzz target", dir.path().display());
        for e in fs::read_dir(dir.path()).unwrap().flatten() {
            let data = fs::read(e.path()).unwrap();
            println!("{target}: {}", e.path().display());
            assert!(tagdeflect::fuzzing::run(&target, &data), "{target} is not known to the harness");
            n += 1;
        }
    }
    println!("{n} fuzz regression inputs replayed");
    // The regressions kept in the repository: 21 assembly inputs, 1 Modbus peer input.
    assert!(n >= 22, "only {n} regression inputs found under {}", root.display());
    // The targets themselves run on a few fixed inputs too (a smoke test of the harness);
    // an unknown name is refused rather than passed.
    for target in tagdeflect::fuzzing::TARGETS {
        for data in [&b""[..], b"P5 1 1 255\n\x00", b"{\"camera\":\"a\",\"seq\":1,\"t_ns\":-9223372036854775808,\"file\":\"x\"}\n"] {
            assert!(tagdeflect::fuzzing::run(target, data), "{target} is not known to the harness");
        }
    }
    assert!(!tagdeflect::fuzzing::run("no-such-target", b""));
}

/// A mutation fuzzer over the same entry points as `fuzz/` (for machines where the
/// cargo-fuzz build is too heavy): valid seeds, mutated at random (bit flips, byte edits,
/// insertions, truncations, splices, interesting integers), each input run under
/// `catch_unwind`; a panicking input is saved to `tests/fixtures/fuzz-regressions/<target>/`.
/// `TAGDEFLECT_FUZZ_SECS` seconds per target (default 10). Run with
/// `cargo test --test it robustness::mutation_fuzz -- --ignored --nocapture`.
#[test]
#[ignore = "a timed fuzzer (TAGDEFLECT_FUZZ_SECS per target): run with --ignored --nocapture; its saved regressions run every time"]
fn mutation_fuzz() {
    use rand::{Rng, SeedableRng};
    let secs: f64 = std::env::var("TAGDEFLECT_FUZZ_SECS").ok().and_then(|s| s.parse().ok()).unwrap_or(10.0);
    let root = common::root();
    let cfg_text = fs::read(root.join("config/one-camera.toml")).unwrap();
    let mut pgm = b"P5\n16 12\n255\n".to_vec();
    pgm.extend((0..192).map(|i| (i * 7) as u8));
    let png = tagdeflect_io::recording::encode_png(&tagdeflect_core::frame::GrayImage {
        width: 16,
        height: 12,
        data: pgm[13..].to_vec(),
        deep: None,
    })
    .unwrap();
    let frames = fs::read(root.join("replay/three-cam/frames.jsonl")).unwrap()[..600].to_vec();
    let utm = fs::read(root.join("replay/three-cam/utm.jsonl")).unwrap()[..600].to_vec();
    let yaml = b"%YAML:1.0\ncamera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ 1000., 0., 320., 0., 1000., 240., 0., 0., 1. ]\ndistortion_coefficients: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n   data: [ 0.1, -0.2, 0., 0., 0. ]\nimage_width: 640\nimage_height: 480\n".to_vec();
    let json = br#"{"camera_matrix": [[1000, 0, 320], [0, 1000, 240], [0, 0, 1]], "distortion_coefficients": [0.1, 0, 0, 0, 0], "image_width": 640}"#.to_vec();
    let mut jpeg = Vec::new();
    image::GrayImage::from_fn(16, 8, |x, y| image::Luma([(x * 16 + y) as u8]))
        .write_to(&mut std::io::Cursor::new(&mut jpeg), image::ImageFormat::Jpeg)
        .unwrap();
    let mut conv = vec![3u8, 0, 16, 0, 8, 0, 0, 0];
    conv.extend(&jpeg);
    // A feed of the bundled recording (report_feed), and one of its lines as the archive
    // receives it on each kind of topic (archive_message: the first byte picks the topic).
    let feed = {
        let (_, lines, _) = common::replay_lines(&root.join("replay/one-cam"), false);
        lines.iter().take(6).map(|l| l.to_json() + "\n").collect::<String>().into_bytes()
    };
    let first_line = feed.split(|b| *b == b'\n').next().unwrap().to_vec();
    let ack = br#"{"runs":[{"run":1,"high":40,"gaps":[[3,5]]}]}"#.to_vec();
    let lab_record = br#"{"rig":"r","test":"t","id":"20261202T101500Z-B12","specimen":"B12","operator":"A","started_t_ns":1700000000000000000,"events":[{"kind":"start","t_ns":1700000000000000000}],"lines":3,"utm_samples":30,"sha256":{}}"#.to_vec();
    let seeds: Vec<(&str, Vec<Vec<u8>>)> = vec![
        ("report_feed", vec![feed.clone()]),
        (
            "archive_message",
            vec![
                [vec![0u8], first_line.clone()].concat(),
                [vec![1u8], b"{\"state\":\"online\"}".to_vec()].concat(),
                [vec![2u8], ack].concat(),
                [vec![3u8], lab_record].concat(),
            ],
        ),
        ("image", vec![pgm.clone(), png.clone()]),
        ("jsonl", vec![frames, utm]),
        ("config", vec![cfg_text]),
        ("calibration", vec![yaml, json]),
        (
            "convert",
            vec![
                conv,
                [vec![0u8, 0, 16, 0, 8, 0, 16, 0], vec![9; 128]].concat(),
                [vec![1u8, 4, 8, 0, 8, 0, 0, 0], vec![200; 128]].concat(),
            ],
        ),
        (
            "modbus",
            vec![vec![0, 0, 0, 0, 0, 0, 0, 0, 0, 0xf0, 0x3f, 0, 0, 0, 0, 0, 0, 0, 0, 0x41, 0x48], vec![3, 1, 1, 0xff, 0xff, 0xff, 0x7f]],
        ),
        (
            "modbus_peer",
            // Two well-formed replies (transaction ids 0 and 1) to the poller's one read of
            // four input registers, then a reply cut short.
            vec![[
                &[17u8, 0, 0, 0, 0, 0, 11, 1, 4, 8, 0x41, 0x20, 0, 0, 0, 0, 0, 5][..],
                &[17u8, 0, 1, 0, 0, 0, 11, 1, 4, 8, 0x41, 0x28, 0, 0, 0, 0, 0, 6][..],
                &[9u8, 0, 2, 0, 0, 0, 11, 1, 4, 8][..],
            ]
            .concat()],
        ),
        ("assembly", vec![(0..200u8).collect(), vec![2, 1, 0, 0, 0, 0, 0, 0, 0, 0x80, 0, 255, 255, 255, 255, 255, 255, 255, 127, 1]]),
        ("roi", vec![(0..200u8).map(|b| b.wrapping_mul(37)).collect()]),
        ("window_detect", vec![png.iter().chain(pgm.iter()).copied().collect()]),
    ];
    let interesting: [u64; 8] = [0, 1, 0x7f, 0xff, 0xffff, 0x7fff_ffff, 0xffff_ffff, u64::MAX];
    let mut rng =
        rand_chacha::ChaCha8Rng::seed_from_u64(std::env::var("TAGDEFLECT_FUZZ_SEED").ok().and_then(|s| s.parse().ok()).unwrap_or(1));
    std::panic::set_hook(Box::new(|_| {}));
    let mut crashes = Vec::new();
    // TAGDEFLECT_FUZZ_TARGETS=a,b: only those targets (default: all).
    let only: Option<Vec<String>> = std::env::var("TAGDEFLECT_FUZZ_TARGETS").ok().map(|v| v.split(',').map(str::to_string).collect());
    for (target, seeds) in &seeds {
        if only.as_ref().is_some_and(|o| !o.iter().any(|t| t == target)) {
            continue;
        }
        let start = std::time::Instant::now();
        let mut execs = 0u64;
        let mut corpus = seeds.clone();
        while start.elapsed().as_secs_f64() < secs {
            let mut d = corpus[rng.gen_range(0..corpus.len())].clone();
            for _ in 0..rng.gen_range(1..6) {
                let n = d.len();
                match rng.gen_range(0..7) {
                    0 if n > 0 => {
                        let i = rng.gen_range(0..n);
                        d[i] ^= 1 << rng.gen_range(0..8);
                    }
                    1 if n > 0 => {
                        let i = rng.gen_range(0..n);
                        d[i] = rng.gen();
                    }
                    2 => {
                        let i = rng.gen_range(0..=n);
                        let k = rng.gen_range(1..16);
                        let b: u8 = rng.gen();
                        d.splice(i..i, std::iter::repeat_n(b, k));
                    }
                    3 if n > 1 => d.truncate(rng.gen_range(0..n)),
                    4 if n > 0 => {
                        let i = rng.gen_range(0..n);
                        let v = interesting[rng.gen_range(0..interesting.len())].to_le_bytes();
                        let k = rng.gen_range(1..=8).min(n - i);
                        d[i..i + k].copy_from_slice(&v[..k]);
                    }
                    5 if n > 0 => {
                        // ASCII digits: numbers in text formats.
                        let i = rng.gen_range(0..n);
                        let s = ["9999999999", "-1", "1e308", "nan", "0", "4294967296", "-9223372036854775809"][rng.gen_range(0..7)];
                        d.splice(i..i, s.bytes());
                    }
                    _ => {
                        let other = &corpus[rng.gen_range(0..corpus.len())];
                        if !other.is_empty() {
                            let a = rng.gen_range(0..other.len());
                            let i = rng.gen_range(0..=d.len());
                            d.splice(i..i, other[a..].iter().copied().take(64));
                        }
                    }
                }
            }
            let input = d.clone();
            let ok = std::panic::catch_unwind(|| tagdeflect::fuzzing::run(target, &input)).is_ok();
            execs += 1;
            if !ok {
                let dir = root.join("tests/fixtures/fuzz-regressions").join(target);
                fs::create_dir_all(&dir).unwrap();
                let name =
                    format!("crash-{:016x}", input.iter().fold(0xcbf29ce484222325u64, |h, b| (h ^ *b as u64).wrapping_mul(0x100000001b3)));
                fs::write(dir.join(&name), &input).unwrap();
                crashes.push(format!("{target}/{name}"));
                if crashes.len() > 20 {
                    break;
                }
            } else if corpus.len() < 256 && rng.gen_ratio(1, 50) {
                corpus.push(d);
            }
        }
        println!(
            "FUZZ {target}: {execs} inputs in {:.0} s ({:.0}/s)",
            start.elapsed().as_secs_f64(),
            execs as f64 / start.elapsed().as_secs_f64()
        );
    }
    let _ = std::panic::take_hook();
    assert!(crashes.is_empty(), "crashing inputs saved: {crashes:?}");
}
