//! `demo --c1609`: the demo is a test — a cracking, softening beam loaded at ASTM C1609's
//! rates in simulated time, played faster than recorded, started and stopped automatically;
//! its report at stop is valid and its strengths are the simulated law's.
//!
//! It is played on a machine made too slow for its pace (`TAGDEFLECT_THROTTLE_MS`: the UTM
//! samples reach the solver later than the frames, and the solver lags the frames): the
//! replay plays slower instead of dropping, and every line, its load, the automatic start and
//! the zero are the recording's — what the same demo gives on a quiet machine.

use std::path::Path;
use std::process::Command;

use tagdeflect::commands::optional::sim::{DemoTest, RATE_AFTER_L900_MM_PER_MIN, RATE_TO_L900_MM_PER_MIN};
use tagdeflect_sim::load_at;

fn read_json(p: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))).unwrap()
}

#[test]
fn the_demo_c1609_test_on_a_machine_too_slow_for_its_pace_gives_a_valid_report_with_the_law_s_strengths() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("demo");
    // A machine too slow for the pace (see the module doc): every UTM sample waits 1 ms in
    // the forwarder, every set 1 ms before the solver — at 50× the recorded pace the UTM stream
    // alone needs a sample every 0.4 ms, so the replay must play slower; the throttle's floor
    // (1 ms for each of ~49 500 samples) is a third of what 3 ms at 20× gave.
    let started = std::time::Instant::now();
    let o = Command::new(env!("CARGO_BIN_EXE_tagdeflect"))
        .args(["demo", "--c1609"])
        .arg(&root)
        .args(["--small", "--speed", "50", "--no-http"])
        .env("TAGDEFLECT_THROTTLE_MS", "1")
        .output()
        .unwrap();
    println!("demo --c1609 at 50x, throttled 1 ms: {:.0} s", started.elapsed().as_secs_f64());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    let tests: Vec<_> = std::fs::read_dir(root.join("tests")).unwrap().flatten().filter(|e| e.path().join("test.json").is_file()).collect();
    assert_eq!(tests.len(), 1, "one test, started and stopped automatically: {err}");
    let folder = tests[0].path();
    let record = read_json(&folder.join("test.json"));
    assert_eq!(record["standard"], "astm-c1609");
    assert!(err.contains("played") && err.contains("slower"), "the replay fell behind and played slower: {err}");
    let lines = feed_lines(&o.stdout);
    in_step_with_the_recording(&lines, &root.join("recording"), &record);
    let j = read_json(&folder.join("report").join("report.json"));
    println!("demo --c1609: valid {}, reasons {}, rates {}", j["valid"], j["invalid_reasons"], j["rates"]);
    assert_eq!(j["valid"], true, "{}", j["invalid_reasons"]);

    // The truth: the simulated law's loads at the first peak, L/600 and L/150.
    let params = DemoTest { speed: 2.0, small: true, root: root.clone() }.params();
    let (b, d, l) = (params.beam_width_mm, params.beam_height_mm, params.span_mm);
    let strength = |p_kn: f64| p_kn * 1e3 * l / (b * d * d);
    let truth = [
        ("f1", strength(load_at(&params, params.crack_deflection_mm))),
        ("f600", strength(load_at(&params, l / 600.0))),
        ("f150", strength(load_at(&params, l / 150.0))),
    ];
    for (key, want) in truth {
        let got = j[key]["value"].as_f64().unwrap_or_else(|| panic!("{key}: {}", j[key]));
        let sigma = j[key]["sigma"].as_f64().unwrap_or(0.0);
        println!("{key}: {got:.4} MPa (σ {sigma:.4}), law {want:.4} MPa, error {:+.2} %", 100.0 * (got - want) / want);
        assert!((got - want).abs() <= 0.02 * want, "{key}: {got} MPa against the law's {want} MPa (2 %)");
    }
    // The rates measured are the ones simulated, each inside its window.
    let rates = j["rates"].as_array().unwrap();
    assert_eq!(rates.len(), 2, "{rates:?}");
    for (r, want) in rates.iter().zip([RATE_TO_L900_MM_PER_MIN, RATE_AFTER_L900_MM_PER_MIN]) {
        let got = r["mm_per_min"].as_f64().unwrap();
        assert!((got - want).abs() < 0.1 * want, "{r}: simulated {want} mm/min");
    }
}

