//! Preload as a step, with the simulated testing machine: a test started below its method's
//! preload waits for the load to reach it (`GET /api/test` says `preloading`) before its zero
//! is taken; its lines start there and a `preload` event says at which load; a start above
//! the method's `max_start_load_kn` is refused (409).

use tagdeflect_core::feed::FeedLine;
use tagdeflect_core::utm_sample::UtmSample;
use tagdeflect_sim::machine::SimMachine;
use tagdeflect_sim::{LoadLaw, SimParams};
use tagdeflect_sinks::lab_test::{LabTests, TestError, TestRecord, ZERO_SETS};

/// A line of the machine's state at `t_ns`, as the measurement would give it.
fn line_at(m: &SimMachine, seq: u64, t_ns: i64) -> FeedLine {
    let s = m.advance(t_ns);
    FeedLine { seq, t_ns, load_kn: Some(s.load_kn), net_deflection_mm: Some(s.deflection_mm), ..FeedLine::default() }
}

#[test]
fn a_start_below_the_preload_waits_for_it_and_one_above_the_limit_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let tests = LabTests::new(dir.path(), String::new(), Vec::new(), None).unwrap();
    let body =
        serde_json::json!({"method": "C1609-19", "specimen": "P1", "measured": {"width_mm": 150.0, "depth_mm": 150.0, "span_mm": 450.0}});
    let params = SimParams { load_law: LoadLaw::Softening, stiffness_kn_per_mm: 500.0, crack_deflection_mm: 0.07, ..SimParams::default() };
    // Lines from a minute after the start on (a manual start takes the clock's time).
    let t0 = tagdeflect_core::clock::now_epoch_ns() + 60_000_000_000;
    // A machine at rest far above the limit: a start is refused, naming the load (409).
    let loaded = SimMachine::new(&params, t0, 10.0);
    loaded.command(t0, 6.0);
    let s = loaded.advance(t0 + 30_000_000_000); // 3 mm of stroke: far past the 2 kN limit
    tests.on_utm(&UtmSample { t_ns: s.t_ns, load_kn: s.load_kn, stroke_mm: Some(s.stroke_mm) });
    let refused = tests.start_request(body.clone(), None);
    let Err(TestError::Conflict(why)) = refused else { panic!("{refused:?}") };
    assert!(why.contains("max_start_load_kn = 2 kN"), "{why}");

    // A fresh machine at rest: the start is taken, the test waits for the 0.5 kN preload.
    let t0 = t0 + 60_000_000_000;
    let m = SimMachine::new(&params, t0, 10.0);
    let s = m.advance(t0);
    tests.on_utm(&UtmSample { t_ns: s.t_ns, load_kn: s.load_kn, stroke_mm: Some(s.stroke_mm) });
    tests.start_request(body, None).unwrap();
    assert_eq!(tests.status()["preloading"]["preload_kn"], 0.5, "{}", tests.status());
    // 0.3 mm/min of stroke, a line every 0.1 s: with the frame's give (0.01 mm/kN) the load
    // rises ≈ 0.042 kN a line and reaches 0.5 kN after ≈ 1.2 s.
    m.command(t0, 0.3);
    let mut first_in_test = None;
    let mut seq = 0;
    for k in 1..=200 {
        let t = t0 + k * 100_000_000;
        let mut l = line_at(&m, seq, t);
        seq += 1;
        let load = l.load_kn.unwrap();
        tests.apply(&mut l);
        tests.on_line(&l);
        if l.test.is_some() && first_in_test.is_none() {
            first_in_test = Some(load);
        } else if l.test.is_none() {
            assert!(load < 0.5, "a line at {load} kN outside the test: only below the preload");
            assert!(!tests.status()["preloading"].is_null(), "preloading while below it");
        }
    }
    let first = first_in_test.expect("the test's lines began");
    assert!(first >= 0.5 && first < 0.6, "the test's first line at the preload: {first} kN");
    assert!(tests.status()["preloading"].is_null());
    let stopped = tests.stop().unwrap();
    let record: TestRecord = serde_json::from_str(&std::fs::read_to_string(stopped.folder.join("test.json")).unwrap()).unwrap();
    let p = record.preload.expect("the preload recorded");
    // The zero: the mean of the first sets from the preload on; the load of the set completing it.
    assert!(p.load_kn >= 0.5 && p.load_kn < 0.5 + 0.05 * ZERO_SETS as f64, "the zero at the preload: {} kN", p.load_kn);
    let ev = record.events.iter().find(|e| e.kind == "preload").expect("a preload event");
    assert_eq!(ev.note.as_deref(), Some(format!("zero taken at {:.3} kN", p.load_kn).as_str()), "{ev:?}");
    // Seated (≈ 0.042 kN a line): the zero's sets span a fraction of the preload, not warned of.
    let [lo, hi] = p.zero_loads_kn.expect("the zero's loads recorded");
    assert!(lo >= 0.5 && hi - lo < 0.25 && p.warning.is_none(), "a seated zero warned of: {p:?}");
}

