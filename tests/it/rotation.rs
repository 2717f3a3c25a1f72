//! The run's feed file rotated under a running daemon
//! (`[output.feed_rotation]`): no line split, lost or repeated across the files, the report and
//! `report verify` over the rotated set, and a full disk during rotations keeps what was written.

use std::fs;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use tagdeflect_core::feed_rotation::{feed_files, FeedRotation};
use tagdeflect_sim::SimParams;

use crate::faults::LoggedDaemon;

/// A demo rig of two small simulated cameras at 5 fps with the simulated UTM and a beam, its
/// feed into `feed` rotated past `max_mb`; the daemon's arguments.
fn rig(dir: &Path, feed: &Path, max_mb: f64) -> Vec<String> {
    rig_rotated(dir, feed, FeedRotation { max_mb, ..FeedRotation::default() })
}

/// [`rig`] with the rotation given.
fn rig_rotated(dir: &Path, feed: &Path, rotation: FeedRotation) -> Vec<String> {
    let params =
        SimParams { cameras: 2, width: 480, height: 360, fps: 5.0, frame_sets: 60, rest_frames: 5, subsamples: 4, ..SimParams::default() };
    let mut cfg = crate::common::beam_rig_config(&params);
    cfg.output.feed = Some(feed.display().to_string());
    cfg.output.feed_rotation = rotation;
    let rig = dir.join("rig.toml");
    fs::write(&rig, cfg.to_toml_string()).unwrap();
    ["demo", "--config", rig.to_str().unwrap(), "--http", "127.0.0.1:0"].iter().map(|s| s.to_string()).collect()
}

/// `(seq, t_ns)` of each whole line of `files` read one after the other; each file must end
/// with a whole line (the current one may hold a line being written: left out).
fn lines_of(files: &[PathBuf]) -> Vec<(u64, i64)> {
    let mut out = Vec::new();
    for (i, f) in files.iter().enumerate() {
        let text = fs::read_to_string(f).unwrap();
        let last = i + 1 == files.len();
        assert!(last || text.is_empty() || text.ends_with('\n'), "{}: a rotated file ends with a whole line", f.display());
        let whole = &text[..text.rfind('\n').map_or(0, |k| k + 1)];
        for l in whole.lines() {
            let v: serde_json::Value = serde_json::from_str(l).unwrap_or_else(|e| panic!("{}: {e}: {l}", f.display()));
            out.push((v["seq"].as_u64().unwrap(), v["t_ns"].as_i64().unwrap()));
        }
    }
    out
}

/// The daemon with its stdout (the feed, every line) into `stdout`; `prefix` runs before it
/// (e.g. `unshare`), its last argument the shell script that ends in `exec "$@"`.
fn spawn(prefix: &[&str], stdout: &Path, args: &[String]) -> LoggedDaemon {
    let mut cmd = Command::new(prefix[0]);
    cmd.args(&prefix[1..]).arg(stdout).arg(env!("CARGO_BIN_EXE_tagdeflect")).args(args);
    LoggedDaemon::spawn(cmd)
}