/// The feed's lines (stdout), in order.
fn feed_lines(stdout: &[u8]) -> Vec<serde_json::Value> {
    String::from_utf8_lossy(stdout).lines().filter(|l| l.starts_with('{')).map(|l| serde_json::from_str(l).unwrap()).collect()
}

/// The recording's UTM load at `t_ns`, linearly interpolated (as the measurement does).
fn recorded_load_at(utm: &[(i64, f64)], t_ns: i64) -> Option<f64> {
    let i = utm.partition_point(|(t, _)| *t < t_ns);
    let b = *utm.get(i)?;
    if b.0 == t_ns {
        return Some(b.1);
    }
    let a = *utm.get(i.checked_sub(1)?)?;
    Some(a.1 + (b.1 - a.1) * (t_ns - a.0) as f64 / (b.0 - a.0) as f64)
}

/// Every recorded frame set has its line, each line's load is the recording's at its time,
/// the automatic start is at the third line at or above 0.5 kN and the zero's preload is the
/// load of the test's fifth line — as on a quiet machine, whatever the pace.
fn in_step_with_the_recording(lines: &[serde_json::Value], rec: &Path, record: &serde_json::Value) {
    let sets = std::fs::read_to_string(rec.join("truth.jsonl")).unwrap().lines().count();
    let seqs: Vec<u64> = lines.iter().map(|l| l["seq"].as_u64().unwrap()).collect();
    assert_eq!(seqs, (0..sets as u64).collect::<Vec<_>>(), "one line per recorded frame set, none dropped");
    let utm: Vec<(i64, f64)> = std::fs::read_to_string(rec.join("utm.jsonl"))
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap())
        .map(|j| (j["t_ns"].as_i64().unwrap(), j["load_kN"].as_f64().unwrap()))
        .collect();
    let t_of = |l: &serde_json::Value| l["t_ns"].as_i64().unwrap();
    let mut off = Vec::new();
    for l in lines {
        let want = recorded_load_at(&utm, t_of(l));
        let got = l["load_kN"].as_f64();
        if want.is_some() && got.is_none_or(|g| (g - want.unwrap()).abs() > 1e-9) {
            off.push((l["seq"].clone(), got, want));
        }
    }
    assert!(off.is_empty(), "{} line(s) without the recording's load at their time, the first: {:?}", off.len(), &off[..off.len().min(5)]);
    // The start: the third line at or above 0.5 kN (the loads rise monotonically from rest).
    let loads: Vec<f64> = lines.iter().map(|l| recorded_load_at(&utm, t_of(l)).unwrap_or(0.0)).collect();
    let start = loads.iter().enumerate().filter(|(_, l)| **l >= 0.5).nth(2).map(|(i, _)| i).expect("the load reaches 0.5 kN");
    let step = loads[start] - loads[start - 1];
    println!("automatic start at seq {start}, {:.3} kN (a set's step {step:.3} kN); zero at {}", loads[start], record["preload"]);
    assert_eq!(record["started_t_ns"].as_i64(), Some(t_of(&lines[start])), "the start's line");
    assert!(loads[start] <= 0.5 + 3.0 * step, "{} kN", loads[start]);
    // The zero: the test's first five lines (from its start); its preload is the fifth's load.
    let zero = start + 4;
    assert_eq!(record["preload"]["t_ns"].as_i64(), Some(t_of(&lines[zero])), "the zero's line: {}", record["preload"]);
    let preload = record["preload"]["load_kn"].as_f64().unwrap();
    assert!((preload - loads[zero]).abs() < 1e-9, "zero at {preload} kN, recorded {} kN", loads[zero]);
}
