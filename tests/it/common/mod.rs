//! Helpers shared by the integration tests: simulate a recording, replay it, compare with
//! truth, check a feed with the SPEC checker; the simulated rig's config for a live run and a
//! test's folder kept when it fails ([`rig`]).
#![allow(dead_code)]

use std::fs;
use std::io::Read;
use std::net::TcpListener as StdListener;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use tagdeflect::accuracy::{evaluate, Accuracy};
use tagdeflect::config::Recording;
use tagdeflect::graph::in_process::{self as replay, ReplayOptions, ReplaySummary};
use tagdeflect_core::feed::FeedLine;
use tagdeflect_sim::SimParams;

mod rig;
pub use rig::{beam_rig_config, sim_beam, sim_rig_config, KeptOnFailure};

/// The demo's own config written into `dir` (`demo.toml`) with its feed into a file there
/// (`feed.jsonl`): the paths of both.
pub fn demo_config_with_feed(dir: &Path) -> (PathBuf, PathBuf) {
    let mut config = tagdeflect::config::Config::demo();
    let feed = dir.join("feed.jsonl");
    config.output.feed = Some(feed.display().to_string());
    let cfg = dir.join("demo.toml");
    fs::write(&cfg, config.to_toml_string()).unwrap();
    (cfg, feed)
}

/// The project's root folder.
pub fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// `../shared` beside the project (the SPEC checker and the real data); fails loudly if absent.
pub fn shared() -> PathBuf {
    let p = root().join("../shared");
    assert!(p.join("tools/feedcheck.py").is_file(), "../shared (SPEC tools and real data) is missing at {}", p.display());
    p
}

/// Simulates `params` into a new folder under `dir`.
pub fn simulate(dir: &Path, name: &str, params: &SimParams) -> PathBuf {
    let out = dir.join(name);
    tagdeflect::commands::simulate::simulate(params, &out).unwrap_or_else(|e| panic!("simulate {name}: {e}"));
    out
}

/// Replays a recording and returns its feed lines and summary.
pub fn replay_lines(dir: &Path, full_frame: bool) -> (Recording, Vec<FeedLine>, ReplaySummary) {
    let rec = Recording::open(dir).unwrap_or_else(|e| panic!("{e}"));
    let mut lines = Vec::new();
    let summary =
        replay::replay(&rec, ReplayOptions { full_frame, progress: false, ..Default::default() }, |l, _, _| lines.push(l.clone())).unwrap();
    (rec, lines, summary)
}

/// Replays and evaluates against the recording's truth; prints the figures.
pub fn accuracy_of(label: &str, dir: &Path, full_frame: bool) -> (Accuracy, Vec<FeedLine>, Recording) {
    let (rec, lines, _) = replay_lines(dir, full_frame);
    let acc = evaluate(&rec.config, &rec.truth, &lines);
    println!("ACCURACY {label}{}: {acc}", if full_frame { " (full-frame)" } else { "" });
    (acc, lines, rec)
}

/// Runs the SPEC feed checker on feed lines; panics with its report on any problem.
pub fn feedcheck(lines: &[FeedLine], config_toml: &Path) {
    let mut text = String::new();
    for l in lines {
        text.push_str(&l.to_json());
        text.push('\n');
    }
    feedcheck_text(&text, config_toml);
}

/// Runs the SPEC feed checker on feed text.
pub fn feedcheck_text(text: &str, config_toml: &Path) {
    use std::io::Write;
    let checker = shared().join("tools/feedcheck.py");
    let mut child = Command::new("python3")
        .arg(&checker)
        .arg("-")
        .arg("--roles")
        .arg(config_toml)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("python3 is needed to run ../shared/tools/feedcheck.py (run scripts/setup.sh)");
    child.stdin.take().unwrap().write_all(text.as_bytes()).unwrap();
    let out = child.wait_with_output().unwrap();
    let report = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "feedcheck found problems:\n{report}{}", String::from_utf8_lossy(&out.stderr));
    assert!(report.contains(" 0 problems"), "{report}");
}

// ----------------------------------------------------------------------------------------
// Python and the pymodbus server (a real Modbus peer that is not our code).

/// The Python with pymodbus: $TAGDEFLECT_PYTHON, else target/test-venv, else python3.
pub fn python() -> PathBuf {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let candidates: Vec<PathBuf> = std::env::var_os("TAGDEFLECT_PYTHON")
        .map(PathBuf::from)
        .into_iter()
        .chain([root.join("target/test-venv/bin/python"), PathBuf::from("python3")])
        .collect();
    for p in &candidates {
        let ok =
            Command::new(p).args(["-c", "import pymodbus"]).stdout(Stdio::null()).stderr(Stdio::null()).status().is_ok_and(|s| s.success());
        if ok {
            return p.clone();
        }
    }
    panic!("no python3 with pymodbus found (tried {candidates:?}): run scripts/setup.sh (it makes target/test-venv with pymodbus)");
}

pub fn fixture() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/modbus_server.py")
}

/// A loopback port nothing listened on a moment ago: only for an address that must have
/// no server behind it (a dead broker, a UTM that is not there). A server of a test takes
/// port 0 and says which port it got, or is checked to listen itself ([`start_pymodbus`]).
pub fn unused_port() -> u16 {
    StdListener::bind("127.0.0.1:0").and_then(|l| l.local_addr()).map(|a| a.port()).expect("no free loopback port")
}

/// A child process killed (and reaped) on drop.
pub struct ChildGuard(pub Child);

