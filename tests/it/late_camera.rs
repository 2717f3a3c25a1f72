//! A camera whose frames arrive late: a live run learns each camera's arrival delay, waits
//! for it within a bound, and says it in every feed line (docs/operations.md "A camera whose
//! frames arrive late"; the wait rule itself is unit-tested on timelines in `crates/io`'s
//! `sync::tests`).

use std::fs;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use tagdeflect_core::feed::FeedLine;

use crate::common;

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
