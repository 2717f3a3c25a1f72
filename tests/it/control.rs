//! A signal the machine can follow (issue 21): the temporal estimate on frame sets that lack
//! cameras, σ of the net deflection on every line, and the control output read by a real
//! Modbus client (pymodbus) while `demo` runs.

use std::collections::HashMap;
use std::fs;
use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Command, Stdio};

use nalgebra::Vector3;
use tagdeflect::accuracy::truth_at;
use tagdeflect::config::{Config, TagRole};
use tagdeflect::feed::FeedLine;
use tagdeflect::pipeline::replay::{self, ReplayOptions};
use tagdeflect::recording::Recording;
use tagdeflect::sim::SimParams;
use tagdeflect::solve::temporal::Estimator;

use crate::common::{self, free_port, ChildGuard};

/// Net-deflection error against truth of every line that has one: (seq, error mm, σ mm, partial).
fn net_errors(config: &Config, rec_truth: &[tagdeflect::recording::TruthLine], lines: &[FeedLine]) -> Vec<(u64, f64, f64, bool)> {
    let up = Vector3::from(config.world.up).normalize();
    let mut first: HashMap<u32, Vector3<f64>> = HashMap::new();
    let mut out = Vec::new();
    for l in lines {
        let tr = truth_at(rec_truth, l.t_ns);
        let mut down: HashMap<u32, f64> = HashMap::new();
        for t in &l.tags {
            let Some(p) = tr.get(&t.id) else { continue };
            let p0 = *first.entry(t.id).or_insert(*p);
            down.insert(t.id, -(p - p0).dot(&up));
        }
        let (Some(net), Some(sigma)) = (l.net_deflection_mm, l.net_deflection_sigma_mm) else {
            assert!(l.net_deflection_mm.is_none(), "line {}: a net deflection without its σ", l.seq);
            continue;
        };
        let mean = |role: TagRole| {
            let v: Vec<f64> = l.tags.iter().filter(|t| config.role_of(t.id) == Some(role)).filter_map(|t| down.get(&t.id)).copied().collect();
            (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
        };
        let truth = mean(TagRole::Midspan).unwrap() - mean(TagRole::Support).unwrap();
        out.push((l.seq, net - truth, sigma, l.partial_set));
    }
    out
}

fn rms(v: impl Iterator<Item = f64>) -> f64 {
    let (s, n) = v.fold((0.0, 0usize), |(s, n), x| (s + x * x, n + 1));
    (s / n.max(1) as f64).sqrt()
}

/// Removes frames from a recording: for set k, the cameras `drop(k)` lose their frame.
fn drop_frames(dir: &Path, cameras: &[String], drop: impl Fn(u64) -> Vec<usize>) -> usize {
    let path = dir.join("frames.jsonl");
    let text = fs::read_to_string(&path).unwrap();
    let mut kept = String::new();
    let mut removed = 0;
    for line in text.lines() {
        let v: serde_json::Value = serde_json::from_str(line).unwrap();
        let cam = cameras.iter().position(|c| c == v["camera"].as_str().unwrap()).unwrap();
        if drop(v["seq"].as_u64().unwrap()).contains(&cam) {
            removed += 1;
            continue;
        }
        kept.push_str(line);
        kept.push('\n');
    }
    fs::write(&path, kept).unwrap();
    removed
}

/// The sets that lack cameras: a third of them lack one or two (changing which), and two
/// cameras are gone for 2 s (20 sets at 10 fps) from set 50.
fn partial_pattern(k: u64) -> Vec<usize> {
    if (50..70).contains(&k) {
        return vec![1, 2];
    }
    match k % 3 {
        1 if k % 2 == 0 => vec![(k / 3 % 3) as usize],
        1 => vec![(k / 3 % 3) as usize, ((k / 3 + 1) % 3) as usize],
        _ => vec![],
    }
}

fn replay_with(dir: &Path, estimator: Estimator) -> (Recording, Vec<FeedLine>) {
    let mut rec = Recording::open(dir).unwrap();
    rec.config.measure.estimator = estimator;
    let mut lines = Vec::new();
    replay::replay(&rec, ReplayOptions { full_frame: false, progress: false }, |l, _, _| lines.push(l.clone())).unwrap();
    (rec, lines)
}

#[test]
fn partial_sets_are_kept_from_the_state_and_every_net_deflection_has_an_honest_sigma() {
    let tmp = tempfile::tempdir().unwrap();
    // Three 1280x960 cameras, tags ~28 px wide, 10 fps, 9 s of slow loading.
    let params = SimParams { frame_sets: 90, fps: 10.0, max_deflection_mm: 1.5, seed: 21, ..SimParams::default() };
    let full = common::simulate(tmp.path(), "full", &params);
    let partial = common::simulate(tmp.path(), "partial", &params);
    let names: Vec<String> = Recording::open(&partial).unwrap().config.cameras.iter().map(|c| c.name.clone()).collect();
    let removed = drop_frames(&partial, &names, partial_pattern);
    assert!(removed > 80, "{removed} frames removed");

    let (rec_full, full_temporal) = replay_with(&full, Estimator::Temporal);
    let (_, full_per_set) = replay_with(&full, Estimator::PerSet);
    let (rec, temporal) = replay_with(&partial, Estimator::Temporal);
    let (_, per_set) = replay_with(&partial, Estimator::PerSet);
    common::feedcheck(&temporal, &partial.join("tagdeflect.toml"));

    let e_full_t = net_errors(&rec_full.config, &rec_full.truth, &full_temporal);
    let e_full_p = net_errors(&rec_full.config, &rec_full.truth, &full_per_set);
    let e_t = net_errors(&rec.config, &rec.truth, &temporal);
    let e_p = net_errors(&rec.config, &rec.truth, &per_set);
    let full_rms_t = rms(e_full_t.iter().map(|e| e.1));
    let full_rms_p = rms(e_full_p.iter().map(|e| e.1));
    let part_t: Vec<_> = e_t.iter().filter(|e| e.3).collect();
    let part_p: Vec<_> = e_p.iter().filter(|e| e.3).collect();
    let part_rms_t = rms(part_t.iter().map(|e| e.1));
    let part_rms_p = rms(part_p.iter().map(|e| e.1));
    let max_t = e_t.iter().map(|e| e.1.abs()).fold(0.0, f64::max);
    let max_p = e_p.iter().map(|e| e.1.abs()).fold(0.0, f64::max);
    let within = e_t.iter().filter(|e| e.1.abs() <= 2.0 * e.2).count() as f64 / e_t.len() as f64;
    let within_p = e_p.iter().filter(|e| e.1.abs() <= 2.0 * e.2).count() as f64 / e_p.len() as f64;
    println!(
        "NET full sets: temporal {:.2} µm, per set {:.2} µm RMS; partial sets ({} of {}): temporal {:.2} µm (max {:.2}), per set {:.2} µm (max {:.2}); within 2σ: temporal {:.0} %, per set {:.0} %",
        full_rms_t * 1e3,
        full_rms_p * 1e3,
        part_t.len(),
        e_t.len(),
        part_rms_t * 1e3,
        max_t * 1e3,
        part_rms_p * 1e3,
        max_p * 1e3,
        within * 100.0,
        within_p * 100.0
    );
    assert!(part_t.len() * 3 >= e_t.len(), "a third of the sets or more are partial: {} of {}", part_t.len(), e_t.len());
    assert!(e_t.len() + 3 >= temporal.len(), "a net deflection on (nearly) every line: {} of {}", e_t.len(), temporal.len());
    // Accuracy on full sets no worse than solving each set on its own (10 % for chance).
    assert!(full_rms_t <= full_rms_p * 1.1, "full sets: temporal {full_rms_t}, per set {full_rms_p}");
    // The partial sets within 2× the full sets', no line beyond 8 µm, σ honest.
    assert!(part_rms_t <= 2.0 * full_rms_t.max(0.001), "partial {part_rms_t} vs full {full_rms_t}");
    assert!(max_t <= 0.008, "largest net-deflection error {max_t} mm");
    assert!(within >= 0.85, "{:.0} % within 2σ", within * 100.0);
}

#[test]
fn pymodbus_reads_the_control_registers_and_they_follow_the_feed() {
    let tmp = tempfile::tempdir().unwrap();
    let port = free_port();
    let addr = format!("127.0.0.1:{port}");
    let feed_path = tmp.path().join("feed.jsonl");
    let log_path = tmp.path().join("demo.log");
    let demo = Command::new(env!("CARGO_BIN_EXE_tagdeflect"))
        .args(["demo", "--duration-s", "12", "--no-http", "--control", &addr])
        .env("TAGDEFLECT_LOG", "info")
        .stdout(fs::File::create(&feed_path).unwrap())
        .stderr(fs::File::create(&log_path).unwrap())
        .spawn()
        .expect("start tagdeflect demo");
    let mut demo = ChildGuard(demo);
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
        assert!(sigma <= 0.01, "valid only with σ ≤ max_sigma_mm: {sigma}");
        if let Some(rate) = line.net_deflection_rate_mm_per_min {
            assert_eq!(r["rate_mm_per_min"].as_f64().unwrap() as f32, rate as f32, "seq {seq}");
        }
        assert!(r["age_ms"].as_u64().unwrap() < 10_000);
    }
    let beats = reads.last().unwrap()["heartbeat"].as_u64().unwrap() - reads[0]["heartbeat"].as_u64().unwrap();
    assert!(beats >= 20, "the heartbeat moved {beats} times over the run");
    let with_net = feed.iter().filter(|l| l.net_deflection_mm.is_some()).count();
    println!("CONTROL {} reads, {valid} valid, {} distinct frame sets of {with_net} with a net deflection", reads.len(), seqs.len());
    assert!(valid * 2 >= reads.len(), "{valid} of {} reads valid", reads.len());
    assert!(seqs.len() * 2 >= with_net, "the registers followed {} of {with_net} frame sets", seqs.len());
    // The last reads after the demo stopped measuring, if any, say invalid.
    assert!(log.contains("control output serving Modbus TCP"), "{log}");
}
