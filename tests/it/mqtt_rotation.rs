//! The MQTT publisher's read-back across the feed's rotation (`[output.feed_rotation]`) during a
//! broker outage, against the real Mosquitto and PostgreSQL of [`crate::archive`]: the lines
//! that left the publisher's memory while the broker was down are read back from the rotated
//! files and reach the archive once each.

use std::fs;
use std::path::{Path, PathBuf};
use std::time::Duration;

use tagdeflect_archive::local::{LocalMosquitto, LocalPostgres};
use tagdeflect_core::feed_rotation::{feed_files, FeedRotation};
use tagdeflect_sim::SimParams;

use crate::archive::{assert_rows_equal_feed, logs_of, start_archive, start_demo, wait_rows};
use crate::common;

/// A small live demo rig (one 480x360 camera at 10 fps, the simulated UTM) publishing to
/// `broker` as `rig`/`test` with a memory of `buffer` lines; its feed into `<dir>/feeds/<rig>.jsonl`,
/// rotated past `max_mb`. The config's path and the current feed file.
fn rotated_config(dir: &Path, broker: &str, rig: &str, buffer: usize, max_mb: f64) -> (PathBuf, PathBuf) {
    let params =
        SimParams { cameras: 1, width: 480, height: 360, fps: 10.0, frame_sets: 60, rest_frames: 5, subsamples: 2, ..SimParams::default() };
    let mut config = common::sim_rig_config(&params);
    let feed = dir.join("feeds").join(format!("{rig}.jsonl"));
    config.output.feed = Some(feed.display().to_string());
    config.output.feed_rotation = FeedRotation { max_mb, ..FeedRotation::default() };
    let mut text = config.to_toml_string();
    text.push_str(&format!(
        "\n[output.mqtt]\nurl = \"{broker}\"\nrig = \"{rig}\"\ntest = \"{rig}\"\nbuffer_lines = {buffer}\nstatus_interval_s = 1.0\n"
    ));
    let path = dir.join(format!("{rig}.toml"));
    fs::write(&path, text).unwrap();
    (path, feed)
}

/// The lines of the feed's files (rotated ones first, the current last), in order.
fn feed_set(feed: &Path) -> Vec<serde_json::Value> {
    let mut out = Vec::new();
    for f in feed_files(feed).unwrap() {
        let text = fs::read_to_string(&f).unwrap();
        out.extend(text.lines().map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap()));
    }
    out
}

/// The seqs missing from the feed's `lines`, each a frame set the live run dropped because its
/// solver fell behind (docs/feed.md, `dropped_sets`), after checking that: the seqs rise (no line
/// twice, none out of order); each line's `dropped_sets` covers the seqs missing before it; the
/// last line's is exactly the number missing (a set is dropped only when a newer one is queued,
/// and counted before that one is: every drop is counted by the last line).
fn missing_seqs_all_counted_dropped(lines: &[serde_json::Value]) -> Vec<u64> {
    let seqs: Vec<u64> = lines.iter().map(|l| l["seq"].as_u64().unwrap()).collect();
    assert!(seqs.windows(2).all(|w| w[0] < w[1]), "the feed's files hold every line once, in order: {seqs:?}");
    for (i, l) in lines.iter().enumerate() {
        let counted = l["dropped_sets"].as_u64().unwrap_or_else(|| panic!("a live run's line without dropped_sets: {l}"));
        let missing_before = seqs[i] - i as u64;
        assert!(
            missing_before <= counted,
            "seq {}: {missing_before} seqs missing before it, {counted} frame sets counted dropped",
            seqs[i]
        );
    }
    let missing: Vec<u64> = (0..=seqs[seqs.len() - 1]).filter(|s| seqs.binary_search(s).is_err()).collect();
    let counted = lines[lines.len() - 1]["dropped_sets"].as_u64().unwrap();
    assert_eq!(
        missing.len() as u64,
        counted,
        "seqs {missing:?} missing from the feed's files; the last line counts {counted} frame sets dropped"
    );
    missing
}