/// A daemon whose feed rotates every ~20 kB: at least three rotated files, named in order, each
/// within the limit and ending with a whole line; the lines across the files are those of the
/// feed on stdout, each once, in order (no gap, no repeat); `report` on the current file reads
/// the whole set (its rotated files listed and hashed as inputs) and `report verify` passes.
/// Without the rotation the feed is one file that is never cut.
#[test]
fn the_feed_rotates_under_a_running_daemon_losing_no_line() {
    let dir = tempfile::tempdir().unwrap();
    let feed = dir.path().join("feeds").join("feed.jsonl");
    let stdout = dir.path().join("stdout.jsonl");
    let args = rig(dir.path(), &feed, 0.02);
    let deadline = Instant::now() + Duration::from_secs(300);
    let mut d = spawn(&["sh", "-c", r#"out="$0"; exec "$@" >"$out""#], &stdout, &args);
    d.wait_for("three rotated feed files", deadline, |_| feed_files(&feed).map_or(0, |f| f.len()) >= 4);
    assert_eq!(d.terminate(), Some(0), "{}", d.log());
    let files = feed_files(&feed).unwrap();
    for (i, f) in files.iter().enumerate() {
        let name = f.file_name().unwrap().to_str().unwrap();
        if i + 1 < files.len() {
            assert!(name.starts_with(&format!("feed.{:06}.", i + 1)) && name.ends_with("Z.jsonl"), "{name}");
            assert!(fs::metadata(f).unwrap().len() <= 20_000, "{name}: within the size limit");
        }
    }
    assert_eq!(files.last().unwrap(), &feed, "the current file keeps its name");
    let in_files = lines_of(&files);
    let on_stdout = lines_of(&[stdout]);
    assert!(in_files.len() >= 10, "{} lines", in_files.len());
    assert_eq!(in_files, on_stdout, "every line once, in order, across the rotated files");
    assert!(d.log().matches("feed file rotated").count() >= 3, "{}", d.log());

    let out = dir.path().join("report");
    let rig_toml = dir.path().join("rig.toml");
    let o = Command::new(env!("CARGO_BIN_EXE_tagdeflect"))
        .args(["report", feed.to_str().unwrap(), "--config", rig_toml.to_str().unwrap(), "--standard", "astm-c1609", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(o.status.success(), "report: {}", String::from_utf8_lossy(&o.stderr));
    let report: serde_json::Value = serde_json::from_str(&fs::read_to_string(out.join("report.json")).unwrap()).unwrap();
    let inputs = report["inputs"]["files"].as_array().unwrap();
    let feeds = inputs.iter().filter(|f| f["role"] == "feed").count();
    assert_eq!(feeds, files.len(), "every file of the rotated feed is an input: {inputs:?}");
    let csv = fs::read_to_string(out.join("curve.csv")).unwrap();
    assert_eq!(csv.lines().count() - 1, in_files.len(), "the report read every line of the set");
    let v = Command::new(env!("CARGO_BIN_EXE_tagdeflect")).args(["report", "verify"]).arg(&out).output().unwrap();
    assert!(v.status.success(), "report verify: {}{}", String::from_utf8_lossy(&v.stdout), String::from_utf8_lossy(&v.stderr));
}

/// Fills the filesystem of `dir` (a file `dir/filler`, written until ENOSPC).
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

/// The feed on a 1 MiB tmpfs of the daemon's own (`unshare -rm`), rotated at every line (a
/// 2 kB limit): the disk filled while the daemon rotates, the lines are held back (one error),
/// no rotated file is cut or lost, and once space is free the held-back lines follow in order:
/// the files hold every line of stdout up to their last one, each once. Read while the daemon
/// is stopped (SIGSTOP), since its tmpfs goes with it.
#[test]
fn a_full_disk_during_rotations_keeps_every_line() {
    let dir = tempfile::tempdir().unwrap();
    let feeds = dir.path().join("feeds");
    fs::create_dir_all(&feeds).unwrap();
    let feed = feeds.join("feed.jsonl");
    let stdout = dir.path().join("stdout.jsonl");
    let args = rig(dir.path(), &feed, 0.002);
    let script = format!(r#"out="$0"; mount -t tmpfs -o size=1m tmpfs "{}" && exec "$@" >"$out""#, feeds.display());
    let deadline = Instant::now() + Duration::from_secs(300);
    let mut d = spawn(&["unshare", "-rm", "sh", "-c", &script], &stdout, &args);
    let view = PathBuf::from(format!("/proc/{}/root{}", d.child.0.id(), feeds.display()));
    let vfeed = view.join("feed.jsonl");
    d.wait_for("three rotated files", deadline, |_| feed_files(&vfeed).map_or(0, |f| f.len()) >= 4);
    let filler = fill(&view);
    d.wait_for("the feed to fail", deadline, |d| d.log().contains("lines are held back"));
    let rotations_full = d.log().matches("feed file rotated").count();
    let held_from = lines_of(&[stdout.clone()]).len();
    d.wait_for("ten lines on stdout while the disk is full", deadline, |_| lines_of(&[stdout.clone()]).len() >= held_from + 10);
    fs::remove_file(&filler).unwrap();
    d.wait_for("the feed to write again", deadline, |d| d.log().contains("feed output writes again"));
    d.wait_for("three rotations after", deadline, |d| d.log().matches("feed file rotated").count() >= rotations_full + 3);
    // SAFETY: kill(2) on the pid of a child this test started and has not reaped.
    unsafe { libc::kill(d.child.0.id() as i32, libc::SIGSTOP) };
    let files = feed_files(&vfeed).unwrap();
    let in_files = lines_of(&files);
    unsafe { libc::kill(d.child.0.id() as i32, libc::SIGCONT) };
    assert_eq!(d.terminate(), Some(0), "{}", d.log());
    let on_stdout = lines_of(&[stdout]);
    assert!(in_files.len() > held_from + 10, "the held-back lines are written: {} after {held_from}", in_files.len());
    assert_eq!(in_files[..], on_stdout[..in_files.len()], "every line once, in order, across the outage and the rotations");
    let log = d.log();
    assert_eq!(log.matches("lines are held back").count(), 1, "one error per outage:\n{log}");
}

/// Bytes of a file (0 when it is not there).
fn len_of(p: &Path) -> u64 {
    fs::metadata(p).map_or(0, |m| m.len())
}

/// `tagdeflect report FEED --config RIG --standard astm-c1609 --out OUT` (must succeed).
fn report(feed: &Path, rig_toml: &Path, out: &Path) {
    let o = Command::new(env!("CARGO_BIN_EXE_tagdeflect"))
        .arg("report")
        .arg(feed)
        .arg("--config")
        .arg(rig_toml)
        .args(["--standard", "astm-c1609", "--out"])
        .arg(out)
        .output()
        .unwrap();
    assert!(o.status.success(), "report: {}", String::from_utf8_lossy(&o.stderr));
}

/// `tagdeflect report verify DIR`: (success, stdout + stderr).
fn verify(dir: &Path) -> (bool, String) {
    let v = Command::new(env!("CARGO_BIN_EXE_tagdeflect")).args(["report", "verify"]).arg(dir).output().unwrap();
    (v.status.success(), format!("{}{}", String::from_utf8_lossy(&v.stdout), String::from_utf8_lossy(&v.stderr)))
}

/// A report made from a running daemon's feed (docs/report.md, "A report made while its feed
/// is still written"): report.json records the feed's length when hashed; once the daemon
/// wrote more, `report verify` passes saying the feed grew (both lengths), also after the
/// daemon stopped; a byte changed inside the part the report hashed is named (exit 1).
/// Without the recorded length the grown feed was "CHANGED".
#[test]
fn a_report_of_a_feed_still_written_verifies_its_part_and_names_an_edit_inside_it() {
    let dir = tempfile::tempdir().unwrap();
    let feed = dir.path().join("feeds").join("feed.jsonl");
    let stdout = dir.path().join("stdout.jsonl");
    let args = rig_rotated(dir.path(), &feed, FeedRotation { max_mb: 0.0, daily: false, ..FeedRotation::default() });
    let deadline = Instant::now() + Duration::from_secs(300);
    let mut d = spawn(&["sh", "-c", r#"out="$0"; exec "$@" >"$out""#], &stdout, &args);
    d.wait_for("30 lines in the feed", deadline, |_| fs::read_to_string(&feed).map_or(0, |t| t.lines().count()) >= 30);
    let out = dir.path().join("report");
    report(&feed, &dir.path().join("rig.toml"), &out);
    let report: serde_json::Value = serde_json::from_str(&fs::read_to_string(out.join("report.json")).unwrap()).unwrap();
    let input = report["inputs"]["files"].as_array().unwrap().iter().find(|f| f["role"] == "feed").unwrap().clone();
    let hashed = input["bytes"].as_u64().expect("the feed's length when hashed");
    assert!(hashed > 0, "{input}");
    d.wait_for("the feed to grow past what was hashed", deadline, |_| len_of(&feed) > hashed + 1000);
    let (ok, text) = verify(&out);
    assert!(ok, "a feed grown since its report verifies: {text}");
    assert!(text.contains("grown") && text.contains(&format!("{hashed} B hashed")), "says it grew: {text}");
    assert_eq!(d.terminate(), Some(0), "{}", d.log());
    let (ok, text) = verify(&out);
    assert!(ok && text.contains("written to since"), "after the stop too: {text}");

    // A digit of the first line's t_ns changed: inside the hashed part, named.
    let mut bytes = fs::read(&feed).unwrap();
    let at = bytes.windows(7).position(|w| w == b"\"t_ns\":").unwrap() + 8;
    assert!(bytes[at].is_ascii_digit() && (at as u64) < hashed);
    bytes[at] = if bytes[at] == b'9' { b'0' } else { bytes[at] + 1 };
    fs::write(&feed, &bytes).unwrap();
    let (ok, text) = verify(&out);
    assert!(!ok, "an edit inside the hashed part is caught: {text}");
    assert!(
        text.contains("CHANGED") && text.contains(&format!("feed {} changed", dir.path().join("feeds/feed.jsonl").display())),
        "{text}"
    );
}

/// The daily cut under a running daemon (`TAGDEFLECT_FEED_CLOCK_START`: the rotation's clock
/// starts at 23:59:00 UTC and runs at the real rate, so the day changes a minute after the
/// feed is opened): one cut, the rotated file named `feed.000001.2030-01-02T00-00-…Z.jsonl`
/// (the cut's time, after midnight), the lines across the two files those of stdout once each
/// in order, and `report` over the set verifies.
#[test]
fn the_daily_cut_under_a_running_daemon_cuts_once_losing_no_line() {
    let dir = tempfile::tempdir().unwrap();
    let feed = dir.path().join("feeds").join("feed.jsonl");
    let stdout = dir.path().join("stdout.jsonl");
    let args = rig_rotated(dir.path(), &feed, FeedRotation { max_mb: 0.0, daily: true, ..FeedRotation::default() });
    let deadline = Instant::now() + Duration::from_secs(400);
    let mut cmd = Command::new("sh");
    cmd.args(["-c", r#"out="$0"; exec "$@" >"$out""#]).arg(&stdout).arg(env!("CARGO_BIN_EXE_tagdeflect")).args(&args);
    cmd.env("TAGDEFLECT_FEED_CLOCK_START", "2030-01-01T23:59:00Z");
    let mut d = LoggedDaemon::spawn(cmd);
    d.wait_for("the daily cut", deadline, |d| d.log().contains("feed file rotated"));
    let rotated = feed_files(&feed).unwrap()[0].clone();
    d.wait_for("ten lines after the cut", deadline, |_| fs::read_to_string(&feed).map_or(0, |t| t.lines().count()) >= 10);
    assert_eq!(d.terminate(), Some(0), "{}", d.log());
    let files = feed_files(&feed).unwrap();
    assert_eq!(files, [rotated.clone(), feed.clone()], "one cut: {files:?}\n{}", d.log());
    let name = rotated.file_name().unwrap().to_str().unwrap();
    assert!(name.starts_with("feed.000001.2030-01-02T00-0") && name.ends_with("Z.jsonl"), "{name}");
    assert_eq!(d.log().matches("feed file rotated").count(), 1, "{}", d.log());
    let (before, after) = (lines_of(&files[..1]), lines_of(&files[1..]));
    assert!(!before.is_empty() && after.len() >= 10, "{} lines before the cut, {} after", before.len(), after.len());
    let in_files = lines_of(&files);
    assert_eq!(in_files, lines_of(&[stdout]), "every line once, in order, across the cut");
    let out = dir.path().join("report");
    report(&feed, &dir.path().join("rig.toml"), &out);
    let (ok, text) = verify(&out);
    assert!(ok, "report verify over the set: {text}");
    assert_eq!(text.matches("same     feed").count(), 2, "both files are inputs: {text}");
}

/// A cut whose rename fails (the feed's folder read-only to a daemon without
/// CAP_DAC_OVERRIDE, `setpriv`): the daemon says so once, the lines go on into the current file
/// (past its limit), the rename is tried again at each next cut by size (quietly), and once the
/// folder is writable the file is rotated ("after N failed tries") and the cuts go on; the lines
/// across the files are those of stdout once each, in order.
#[test]
fn a_cut_whose_rename_fails_keeps_writing_says_so_once_and_rotates_later() {
    use std::os::unix::fs::PermissionsExt;
    let dir = tempfile::tempdir().unwrap();
    let feeds = dir.path().join("feeds");
    fs::create_dir_all(&feeds).unwrap();
    let feed = feeds.join("feed.jsonl");
    let stdout = dir.path().join("stdout.jsonl");
    let args = rig(dir.path(), &feed, 0.01);
    let deadline = Instant::now() + Duration::from_secs(400);
    let script = r#"out="$0"; exec "$@" >"$out""#;
    let prefix = ["setpriv", "--bounding-set=-dac_override,-dac_read_search,-fowner", "sh", "-c", script];
    let mut d = spawn(&prefix, &stdout, &args);
    d.wait_for("a first rotation", deadline, |d| d.log().contains("feed file rotated"));
    fs::set_permissions(&feeds, fs::Permissions::from_mode(0o555)).unwrap();
    d.wait_for("a rename to fail", deadline, |d| d.log().contains("feed file not rotated"));
    d.wait_for("the current file past three limits", deadline, |_| len_of(&feed) > 30_000);
    let rotated_while_read_only = d.log().matches("feed file rotated").count();
    fs::set_permissions(&feeds, fs::Permissions::from_mode(0o755)).unwrap();
    d.wait_for("the rotation after", deadline, |d| d.log().contains("feed file rotated after"));
    d.wait_for("a rotation more", deadline, |d| d.log().matches("feed file rotated").count() >= rotated_while_read_only + 2);
    assert_eq!(d.terminate(), Some(0), "{}", d.log());
    let log = d.log();
    assert_eq!(log.matches("feed file not rotated").count(), 1, "said once:\n{log}");
    let tries: u32 = log.split("feed file rotated after ").nth(1).unwrap().split(' ').next().unwrap().parse().unwrap();
    assert!(tries >= 2, "tried again at the next cuts ({tries} failed tries):\n{log}");
    let files = feed_files(&feed).unwrap();
    assert!(files.iter().any(|f| len_of(f) > 30_000), "the lines went on into the current file: {files:?}");
    assert_eq!(lines_of(&files), lines_of(&[stdout]), "every line once, in order");
}