impl Drop for ChildGuard {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// The pymodbus server of tests/fixtures/modbus_server.py on a free loopback port, listening
/// when this returns: the server and its port. A port taken by another program between
/// the choice and the server's bind is noticed (the listening socket must be the server's
/// own) and another one is tried.
pub fn start_pymodbus() -> (ChildGuard, u16) {
    for _ in 0..5 {
        let port = unused_port();
        if let Some(server) = try_start_pymodbus(port) {
            return (server, port);
        }
    }
    panic!("the pymodbus server did not listen on any of 5 free ports");
}

/// The pymodbus server on 127.0.0.1:`port` (a server restarted on the port it had); panics
/// when it does not listen there itself within 30 s.
pub fn start_pymodbus_on(port: u16) -> ChildGuard {
    try_start_pymodbus(port).unwrap_or_else(|| panic!("the pymodbus server did not listen on 127.0.0.1:{port}"))
}

fn try_start_pymodbus(port: u16) -> Option<ChildGuard> {
    let child = Command::new(python())
        .arg(fixture())
        .arg(port.to_string())
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("cannot start python");
    let mut guard = ChildGuard(child);
    listens_within_30_s(&mut guard, port, "the pymodbus server").then_some(guard)
}

/// Waits up to 30 s until `server` (a fixture started with its stderr piped) listens on
/// 127.0.0.1:`port` itself: true; false, with what happened printed (`what` names the
/// server), when it exited first or did not listen in time.
pub fn listens_within_30_s(server: &mut ChildGuard, port: u16, what: &str) -> bool {
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        if tagdeflect_archive::local::process_listens_on(server.0.id(), port) {
            return true;
        }
        if let Ok(Some(status)) = server.0.try_wait() {
            let mut err = String::new();
            if let Some(mut e) = server.0.stderr.take() {
                let _ = e.read_to_string(&mut err);
            }
            eprintln!("{what} exited ({status}) before listening on 127.0.0.1:{port}: {err}");
            return false;
        }
        if Instant::now() > deadline {
            eprintln!("{what} did not listen on 127.0.0.1:{port} within 30 s");
            return false;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// Copies the folder `from` (a recording) to `to`, recursively.
pub fn copy_dir(from: &Path, to: &Path) {
    fs::create_dir_all(to).unwrap();
    for e in fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        let dest = to.join(e.file_name());
        if e.file_type().unwrap().is_dir() {
            copy_dir(&e.path(), &dest);
        } else {
            fs::copy(e.path(), dest).unwrap();
        }
    }
}

/// `config/one-camera.toml` without its `[specimen.beam]` table (for tests that give their own).
pub fn one_camera_without_beam() -> String {
    let text = std::fs::read_to_string(root().join("config/one-camera.toml")).unwrap();
    let mut out = String::new();
    let mut skipping = false;
    for line in text.lines() {
        if line.starts_with('[') {
            skipping = line.trim() == "[specimen.beam]";
        }
        if !skipping {
            out.push_str(line);
            out.push('\n');
        }
    }
    out
}

/// A simulated test's curve as `report` builds it, for the report's Monte Carlo tests: the
/// deflection (CMOD) `x_at(t)` read at 10 Hz by a gauge of σ `sx_mm` with a zero reference
/// off by its σ (0.001 mm), the load `law(x)` read by a UTM at 100 Hz (noise 0.03 kN,
/// resolution 0.01 kN) whose clock is 20 ms ahead and known to 4 ms, the feed's curve put on
/// the UTM's samples over `dur_s` seconds.
pub fn simulated_utm_curve(
    rng: &mut rand_chacha::ChaCha8Rng,
    law: &dyn Fn(f64) -> f64,
    x_at: &dyn Fn(f64) -> f64,
    dur_s: f64,
    sx_mm: f64,
    x_name: &'static str,
) -> tagdeflect_report::Curve {
    use rand::Rng;
    use rand_distr::{Distribution, Normal};
    const T0: i64 = 1_767_225_600_000_000_000;
    let (ref_sigma, load_noise, res) = (0.001, 0.03, 0.01);
    let (offset_s, offset_sigma_s) = (0.020, 0.004);
    let nx = Normal::new(0.0, sx_mm).unwrap();
    let np = Normal::new(0.0, load_noise).unwrap();
    let ref_err = Normal::new(0.0, ref_sigma).unwrap().sample(rng);
    // The alignment's error: the UTM stamps are off by what the clock check did not catch.
    let t_err = Normal::new(0.0, offset_sigma_s).unwrap().sample(rng);
    let phase: f64 = rng.gen_range(0.0..0.01);
    let n = (dur_s / 0.1) as usize;
    let t_ns: Vec<i64> = (0..n).map(|k| T0 + k as i64 * 100_000_000).collect();
    let x: Vec<f64> = (0..n).map(|k| x_at(k as f64 * 0.1) + ref_err + nx.sample(rng)).collect();
    let p_frames: Vec<f64> = (0..n).map(|k| law(x_at(k as f64 * 0.1))).collect();
    let feed = tagdeflect_report::Curve::new(t_ns, p_frames, x, vec![Some(sx_mm); n], ref_sigma, 5, res, x_name).unwrap();
    let utm: Vec<tagdeflect_io::utm::UtmSample> = (0..(dur_s * 100.0) as usize)
        .map(|j| {
            let t_true = j as f64 * 0.01 + phase;
            let p = ((law(x_at(t_true)) + np.sample(rng)) / res).round() * res;
            // Stamped on the UTM clock (offset ahead), taken at t_true.
            let stamp = t_true + offset_s + t_err;
            tagdeflect_io::utm::UtmSample { t_ns: T0 + (stamp * 1e9).round() as i64, load_kn: p, stroke_mm: None }
        })
        .collect();
    feed.on_utm(&utm, (offset_s * 1e9).round() as i64, offset_sigma_s, res, 2.0).unwrap()
}
