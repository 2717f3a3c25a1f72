//! The MQTT publisher's read-back across the feed's rotation (`[output.feed_rotation]`) during a
//! broker outage, against the real Mosquitto and PostgreSQL of [`crate::archive`]: the lines
//! that left the publisher's memory while the broker was down are read back from the rotated
//! files and reach the archive once each.

use std::fs;
use std::path::{Path, PathBuf};
use std::time::Duration;

use tagdeflect_archive::local::{LocalMosquitto, LocalPostgres};
use tagdeflect_core::feed_rotation::{feed_files, FeedRotation};
use tagdeflect_sim::{SimParams, SimRig};

use crate::archive::{assert_rows_equal_feed, logs_of, start_archive, start_demo, wait_rows};

/// A small live demo rig (one 480x360 camera at 10 fps, the simulated UTM) publishing to
/// `broker` as `rig`/`test` with a memory of `buffer` lines; its feed into `<dir>/feeds/<rig>.jsonl`,
/// rotated past `max_mb`. The config's path and the current feed file.
fn rotated_config(dir: &Path, broker: &str, rig: &str, buffer: usize, max_mb: f64) -> (PathBuf, PathBuf) {
    let params =
        SimParams { cameras: 1, width: 480, height: 360, fps: 10.0, frame_sets: 60, rest_frames: 5, subsamples: 2, ..SimParams::default() };
    let mut config = tagdeflect::config::Config::from_sim(&SimRig::new(&params).unwrap());
    config.utm = tagdeflect::config::Config::demo().utm;
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

/// A broker (with persistence) down for 10 s while the rig's feed rotates every ~20 kB and its
/// publisher keeps only 15 lines in memory: the ~100 lines of the outage leave its memory and
/// are spread over several rotated files when the broker is back. Every line is then read back
/// from those files and the archive holds each line of the feed once, equal to it; the feed's
/// files hold every line once, in order (seq 0…n−1); nothing is counted dropped and the rig
/// never says a line was missing from the feed or that the file could not be read back.
#[test]
fn a_broker_outage_across_feed_rotations_is_read_back_from_the_rotated_files_once() {
    let dir = tempfile::tempdir().unwrap();
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
    let seqs: Vec<i64> = lines.iter().map(|l| l["seq"].as_i64().unwrap()).collect();
    assert_eq!(seqs, (0..lines.len() as i64).collect::<Vec<_>>(), "the feed's files hold every line once, in order");
    let rows = wait_rows(&pg.url(), "rot", "rot", lines.len(), Duration::from_secs(60));
    let missing: Vec<i64> = seqs.iter().copied().filter(|s| !rows.contains_key(s)).collect();
    assert_eq!(rows.len(), lines.len(), "archived {} of {} lines; missing {missing:?}\n{}", rows.len(), lines.len(), logs());
    assert_rows_equal_feed(&rows, &lines);
    assert_eq!(lines.last().unwrap()["mqtt_dropped"], 0, "nothing lost for good\n{}", logs());
    let demo_log = fs::read_to_string(dir.path().join("demo.log")).unwrap();
    for never in ["not in the feed file", "cannot read the feed file back"] {
        assert!(!demo_log.contains(never), "the rig said \"{never}\"\n{}", logs());
    }
    assert!(demo_log.contains("the archive confirmed every feed line"), "{}", logs());
    assert!(archive.alive());
}
