//! An automatic start on a played recording: the test starts at the line that started it (the
//! recording's time, not the clock's) and keeps the UTM samples seen before that line was solved;
//! its automatic stop is stamped by the line that decided it, too.

use tagdeflect_core::feed::FeedLine;
use tagdeflect_core::utm_sample::UtmSample;

use super::auto::{AutoRules, AutoTestConfig};
use super::{LabTests, TestRecord};

/// A line every second, an hour before the clock (a recording played later).
fn t(k: i64) -> i64 {
    static BASE: std::sync::OnceLock<i64> = std::sync::OnceLock::new();
    *BASE.get_or_init(|| tagdeflect_core::clock::now_epoch_ns() / 1_000_000_000 * 1_000_000_000 - 3_600_000_000_000) + k * 1_000_000_000
}

fn read_lines(p: &std::path::Path) -> Vec<serde_json::Value> {
    std::fs::read_to_string(p).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect()
}

#[test]
fn an_automatic_start_begins_at_its_line_with_the_utm_samples_seen_before_it() {
    let dir = tempfile::tempdir().unwrap();
    let tests = LabTests::new(dir.path(), String::new(), Vec::new(), None).unwrap();
    let config = AutoTestConfig {
        start_load_kn: 1.0,
        rearm_load_kn: None,
        specimen: "auto".into(),
        standard: Some("astm-c1609".into()),
        method: None,
        stop_at_end: false,
        end_margin_mm: 0.5,
        stop_below_peak_fraction: 0.0,
    };
    tests.set_auto(AutoRules { config, standard: Some("astm-c1609".into()), span_mm: Some(450.0), cmod_gauge: None, method: None });
    let t0 = t(0);
    let load = |t_ns: i64| 0.1 + 0.2 * (t_ns - t0) as f64 * 1e-9;
    // The UTM's samples (10 Hz) run 3 s ahead of the lines solved (the measurement's lag).
    let mut next_sample = t0;
    for k in 0..20 {
        while next_sample <= t(k) + 3_000_000_000 {
            tests.on_utm(&UtmSample { t_ns: next_sample, load_kn: load(next_sample), stroke_mm: None });
            next_sample += 100_000_000;
        }
        let mut l = FeedLine { seq: k as u64, t_ns: t(k), load_kn: Some(load(t(k))), net_deflection_mm: Some(0.0), ..FeedLine::default() };
        tests.apply(&mut l);
        tests.on_line(&l);
    }
    let stopped = tests.stop().unwrap();
    let record: TestRecord = serde_json::from_str(&std::fs::read_to_string(stopped.folder.join("test.json")).unwrap()).unwrap();
    // 1.1 kN at line 5: lines 5, 6, 7 confirm it, the test starts at line 7's time.
    assert_eq!(record.started_t_ns, t(7), "the start at its line's time");
    let start = record.events.iter().find(|e| e.kind == "start").unwrap();
    assert_eq!(start.t_ns, t(7), "{start:?}");
    let feed = read_lines(&stopped.folder.join("feed.jsonl"));
    assert_eq!(feed[0]["t_ns"], t(7), "the test's first line is the one that started it");
    assert_eq!(feed.len(), 13, "lines 7 to 19");
    assert_eq!(feed[0]["events"][0]["kind"], "start", "{}", feed[0]);
    let utm = read_lines(&stopped.folder.join("utm.jsonl"));
    assert_eq!(utm[0]["t_ns"], t(7), "its UTM samples from its line on, those seen before it was solved too");
    assert_eq!(utm.len() as i64, (next_sample - t(7)) / 100_000_000, "every sample from then on, once");
    let times: Vec<i64> = utm.iter().map(|s| s["t_ns"].as_i64().unwrap()).collect();
    assert!(times.windows(2).all(|w| w[1] > w[0]), "in time order");
}

/// The automatic stop of a played recording's test (the load fallen below half its peak) is
/// stamped by the line that decided it, not by the clock an hour later.
#[test]
fn an_automatic_stop_is_stamped_by_its_line() {
    let dir = tempfile::tempdir().unwrap();
    let tests = LabTests::new(dir.path(), String::new(), Vec::new(), None).unwrap();
    let config = AutoTestConfig {
        start_load_kn: 1.0,
        rearm_load_kn: None,
        specimen: "auto".into(),
        standard: None,
        method: None,
        stop_at_end: false,
        end_margin_mm: 0.5,
        stop_below_peak_fraction: 0.5,
    };
    tests.set_auto(AutoRules { config, standard: None, span_mm: Some(450.0), cmod_gauge: None, method: None });
    // Up 0.2 kN/s to 4.1 kN at line 20, then down 0.5 kN/s.
    let load = |k: i64| if k <= 20 { 0.1 + 0.2 * k as f64 } else { 4.1 - 0.5 * (k - 20) as f64 };
    let stopped_folder = || {
        std::fs::read_dir(dir.path()).unwrap().flatten().find_map(|e| {
            let text = std::fs::read_to_string(e.path().join("test.json")).ok()?;
            serde_json::from_str::<TestRecord>(&text).ok().filter(|r| r.stopped_t_ns.is_some())
        })
    };
    let mut k = 0i64;
    let found = loop {
        let mut l =
            FeedLine { seq: k as u64, t_ns: t(k), load_kn: Some(load(k).max(0.0)), net_deflection_mm: Some(0.0), ..FeedLine::default() };
        tests.apply(&mut l);
        tests.on_line(&l);
        if let Some(p) = stopped_folder().filter(|_| tests.status()["stopping"].is_null()) {
            break p;
        }
        assert!(k < 2000, "no automatic stop");
        std::thread::sleep(std::time::Duration::from_millis(if k > 20 { 20 } else { 0 }));
        k += 1;
    };
    let record = found;
    let stop = record.events.iter().find(|e| e.kind == "stop").unwrap();
    assert_eq!(record.stopped_t_ns, Some(stop.t_ns));
    // Decided at the first line below 2.05 kN (line 25) or a few after: that line's time.
    assert!(stop.t_ns >= t(25) && stop.t_ns <= t(k), "stop at {} s", (stop.t_ns - t(0)) as f64 * 1e-9);
    assert_eq!((stop.t_ns - t(0)) % 1_000_000_000, 0, "a line's own time: {stop:?}");
}