/// A zero taken on a climbing load is said, through the daemon: `demo` on a softening beam the
/// simulated machine loads from rest with no seating (0.6 kN a frame set up to its 6 kN crack:
/// 6 mm over 99 sets at 10 kN/mm); a C1609-19
/// test started at rest waits for the 0.5 kN preload and takes its zero's five sets on the
/// climb, which span several kN — more than max(preload, 0.5 kN). test.json's
/// `preload.warning` says so, the report at stop lists it in its QC (report.json and the
/// page), and the daemon's log has it once, as a WARN.
#[test]
fn a_zero_taken_on_a_climbing_load_is_warned_of_in_test_json_the_report_and_the_log_once() {
    use crate::http::{post, small_rig, tagdeflect_test, Daemon};
    use std::time::{Duration, Instant};
    use tagdeflect::config::Config;

    let dir = tempfile::tempdir().unwrap();
    let params = SimParams { load_law: LoadLaw::Softening, frame_sets: 140, rest_frames: 40, crack_deflection_mm: 0.6, ..small_rig() };
    let mut cfg = Config::from_sim(&tagdeflect_sim::SimRig::new(&params).unwrap());
    cfg.utm = Config::demo().utm;
    let cfg_path = dir.path().join("rig.toml");
    std::fs::write(&cfg_path, cfg.to_toml_string()).unwrap();
    let tests_dir = dir.path().join("tests");
    let mut d =
        Daemon::start(&["demo", "--config", cfg_path.to_str().unwrap(), "--http", "127.0.0.1:0", "--tests", tests_dir.to_str().unwrap()]);
    let addr = d.addr();
    let token_file = tests_dir.join(".token");
    let deadline = Instant::now() + Duration::from_secs(180);
    // At rest (the 8 s between cycles): the start waits for the preload, then the climb.
    while d.lines().last().and_then(|(_, l)| l.load_kn).is_none_or(|p| p > 0.1) {
        assert!(Instant::now() < deadline, "the simulated machine never came to rest");
        std::thread::sleep(Duration::from_millis(100));
    }
    let token = std::fs::read_to_string(&token_file).unwrap().trim().to_string();
    let body = serde_json::json!({
        "method": "C1609-19", "specimen": "U1",
        "measured": {"width_mm": params.beam_width_mm, "depth_mm": params.beam_height_mm, "span_mm": params.span_mm},
    });
    let auth = format!("Bearer {token}");
    let (code, answer) =
        post(addr, "/api/test/start", &[("Content-Type", "application/json"), ("Authorization", &auth)], body.to_string().as_bytes());
    assert_eq!(code, 200, "{answer}");
    let id = serde_json::from_str::<serde_json::Value>(&answer).unwrap()["id"].as_str().unwrap().to_string();
    let of_test = |d: &Daemon| d.lines().iter().filter(|(_, l)| l.test.as_ref().is_some_and(|t| t.id == id)).count();
    while of_test(&d) < 15 {
        assert!(Instant::now() < deadline, "the test's lines did not come");
        std::thread::sleep(Duration::from_millis(100));
    }
    let stopped = tagdeflect_test(addr, &token_file, &["stop"]);
    assert_eq!(d.stop(), Some(0));
    let folder = std::path::PathBuf::from(stopped["folder"].as_str().unwrap());
    let record: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(folder.join("test.json")).unwrap()).unwrap();
    let preload = &record["preload"];
    let [lo, hi] = [0, 1].map(|j| preload["zero_loads_kn"][j].as_f64().unwrap_or_else(|| panic!("{preload}")));
    println!("the zero's sets from {lo} to {hi} kN; warning: {}", preload["warning"]);
    assert!(lo >= 0.5 && hi - lo > 0.5, "the zero taken on the climb: {preload}");
    let warning = preload["warning"].as_str().unwrap_or_else(|| panic!("no warning in test.json's preload: {preload}"));
    assert!(warning.contains("spanned") && warning.contains("no seating?"), "{warning}");
    let report: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(folder.join("report/report.json")).unwrap()).unwrap();
    let qc = report["qc"]["warnings"].as_array().unwrap();
    assert_eq!(qc.iter().filter(|w| w.as_str() == Some(warning)).count(), 1, "the warning once in the report's QC: {qc:?}");
    let html = std::fs::read_to_string(folder.join("report/report.html")).unwrap();
    let tail = &warning[warning.find("spanned").unwrap()..];
    assert!(html.contains(tail.split('(').next().unwrap()), "the QC line on the report's page");
    let log = d.stderr.lock().unwrap().clone();
    let warned: Vec<&str> = log.lines().filter(|l| l.contains("spanned") && l.contains("kN of load")).collect();
    assert!(warned.len() == 1 && warned[0].contains("WARN"), "one WARN in the log: {warned:?}");
}
