//! The control output read by a real Modbus client (pymodbus) while `demo` runs: the registers
//! follow the feed, a value exposed long before it arrived is never read valid, a flood of
//! frames that would panic the decoder is refused before it, a test zeroed while the beam
//! moves keeps the output valid.

use std::collections::HashMap;
use std::fs;
use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};

use crate::common::{self, ChildGuard};
use tagdeflect::config::Config;
use tagdeflect_core::feed::FeedLine;
use tagdeflect_sinks::control_output::ControlConfig;

/// Tenths of the reads that must be valid while `demo` measures. Measured 2026-12-06 at load
/// 15–17 on 2 cores, three runs: 112 of 221, 86 of 201, 127 of 176 reads valid (43–72 %; the
/// rest: the demo's own σ above `max_sigma_mm` 0.05 at times, up to 0.21 mm, and stale sets on
/// the loaded machine). Floor: 30 %.
const VALID_READS_TENTHS: usize = 3;

/// A 12-s `demo` (its rig, no page) serving `control` from a config in `dir`, its feed to
/// `stdout` and its log into `log_path`: the demo and the port its control output took.
fn demo_with_control(dir: &std::path::Path, control: ControlConfig, stdout: Stdio, log_path: &std::path::Path) -> (ChildGuard, u16) {
    let mut cfg = Config::demo();
    cfg.output.control = Some(control);
    let cfg_path = dir.join("demo.toml");
    fs::write(&cfg_path, cfg.to_toml_string()).unwrap();
    let demo = Command::new(env!("CARGO_BIN_EXE_tagdeflect"))
        .args(["demo", "--duration-s", "12", "--no-http", "--config"])
        .arg(&cfg_path)
        .env("TAGDEFLECT_LOG", "info")
        .stdout(stdout)
        .stderr(fs::File::create(log_path).unwrap())
        .spawn()
        .expect("start tagdeflect demo");
    let mut demo = ChildGuard(demo);
    let port = control_port_from_log(log_path, &mut demo);
    (demo, port)
}

