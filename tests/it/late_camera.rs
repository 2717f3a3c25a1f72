//! A camera whose frames arrive late: a live run learns each camera's arrival delay, waits
//! for it within a bound, and says it in every feed line, on `/metrics` and in the live page's
//! status (docs/operations.md "A camera whose frames arrive late"; the wait rule itself is
//! unit-tested on timelines in `crates/io`'s `sync::tests`).

use std::fs;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use tagdeflect_core::feed::FeedLine;

use crate::common;
use crate::http::{get, Daemon as PageDaemon};

/// The daemon as a child process, its output into files; killed on drop if still running.
struct Daemon(Child);

impl Daemon {
    fn start(args: &[&str], dir: &std::path::Path) -> Daemon {
        let child = Command::new(env!("CARGO_BIN_EXE_tagdeflect"))
            .args(args)
            .env("TAGDEFLECT_LOG", "info")
            .stdout(fs::File::create(dir.join("stdout")).unwrap())
            .stderr(fs::File::create(dir.join("stderr")).unwrap())
            .stdin(Stdio::null())
            .spawn()
            .expect("start tagdeflect");
        Daemon(child)
    }

    /// SIGTERM, then the exit code (within 20 s).
    fn terminate(mut self) -> Option<i32> {
        // SAFETY: kill(2) on the pid of a child this test started and still owns.
        unsafe { libc::kill(self.0.id() as i32, libc::SIGTERM) };
        let deadline = Instant::now() + Duration::from_secs(20);
        loop {
            if let Some(status) = self.0.try_wait().unwrap() {
                return status.code();
            }
            assert!(Instant::now() < deadline, "tagdeflect did not stop within 20 s of SIGTERM");
            std::thread::sleep(Duration::from_millis(50));
        }
    }
}

impl Drop for Daemon {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

#[test]
fn a_live_feed_carries_each_cameras_learned_arrival_delay() {
    // The demo's simulated cameras stamp a frame with its exposure and hand it over once it is
    // rendered: every frame arrives after its time, so each camera's learned delay is
    // positive, and shorter than the run.
    let dir = tempfile::tempdir().unwrap();
    let (cfg, feed) = common::demo_config_with_feed(dir.path());
    let started = Instant::now();
    let d = Daemon::start(&["demo", "--config", cfg.to_str().unwrap(), "--no-http"], dir.path());
    let deadline = started + Duration::from_secs(180);
    while fs::read_to_string(&feed).map_or(0, |t| t.lines().count()) < 30 {
        assert!(Instant::now() < deadline, "fewer than 30 feed lines within 180 s");
        std::thread::sleep(Duration::from_millis(100));
    }
    let code = d.terminate();
    let run_ms = started.elapsed().as_secs_f64() * 1e3;
    let log = fs::read_to_string(dir.path().join("stderr")).unwrap();
    assert_eq!(code, Some(0), "{log}");
    let text = fs::read_to_string(&feed).unwrap();
    common::feedcheck_text(&text, &cfg);
    let lines: Vec<FeedLine> = text.lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    // Learned after 8 frames of a camera; the last 10 lines come well after that.
    for l in &lines[lines.len() - 10..] {
        for c in &l.cameras {
            let delay_ms = c.arrival_delay_ms.unwrap_or_else(|| panic!("seq {}: no arrival_delay_ms for {}", l.seq, c.name));
            assert!(delay_ms > 0.0 && delay_ms < run_ms, "seq {}: {} arrival_delay_ms {delay_ms} (run {run_ms:.0} ms)", l.seq, c.name);
        }
    }
    let whole = lines.iter().filter(|l| l.cameras.iter().all(|c| c.frame)).count();
    let last = &lines[lines.len() - 1];
    let delays: Vec<_> = last.cameras.iter().map(|c| (c.name.as_str(), c.arrival_delay_ms, c.dropped_frames)).collect();
    println!("{} lines, {whole} whole; last line's (camera, arrival_delay_ms, dropped_frames): {delays:?}", lines.len());
}

/// Each camera's `tagdeflect_camera_arrival_delay_seconds{camera=…}` series in `/metrics`.
fn arrival_delays_s(metrics: &str) -> Vec<(String, f64)> {
    metrics
        .lines()
        .filter_map(|l| l.strip_prefix("tagdeflect_camera_arrival_delay_seconds{camera=\""))
        .map(|rest| {
            let (name, value) = rest.split_once("\"} ").unwrap_or_else(|| panic!("a malformed series: {rest}"));
            (name.to_string(), value.trim().parse().unwrap_or_else(|e| panic!("{rest}: {e}")))
        })
        .collect()
}

/// `/metrics` and the live page's status show what the feed says of each camera's learned
/// arrival delay: over HTTP on a live demo, every camera has its gauge in seconds and its
/// `sources[].arrival_delay_ms`, each the delay of one of that camera's feed lines.
#[test]
fn metrics_and_the_status_show_each_cameras_learned_arrival_delay() {
    let mut d = PageDaemon::start(&["demo", "--http", "127.0.0.1:0"]);
    let addr = d.addr();
    // Learned after 8 frames of a camera: 30 lines is well after that.
    d.wait_lines(30, Duration::from_secs(180));
    let (code, _, metrics) = get(addr, "/metrics");
    assert_eq!(code, 200);
    let metrics = String::from_utf8(metrics).unwrap();
    let (code, _, status) = get(addr, "/api/status");
    assert_eq!(code, 200);
    let status: serde_json::Value = serde_json::from_slice(&status).unwrap();
    // The lines published before these answers reach the stdout reader a little later.
    d.wait_lines(d.lines().len() + 3, Duration::from_secs(60));
    let lines = d.lines();
    assert_eq!(d.stop(), Some(0), "{}", d.stderr.lock().unwrap());
    let names: Vec<String> = lines[lines.len() - 1].1.cameras.iter().map(|c| c.name.clone()).collect();
    let fed = |name: &str| -> Vec<f64> {
        lines.iter().flat_map(|(_, l)| l.cameras.iter()).filter(|c| c.name == name).filter_map(|c| c.arrival_delay_ms).collect()
    };
    let in_feed = |name: &str, ms: f64| fed(name).iter().any(|f| (f - ms).abs() <= 1e-6 * f.abs().max(1.0));
    let gauges = arrival_delays_s(&metrics);
    println!("/metrics: {gauges:?}");
    for name in &names {
        let s = gauges.iter().find(|(n, _)| n == name).map(|g| g.1).unwrap_or_else(|| panic!("no arrival delay of {name} in:\n{metrics}"));
        assert!(s > 0.0, "{name}: {s} s");
        assert!(in_feed(name, s * 1e3), "{name}: {s} s in /metrics, none of its feed lines says so: {:?}", fed(name));
        let src = status["sources"].as_array().unwrap().iter().find(|c| c["name"] == name.as_str()).expect("the camera in the status");
        let ms = src["arrival_delay_ms"].as_f64().unwrap_or_else(|| panic!("{name}: no arrival_delay_ms in the status: {src}"));
        assert!(in_feed(name, ms), "{name}: {ms} ms in the status, none of its feed lines says so: {:?}", fed(name));
    }
    assert_eq!(gauges.len(), names.len(), "one series per camera: {gauges:?}");
}