/// A broker (with persistence) down for 10 s while the rig's feed rotates every ~20 kB and its
/// publisher keeps only 15 lines in memory: the ~100 lines of the outage leave its memory and
/// are spread over several rotated files when the broker is back. Every line is then read back
/// from those files and the archive holds each line of the feed once, equal to it; the feed's
/// files hold every line once, in order, a seq missing only for a frame set the solver dropped
/// (counted in `dropped_sets`, the first said in the log: on a loaded machine a set in a few
/// hundred is); no line is counted lost for the archive (`mqtt_dropped`) and the rig never says
/// a line was missing from the feed or that the file could not be read back.
#[test]
fn a_broker_outage_across_feed_rotations_is_read_back_from_the_rotated_files_once() {
    let dir = common::KeptOnFailure::new("mqtt_rotation");
    let mut broker = LocalMosquitto::start().unwrap();
    let pg = LocalPostgres::start(false).unwrap();
    let mut archive = start_archive(&broker.url(), &pg.url(), "archive-rot", &dir.path().join("archive.log"));
    let (cfg, feed) = rotated_config(dir.path(), &broker.url(), "rot", 15, 0.02);
    let mut demo = start_demo(&cfg, 24.0, &dir.path().join("demo.log"));
    assert!(!wait_rows(&pg.url(), "rot", "rot", 10, Duration::from_secs(30)).is_empty(), "nothing archived before the outage");
    let files_before = feed_files(&feed).unwrap().len();
    broker.stop();
    std::thread::sleep(Duration::from_secs(10)); // the outage itself
    let files_after = feed_files(&feed).unwrap().len();
    broker.start_again().unwrap();
    let logs = || logs_of(dir.path(), &["demo.log", "archive.log"]);
    assert!(demo.wait(Duration::from_secs(90)).success(), "the rig failed\n{}", logs());
    assert!(files_after >= files_before + 3, "the feed rotated {} times during the outage\n{}", files_after - files_before, logs());

    let lines = feed_set(&feed);
    let dropped = missing_seqs_all_counted_dropped(&lines);
    println!("{} lines; frame sets dropped (the solver fell behind): {dropped:?}", lines.len());
    let seqs: Vec<i64> = lines.iter().map(|l| l["seq"].as_i64().unwrap()).collect();
    let rows = wait_rows(&pg.url(), "rot", "rot", lines.len(), Duration::from_secs(60));
    let missing: Vec<i64> = seqs.iter().copied().filter(|s| !rows.contains_key(s)).collect();
    assert_eq!(rows.len(), lines.len(), "archived {} of {} lines; missing {missing:?}\n{}", rows.len(), lines.len(), logs());
    assert_rows_equal_feed(&rows, &lines);
    assert_eq!(lines.last().unwrap()["mqtt_dropped"], 0, "nothing lost for good\n{}", logs());
    let demo_log = fs::read_to_string(dir.path().join("demo.log")).unwrap();
    for never in ["not in the feed file", "cannot read the feed file back"] {
        assert!(!demo_log.contains(never), "the rig said \"{never}\"\n{}", logs());
    }
    if let Some(first) = dropped.first() {
        let said = demo_log.lines().any(|l| l.contains("WARN") && l.contains("frame set dropped") && l.contains(&format!(" seq={first} ")));
        assert!(said, "the first frame set dropped (seq {first}) is said in the log\n{}", logs());
    }
    assert!(demo_log.contains("the archive confirmed every feed line"), "{}", logs());
    assert!(archive.alive());
}

/// The check above on lines made by hand: a set dropped and counted passes (its seq returned),
/// a line lost without a count, a line twice or out of order, or a count with no seq missing
/// each fail.
#[test]
fn a_missing_seq_passes_only_as_a_counted_dropped_set() {
    let lines = |v: &[(u64, u64)]| -> Vec<serde_json::Value> {
        v.iter().map(|(seq, d)| serde_json::json!({"seq": seq, "dropped_sets": d})).collect()
    };
    let fails = |v: &[(u64, u64)]| std::panic::catch_unwind(|| missing_seqs_all_counted_dropped(&lines(v))).is_err();
    assert_eq!(missing_seqs_all_counted_dropped(&lines(&[(0, 0), (1, 0), (3, 1), (4, 1)])), vec![2]);
    // Counted while the solver still worked on the set before the gap.
    assert_eq!(missing_seqs_all_counted_dropped(&lines(&[(0, 0), (1, 1), (3, 1)])), vec![2]);
    assert!(fails(&[(0, 0), (1, 0), (3, 0), (4, 0)]), "a line lost, not counted");
    assert!(fails(&[(0, 0), (1, 0), (3, 0), (4, 1)]), "counted only after the line after the gap");
    assert!(fails(&[(0, 0), (1, 0), (1, 0), (2, 0)]), "a line twice");
    assert!(fails(&[(0, 0), (2, 0), (1, 0)]), "out of order");
    assert!(fails(&[(0, 0), (1, 0), (2, 1)]), "a drop counted with no seq missing");
}
