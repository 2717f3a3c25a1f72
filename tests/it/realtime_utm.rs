//! `replay --realtime` on a machine too slow for its recording: the frames keep the live drop
//! policy (a late set is dropped and counted), and every line that goes out carries the
//! recording's load at its time — the UTM samples are handed over in recorded order with the
//! frames, so a busy machine can cost a line, never its load (docs/simulation.md).

use std::path::Path;
use std::process::Command;

use tagdeflect_sim::SimParams;

use crate::common;

/// The recording's UTM load at `t_ns`, linearly interpolated (as the measurement does); none
/// outside the recorded stream.
fn recorded_load_at(utm: &[(i64, f64)], t_ns: i64) -> Option<f64> {
    let i = utm.partition_point(|(t, _)| *t < t_ns);
    let b = *utm.get(i)?;
    if b.0 == t_ns {
        return Some(b.1);
    }
    let a = *utm.get(i.checked_sub(1)?)?;
    Some(a.1 + (b.1 - a.1) * (t_ns - a.0) as f64 / (b.0 - a.0) as f64)
}

fn recorded_utm(rec: &Path) -> Vec<(i64, f64)> {
    std::fs::read_to_string(rec.join("utm.jsonl"))
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap())
        .map(|j| (j["t_ns"].as_i64().unwrap(), j["load_kN"].as_f64().unwrap()))
        .collect()
}

#[test]
fn a_realtime_replay_on_a_machine_too_slow_for_its_utm_stream_gives_every_line_its_recorded_load() {
    let dir = tempfile::tempdir().unwrap();
    // 4 s of frames at 10 fps and UTM samples at 200 Hz (one every 5 ms); the throttle makes
    // the UTM's path take 6 ms a sample or more (slower than the recorded stream: it lags it
    // more and more) and the solver 6 ms a set.
    let params = SimParams { cameras: 2, width: 320, height: 240, frame_sets: 40, fps: 10.0, utm_hz: 200.0, ..SimParams::default() };
    let rec = common::simulate(dir.path(), "rec", &params);
    let utm = recorded_utm(&rec);
    assert!(utm.len() > 700, "{} samples", utm.len());
    let o = Command::new(env!("CARGO_BIN_EXE_tagdeflect"))
        .args(["replay", "--realtime"])
        .arg(&rec)
        .env("TAGDEFLECT_THROTTLE_MS", "6")
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    let lines: Vec<serde_json::Value> =
        String::from_utf8_lossy(&o.stdout).lines().filter(|l| l.starts_with('{')).map(|l| serde_json::from_str(l).unwrap()).collect();
    let dropped = lines.last().and_then(|l| l["dropped_sets"].as_u64()).unwrap_or(0);
    println!("replay --realtime, throttled 6 ms: {} lines, {dropped} sets dropped", lines.len());
    // A set is a line, or dropped (by the solver's queue, or its frames by the capture when
    // the players waited for the UTM's path: each camera's `dropped_frames`).
    assert!(lines.len() as u64 + dropped <= 40, "{} lines and {dropped} dropped of 40 sets", lines.len());
    let mut inside = 0;
    let mut off = Vec::new();
    for l in &lines {
        let Some(want) = recorded_load_at(&utm, l["t_ns"].as_i64().unwrap()) else { continue };
        inside += 1;
        let got = l["load_kN"].as_f64();
        if got.is_none_or(|g| (g - want).abs() > 1e-9) {
            off.push((l["seq"].clone(), got, want));
        }
    }
    assert!(inside >= 5, "{inside} lines inside the recorded UTM stream");
    assert!(off.is_empty(), "{} of {inside} line(s) without the recording's load, the first: {:?}", off.len(), &off[..off.len().min(5)]);
}