#[test]
fn pymodbus_reads_the_control_registers_and_they_follow_the_feed() {
    let tmp = tempfile::tempdir().unwrap();
    // The control output takes any free port and logs the one it took.
    let addr = "127.0.0.1:0";
    let feed_path = tmp.path().join("feed.jsonl");
    let log_path = tmp.path().join("demo.log");
    // The demo rig (three 640x480 cameras: σ of its net deflection is a few µm to ~0.02 mm)
    // with a σ limit it meets, and three frame sets of slack for a loaded machine.
    let control = ControlConfig { max_sigma_mm: 0.05, stale_sets: 3, ..ControlConfig::on(addr) };
    let (mut demo, port) = demo_with_control(tmp.path(), control, fs::File::create(&feed_path).unwrap().into(), &log_path);
    let monitor = Command::new(common::python())
        .arg(common::root().join("scripts/control_monitor.py"))
        .args(["127.0.0.1", &port.to_string(), "--interval", "0.05", "--try-write"])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start the pymodbus monitor");
    let mut monitor = ChildGuard(monitor);
    // The monitor reads until the server goes away when the demo ends.
    let reads: Vec<serde_json::Value> = BufReader::new(monitor.0.stdout.take().unwrap())
        .lines()
        .map(|l| serde_json::from_str(&l.unwrap()).expect("a JSON line from the monitor"))
        .collect();
    let status = demo.0.wait().unwrap();
    let log = fs::read_to_string(&log_path).unwrap();
    assert!(status.success(), "demo failed: {log}");
    assert!(monitor.0.wait().unwrap().success());
    let feed: Vec<FeedLine> = fs::read_to_string(&feed_path).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    let by_seq: HashMap<u16, &FeedLine> = feed.iter().map(|l| ((l.seq % 65_536) as u16, l)).collect();

    assert_eq!(reads.first().and_then(|r| r.get("write_refused")), Some(&serde_json::json!(true)), "a write is refused");
    let reads = &reads[1..];
    assert!(reads.len() >= 50, "{} reads", reads.len());
    assert!(feed.len() >= 30, "{} feed lines", feed.len());
    let mut valid = 0;
    let mut seqs = std::collections::BTreeSet::new();
    let all_seqs: std::collections::BTreeSet<u64> = reads.iter().map(|r| r["seq"].as_u64().unwrap()).collect();
    let mut last_beat: Option<u64> = None;
    for r in reads {
        let beat = r["heartbeat"].as_u64().unwrap();
        if let Some(b) = last_beat {
            assert!(beat >= b || b - beat > 60_000, "the heartbeat never goes back: {b} → {beat}");
        }
        last_beat = Some(beat);
        if r["valid"] != 1 {
            continue;
        }
        valid += 1;
        let seq = r["seq"].as_u64().unwrap() as u16;
        seqs.insert(seq);
        let line = by_seq.get(&seq).unwrap_or_else(|| panic!("a register seq {seq} not in the feed"));
        let net = line.net_deflection_mm.expect("a valid value comes from a line with a net deflection");
        let sigma = line.net_deflection_sigma_mm.expect("and its σ");
        assert_eq!(r["value"].as_f64().unwrap() as f32, net as f32, "seq {seq}");
        assert_eq!(r["um"].as_i64().unwrap(), (net * 1e3).round() as i64, "seq {seq}");
        assert_eq!(r["sigma"].as_f64().unwrap() as f32, sigma as f32, "seq {seq}");
        assert!(sigma <= 0.05, "valid only with σ ≤ max_sigma_mm: {sigma}");
        if let Some(rate) = line.net_deflection_rate_mm_per_min {
            assert_eq!(r["rate_mm_per_min"].as_f64().unwrap() as f32, rate as f32, "seq {seq}");
        }
        assert!(r["age_ms"].as_u64().unwrap() < 10_000);
    }
    let beats = reads.last().unwrap()["heartbeat"].as_u64().unwrap() - reads[0]["heartbeat"].as_u64().unwrap();
    assert!(beats >= 20, "the heartbeat moved {beats} times over the run");
    let with_net = feed.iter().filter(|l| l.net_deflection_mm.is_some()).count();
    let sigmas: Vec<f64> = feed.iter().filter_map(|l| l.net_deflection_sigma_mm).collect();
    println!(
        "CONTROL {} reads, {valid} valid, {} distinct frame sets ({} valid) of {with_net} with a net deflection; σ {:.4}..{:.4} mm",
        reads.len(),
        all_seqs.len(),
        seqs.len(),
        sigmas.iter().cloned().fold(f64::INFINITY, f64::min),
        sigmas.iter().cloned().fold(0.0, f64::max)
    );
    assert!(valid * 10 >= reads.len() * VALID_READS_TENTHS, "{valid} of {} reads valid", reads.len());
    assert!(all_seqs.len() * 2 >= with_net, "the registers followed {} of {with_net} frame sets", all_seqs.len());
    // A valid value is never older than the rule allows: `stale_sets + ½` frame periods plus
    // the latency allowance since its exposure (register 8).
    let mut spacing: Vec<i64> = feed.windows(2).map(|w| w[1].t_ns - w[0].t_ns).collect();
    spacing.sort_unstable();
    let period_s = spacing[spacing.len() / 2] as f64 * 1e-9;
    let max_age_s = 3.5 * period_s + tagdeflect_sinks::signal::LATENCY_ALLOWANCE_MS * 1e-3;
    let too_old: Vec<u64> = reads
        .iter()
        .filter(|r| r["valid"] == 1)
        .map(|r| r["age_ms"].as_u64().unwrap())
        .filter(|&a| a as f64 > max_age_s * 1e3 + 1.0)
        .collect();
    assert!(too_old.is_empty(), "valid reads of values older than {max_age_s} s: {too_old:?} ms");
    // The reads after the demo stopped measuring (its last frame set older than the rule
    // allows; the server answers `STOP_HOLD` = 1 s after the end) say invalid, and the
    // heartbeat stands still.
    let last_s = feed.last().unwrap().t_ns as f64 * 1e-9;
    let after: Vec<&serde_json::Value> = reads.iter().filter(|r| r["t"].as_f64().unwrap() > last_s + max_age_s + 0.05).collect();
    println!("CONTROL after the last frame set: {} reads, {} valid", after.len(), after.iter().filter(|r| r["valid"] == 1).count());
    assert!(after.len() >= 3, "{} reads after the measurement stopped (the server answers 1 s more)", after.len());
    assert!(after.iter().all(|r| r["valid"] == 0), "valid after the measurement stopped");
    let still: std::collections::BTreeSet<u64> = after.iter().rev().take(3).map(|r| r["heartbeat"].as_u64().unwrap()).collect();
    assert_eq!(still.len(), 1, "the heartbeat stops with the measurement: {still:?}");
    assert!(log.contains("control output serving Modbus TCP"), "{log}");
}

