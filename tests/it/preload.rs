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