/// The port the control output logged (`control output serving Modbus TCP … addr=IP:PORT`),
/// waiting for the line while the daemon starts.
fn control_port_from_log(log: &std::path::Path, demo: &mut ChildGuard) -> u16 {
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(60);
    loop {
        let text = fs::read_to_string(log).unwrap_or_default();
        if let Some(line) = text.lines().find(|l| l.contains("control output serving Modbus TCP")) {
            let addr = line.split_whitespace().find_map(|w| w.strip_prefix("addr=")).unwrap_or_else(|| panic!("no addr= in {line}"));
            return addr.parse::<std::net::SocketAddr>().unwrap_or_else(|e| panic!("{addr}: {e}")).port();
        }
        if let Ok(Some(status)) = demo.0.try_wait() {
            panic!("demo exited ({status}) before serving the control output:\n{text}");
        }
        assert!(std::time::Instant::now() < deadline, "the control output was not served within 60 s:\n{text}");
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
}

/// Lines that reach the control output on time but carry values exposed long before (the
/// sinks' thread held up, e.g. by a report made in-process: 1.18 s in the issue) are never
/// served as valid — the age counts from exposure. Read by pymodbus: the
/// values exposed 10 ms before they arrived are valid in most reads, those exposed 1.18 s
/// before in none.
#[test]
fn pymodbus_never_reads_valid_a_value_exposed_long_before_it_arrived() {
    use std::time::{Duration, Instant};
    use tagdeflect_sinks::control_output::ControlOutput;
    let mut control = ControlOutput::start(&ControlConfig { stale_sets: 2, ..ControlConfig::on("127.0.0.1:0") }).unwrap();
    let port = control.addr().port().to_string();
    let mut monitor = ChildGuard(
        Command::new(common::python())
            .arg(common::root().join("scripts/control_monitor.py"))
            .args(["127.0.0.1", &port, "--interval", "0.03"])
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .expect("start the pymodbus monitor"),
    );
    let mut out = BufReader::new(monitor.0.stdout.take().unwrap());
    let mut first = String::new();
    out.read_line(&mut first).expect("the monitor's first read");
    let reader = std::thread::spawn(move || out.lines().map_while(Result::ok).collect::<Vec<String>>());
    // 40 lines 50 ms apart exposed 10 ms before they arrive, then 40 exposed 1.18 s before.
    let started = Instant::now();
    for k in 0..80u64 {
        if let Some(wait) = (started + Duration::from_millis(50 * k)).checked_duration_since(Instant::now()) {
            std::thread::sleep(wait);
        }
        let late_ns = if k < 40 { 10_000_000 } else { 1_180_000_000 };
        let t_ns = tagdeflect_core::clock::now_epoch_ns() - late_ns;
        let line = FeedLine {
            seq: k,
            t_ns,
            net_deflection_mm: Some(0.01 * k as f64),
            net_deflection_sigma_mm: Some(0.001),
            ..FeedLine::default()
        };
        control.take_line(&line);
    }
    control.shutdown();
    let reads: Vec<serde_json::Value> = reader.join().unwrap().iter().map(|l| serde_json::from_str(l).unwrap()).collect();
    let _ = monitor.0.wait();
    let with_seq =
        |early: bool| reads.iter().filter(move |r| (r["seq"].as_u64().unwrap() < 40) == early && r["sigma"].as_f64().unwrap() > 0.0);
    let (early, late) = (with_seq(true).count(), with_seq(false).count());
    let early_valid = with_seq(true).filter(|r| r["valid"] == 1).count();
    let late_valid: Vec<u64> = with_seq(false).filter(|r| r["valid"] == 1).map(|r| r["age_ms"].as_u64().unwrap()).collect();
    println!(
        "LATE LINES: {early_valid} of {early} reads of fresh values valid; {} of {late} reads of 1.18 s old values valid",
        late_valid.len()
    );
    assert!(early >= 20 && late >= 20, "{early} and {late} reads");
    assert!(early_valid * 2 >= early, "fresh values valid in {early_valid} of {early} reads");
    assert!(late_valid.is_empty(), "values exposed 1.18 s before were read valid (ages {late_valid:?} ms)");
    assert!(with_seq(false).all(|r| r["age_ms"].as_u64().unwrap() >= 1180), "register 8 counts from exposure");
}

/// A malformed frame that panicked tokio-modbus 0.15's decoder (function 0x0F, quantity 65 535,
/// byte count 0), sent by 300 clients one after another over real TCP connections: each
/// gets the exception "illegal data value" and its connection is closed — the frame never
/// reaches the library's decoder, so there is no panic — the control output serves on, and
/// the log gets a line per 10 s of them with the count, not 300. A good
/// read sent before the bad frame on the same connection is answered first.
#[test]
fn a_flood_of_frames_that_panic_the_modbus_decoder_is_refused_before_the_decoder() {
    use std::io::{Read, Write};
    use std::time::Duration;
    let tmp = tempfile::tempdir().unwrap();
    let log_path = tmp.path().join("demo.log");
    let (mut demo, port) = demo_with_control(tmp.path(), ControlConfig::on("127.0.0.1:0"), Stdio::null(), &log_path);
    let addr = std::net::SocketAddr::from(([127, 0, 0, 1], port));
    let connect = || {
        let s = std::net::TcpStream::connect_timeout(&addr, Duration::from_secs(5)).expect("the control output still accepts");
        s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
        s
    };
    let read_regs: [u8; 12] = [0x00, 0x02, 0x00, 0x00, 0x00, 0x06, 0x01, 0x04, 0x00, 0x00, 0x00, 0x0C];
    let frame = [0x00, 0x01, 0x00, 0x00, 0x00, 0x07, 0x01, 0x0F, 0x00, 0x00, 0xFF, 0xFF, 0x00];
    let exception = [0x00, 0x01, 0x00, 0x00, 0x00, 0x03, 0x01, 0x8F, 0x03];
    // A good read and the bad frame in one write: the read answered, then the exception, then
    // the end of the stream.
    let mut s = connect();
    s.write_all(&[&read_regs[..], &frame].concat()).unwrap();
    let mut got = Vec::new();
    s.read_to_end(&mut got).expect("the server closes the connection");
    assert_eq!(got.len(), 9 + 24 + exception.len(), "{got:?}");
    assert_eq!((got[7], got[8]), (0x04, 24), "the read before it answered: {got:?}");
    assert_eq!(got[33..], exception, "the exception \"illegal data value\" for the bad frame");
    let mut answered = 0;
    for _ in 0..300 {
        let mut s = connect();
        s.write_all(&frame).unwrap();
        let mut got = Vec::new();
        let _ = s.read_to_end(&mut got);
        answered += (got == exception) as usize;
    }
    // A well-formed read still answered: the server is up.
    let mut s = connect();
    s.write_all(&read_regs).unwrap();
    let mut answer = [0u8; 9 + 24];
    s.read_exact(&mut answer).expect("an answer to a read of registers 0-11");
    assert_eq!((answer[7], answer[8]), (0x04, 24), "{answer:?}");
    drop(s);
    assert!(demo.0.wait().unwrap().success());
    let log = fs::read_to_string(&log_path).unwrap();
    let panics = log.lines().filter(|l| l.contains("panic")).count(); // the hook's `panic: …` line, or the default text
    let refused = log.lines().filter(|l| l.contains("control output: refused a malformed request (function 0x0F: quantity 65535")).count();
    let connected = log.lines().filter(|l| l.contains("control output: client connected")).count();
    println!(
        "MALFORMED FRAMES: 301 clients → {answered} of 300 answered with the exception, {panics} panic line(s), {refused} refusal line(s), {connected} \"client connected\" line(s)"
    );
    assert_eq!(answered, 300, "every malformed frame answered with the exception");
    assert_eq!(panics, 0, "no panic:\n{log}");
    assert!((1..=4).contains(&refused), "{refused} refusal lines for 301 malformed frames:\n{log}");
    assert!((1..=4).contains(&connected), "{connected} connection lines for 302 clients");
    assert!(log.contains("since the last such line"), "the count is logged");
}

/// A test started while the demo's beam moves: its zero is taken over moving sets, and its σ
/// (added to every later value's) is the noise's, not the motion's — the control registers
/// stay valid through the test, read by pymodbus (with the zero's σ from
/// the plain scatter, `valid` was 0 on 92 of 94 lines).
#[test]
fn a_test_zeroed_while_the_beam_moves_keeps_the_control_output_valid() {
    use crate::http::{tagdeflect_test, Daemon};
    use std::time::{Duration, Instant};
    let tmp = tempfile::tempdir().unwrap();
    let tests_dir = tmp.path().join("tests");
    let mut cfg = Config::demo();
    cfg.output.control = Some(ControlConfig { max_sigma_mm: 0.05, stale_sets: 3, ..ControlConfig::on("127.0.0.1:0") });
    let cfg_path = tmp.path().join("demo.toml");
    fs::write(&cfg_path, cfg.to_toml_string()).unwrap();
    let mut d =
        Daemon::start(&["demo", "--config", cfg_path.to_str().unwrap(), "--http", "127.0.0.1:0", "--tests", tests_dir.to_str().unwrap()]);
    let addr = d.addr();
    d.wait_stderr("control output serving Modbus TCP", Duration::from_secs(60), "the control output");
    let log = d.stderr.lock().unwrap().clone();
    let line = log.lines().find(|l| l.contains("control output serving Modbus TCP")).unwrap();
    let port = line.split_whitespace().find_map(|w| w.strip_prefix("addr=")).unwrap().parse::<std::net::SocketAddr>().unwrap().port();
    // Wait for the ramp: two lines in a row whose net deflection moved 20 µm or more.
    let deadline = Instant::now() + Duration::from_secs(90);
    loop {
        let lines = d.lines();
        let nets: Vec<f64> = lines.iter().rev().take(3).filter_map(|(_, l)| l.net_deflection_mm).collect();
        if nets.len() == 3 && (nets[0] - nets[1]).abs() >= 0.02 && (nets[1] - nets[2]).abs() >= 0.02 {
            break;
        }
        assert!(Instant::now() < deadline, "the demo's beam did not move");
        std::thread::sleep(Duration::from_millis(50));
    }
    let token_file = tests_dir.join(".token");
    let id = tagdeflect_test(addr, &token_file, &["start", "--specimen", "Z1"])["id"].as_str().unwrap().to_string();
    let monitor = Command::new(common::python())
        .arg(common::root().join("scripts/control_monitor.py"))
        .args(["127.0.0.1", &port.to_string(), "--interval", "0.05", "--reads", "60"])
        .output()
        .expect("run the pymodbus monitor");
    assert!(monitor.status.success(), "{}", String::from_utf8_lossy(&monitor.stderr));
    tagdeflect_test(addr, &token_file, &["stop"]);
    assert_eq!(d.stop(), Some(0));
    let lines: Vec<FeedLine> = d.lines().into_iter().map(|(_, l)| l).collect();
    let test_lines: Vec<&FeedLine> = lines.iter().filter(|l| l.test.as_ref().is_some_and(|t| t.id == id)).collect();
    let zero: Vec<f64> = test_lines.iter().filter(|l| l.test.as_ref().unwrap().zeroing).filter_map(|l| l.net_deflection_mm).collect();
    let moved = zero.last().zip(zero.first()).map_or(0.0, |(a, b)| (a - b).abs());
    let after: HashMap<u16, &FeedLine> =
        test_lines.iter().filter(|l| !l.test.as_ref().unwrap().zeroing).map(|l| ((l.seq % 65_536) as u16, *l)).collect();
    let reads: Vec<serde_json::Value> =
        String::from_utf8_lossy(&monitor.stdout).lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    let of_test: Vec<&serde_json::Value> = reads.iter().filter(|r| after.contains_key(&(r["seq"].as_u64().unwrap() as u16))).collect();
    let valid = of_test.iter().filter(|r| r["valid"] == 1).count();
    let sigmas: Vec<f64> = after.values().filter_map(|l| l.net_deflection_sigma_mm).collect();
    let max_sigma = sigmas.iter().cloned().fold(0.0, f64::max);
    println!(
        "ZERO WHILE MOVING: the beam moved {:.3} mm over the zero's {} sets; {valid} of {} reads of the test's lines valid; σ up to {max_sigma:.4} mm",
        moved,
        zero.len(),
        of_test.len()
    );
    assert!(moved >= 0.05, "the zero was taken while the beam moved: {moved} mm");
    assert!(of_test.len() >= 20, "{} reads of the test's lines", of_test.len());
    // Measured 41 of 60 reads valid under a load of 14 on 2 cores (the rest: the demo's own σ
    // above 0.05 mm at times, up to 0.32 mm, and stale sets); with the zero's σ from the plain
    // scatter, 2 of 94. Floor: half.
    assert!(valid * 2 >= of_test.len(), "valid in {valid} of {} reads", of_test.len());
}
