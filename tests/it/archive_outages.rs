//! The archive's outages against the real servers (Debian's `mosquitto` and `postgresql`, on
//! loopback, started by the harness of `archive.rs`): the broker restarted or down, the archive
//! stopped or killed, the database down or failing, a run restarted under the same test id —
//! nothing lost, nothing twice.

use std::fs;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use crate::archive::{
    archived, assert_converged, assert_rows_equal_feed, bin, count, demo_config, demo_config_with, logs_of, query, read_feed,
    start_archive, start_demo, start_demo_to, tag_count, wait_rows, Proc, LINE_ROWS, TAG_ROWS,
};
use tagdeflect_archive::local::{LocalMosquitto, LocalPostgres};

/// The outage of a broker *without* persistence stopped for 8 s mid-run and
/// started again. It forgets the archive's session; after its restart it acknowledges the
/// rig's backlog and delivers it to nobody if the rig reconnects before the archive has
/// subscribed again. The archive's acknowledgement makes the rig send those lines again.
#[test]
fn broker_without_persistence_restarted_mid_run_the_archive_gets_every_line() {
    let dir = tempfile::tempdir().unwrap();
    let mut broker = LocalMosquitto::start_with(false).unwrap();
    let pg = LocalPostgres::start(false).unwrap();
    let mut archive = start_archive(&broker.url(), &pg.url(), "archive-np", &dir.path().join("archive.log"));
    let (cfg, feed_path) = demo_config(dir.path(), &broker.url(), "np", "np", 10_000);
    let mut demo = start_demo(&cfg, 20.0, &dir.path().join("demo.log"));
    // Mid-run: once the archive holds lines.
    assert!(wait_rows(&pg.url(), "np", "np", 20, Duration::from_secs(30)).len() >= 20, "nothing archived");
    broker.stop();
    std::thread::sleep(Duration::from_secs(8)); // the outage itself
    broker.start_again().unwrap();
    assert!(demo.wait(Duration::from_secs(60)).success(), "{}", fs::read_to_string(dir.path().join("demo.log")).unwrap());
    let logs = || logs_of(dir.path(), &["demo.log", "archive.log"]);
    let n = assert_converged(&pg.url(), "np", "np", &feed_path, logs);
    let feed = read_feed(&feed_path);
    assert_eq!(feed.last().unwrap()["mqtt_dropped"], 0, "nothing was lost for good");
    assert!(n >= 150, "only {n} lines");
    let demo_log = fs::read_to_string(dir.path().join("demo.log")).unwrap();
    assert!(demo_log.contains("the archive confirmed every feed line"), "{}", logs());
    assert!(archive.alive());
}

/// A broker *with* persistence down for 10 s: a rig whose buffer holds the outage, one
/// whose 15-line buffer does not but whose feed file does (lines are read back from it),
/// and one with a 15-line buffer and no feed file: it loses exactly what it counts.
#[test]
fn broker_down_for_10_s_loses_nothing_with_a_feed_file_and_counts_exactly_without() {
    let dir = tempfile::tempdir().unwrap();
    let mut broker = LocalMosquitto::start().unwrap();
    let pg = LocalPostgres::start(false).unwrap();
    let mut archive = start_archive(&broker.url(), &pg.url(), "archive-bo", &dir.path().join("archive.log"));
    let (cfg_big, feed_big) = demo_config(dir.path(), &broker.url(), "big", "bo", 10_000);
    let (cfg_small, feed_small) = demo_config(dir.path(), &broker.url(), "small", "bo", 15);
    let (cfg_tiny, _) = demo_config_with(dir.path(), &broker.url(), "tiny", "bo", 15, false, 60);
    let mut big = start_demo(&cfg_big, 22.0, &dir.path().join("big.log"));
    let mut small = start_demo(&cfg_small, 22.0, &dir.path().join("small.log"));
    let tiny_feed = dir.path().join("tiny-stdout.jsonl");
    let mut tiny = start_demo_to(&cfg_tiny, 22.0, &dir.path().join("tiny.log"), Some(&tiny_feed));
    for rig in ["big", "small", "tiny"] {
        assert!(!wait_rows(&pg.url(), rig, "bo", 10, Duration::from_secs(30)).is_empty(), "rig {rig}: nothing archived");
    }
    broker.stop();
    std::thread::sleep(Duration::from_secs(10)); // the outage itself
    broker.start_again().unwrap();
    let logs = || logs_of(dir.path(), &["big.log", "small.log", "tiny.log", "archive.log"]);
    for (p, name) in [(&mut big, "big"), (&mut small, "small"), (&mut tiny, "tiny")] {
        assert!(p.wait(Duration::from_secs(60)).success(), "rig {name} failed\n{}", logs());
    }
    for (rig, feed) in [("big", &feed_big), ("small", &feed_small)] {
        assert_converged(&pg.url(), rig, "bo", feed, logs);
        assert_eq!(read_feed(feed).last().unwrap()["mqtt_dropped"], 0, "rig {rig} lost nothing for good");
    }
    // Without a feed file: what left the 15-line memory before the broker took it is lost,
    // and exactly that is counted (the tiny rig's feed went to its stdout).
    let tiny_lines = read_feed(&tiny_feed);
    let made = tiny_lines.len() as i64;
    // The count at the rig's end: its last (offline) status; the last feed line's is not above it.
    let dropped = query(&pg.url(), |c| {
        Box::pin(async move {
            let r = c
                .query_one("SELECT t.status FROM tests t JOIN rigs r ON r.id = t.rig_id WHERE r.name = 'tiny' AND t.name = 'bo'", &[])
                .await
                .unwrap();
            r.get::<_, serde_json::Value>(0)["mqtt_dropped"].as_i64().unwrap()
        })
    });
    assert!(tiny_lines.last().unwrap()["mqtt_dropped"].as_i64().unwrap() <= dropped);
    assert!(dropped >= 50, "only {dropped} lines dropped from a 15-line memory during a 10 s outage\n{}", logs());
    let rows = wait_rows(&pg.url(), "tiny", "bo", (made - dropped) as usize, Duration::from_secs(30));
    assert_eq!(rows.len() as i64 + dropped, made, "rig tiny: {} archived + {dropped} dropped vs {made} made\n{}", rows.len(), logs());
    assert!(archive.alive());
}

/// The archive stopped while the rig runs and started again only after the rig ended:
/// the broker's persistent session keeps what the archive missed.
#[test]
fn archive_stopped_during_the_run_and_started_after_it_gets_every_line() {
    let dir = tempfile::tempdir().unwrap();
    let broker = LocalMosquitto::start().unwrap();
    let pg = LocalPostgres::start(false).unwrap();
    let alog = dir.path().join("archive.log");
    let mut archive = start_archive(&broker.url(), &pg.url(), "archive-sa", &alog);
    let (cfg, feed_path) = demo_config(dir.path(), &broker.url(), "sa", "sa", 10_000);
    let mut demo = start_demo(&cfg, 10.0, &dir.path().join("demo.log"));
    assert!(!wait_rows(&pg.url(), "sa", "sa", 10, Duration::from_secs(30)).is_empty());
    archive.kill();
    assert!(demo.wait(Duration::from_secs(60)).success());
    let mut archive = start_archive(&broker.url(), &pg.url(), "archive-sa", &alog);
    assert_converged(&pg.url(), "sa", "sa", &feed_path, || logs_of(dir.path(), &["demo.log", "archive.log"]));
    assert!(archive.alive());
}

#[test]
fn archive_killed_and_restarted_resumes_without_duplicates() {
    let dir = tempfile::tempdir().unwrap();
    let broker = LocalMosquitto::start().unwrap();
    let pg = LocalPostgres::start(false).unwrap();
    let alog = dir.path().join("archive.log");
    let mut archive = start_archive(&broker.url(), &pg.url(), "archive-ar", &alog);
    let (cfg, feed_path) = demo_config(dir.path(), &broker.url(), "frame-2", "ar", 10_000);
    let mut demo = start_demo(&cfg, 12.0, &dir.path().join("demo.log"));
    // Mid-run: once the archive holds lines.
    let before = wait_rows(&pg.url(), "frame-2", "ar", 5, Duration::from_secs(30)).len();
    assert!(before >= 5, "nothing archived in 30 s");
    archive.kill(); // SIGKILL: whatever it held uncommitted is unacknowledged
    std::thread::sleep(Duration::from_secs(3));
    let mut archive = start_archive(&broker.url(), &pg.url(), "archive-ar", &alog);
    assert!(demo.wait(Duration::from_secs(60)).success());
    let feed = read_feed(&feed_path);
    let rows = wait_rows(&pg.url(), "frame-2", "ar", feed.len(), Duration::from_secs(30));
    assert_eq!(rows.len(), feed.len(), "archived {} of {} lines", rows.len(), feed.len());
    assert_rows_equal_feed(&rows, &feed);
    assert_eq!(count(&pg.url(), LINE_ROWS, "ar"), feed.len() as i64, "frame sets");
    assert_eq!(count(&pg.url(), TAG_ROWS, "ar"), tag_count(&feed), "tag samples (no duplicates)");
    assert!(archive.alive());
}

#[test]
fn postgres_down_for_10_s_the_archive_retries_and_loses_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let broker = LocalMosquitto::start().unwrap();
    let pg = LocalPostgres::start(false).unwrap();
    let alog = dir.path().join("archive.log");
    let mut archive = start_archive(&broker.url(), &pg.url(), "archive-pd", &alog);
    let (cfg, feed_path) = demo_config(dir.path(), &broker.url(), "frame-3", "pd", 10_000);
    let mut demo = start_demo(&cfg, 15.0, &dir.path().join("demo.log"));
    // Mid-run: once the archive holds lines.
    assert!(wait_rows(&pg.url(), "frame-3", "pd", 5, Duration::from_secs(30)).len() >= 5, "nothing archived");
    pg.stop().unwrap();
    std::thread::sleep(Duration::from_secs(10)); // the outage itself
    pg.start_again().unwrap();
    assert!(demo.wait(Duration::from_secs(60)).success());
    let feed = read_feed(&feed_path);
    let rows = wait_rows(&pg.url(), "frame-3", "pd", feed.len(), Duration::from_secs(30));
    assert_eq!(rows.len(), feed.len(), "archived {} of {} lines", rows.len(), feed.len());
    assert_rows_equal_feed(&rows, &feed);
    assert_eq!(count(&pg.url(), TAG_ROWS, "pd"), tag_count(&feed));
    let log = fs::read_to_string(&alog).unwrap();
    assert!(log.contains("database unreachable") || log.contains("cannot commit"), "{log}");
    assert!(archive.alive(), "{log}");
}

/// A database error is logged with its cause, not as a bare "db error".
#[test]
fn a_database_error_is_logged_with_its_cause() {
    let dir = tempfile::tempdir().unwrap();
    let broker = LocalMosquitto::start().unwrap();
    let pg = LocalPostgres::start(false).unwrap();
    let url = pg.url().replace("/postgres", "/no_such_db");
    let log = dir.path().join("archive.log");
    let child = Command::new(bin())
        .args(["archive", "--mqtt", &broker.url(), "--postgres", &url, "--client-id", "archive-err"])
        .env("TAGDEFLECT_LOG", "info")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(fs::File::create(&log).unwrap())
        .spawn()
        .unwrap();
    let mut p = Proc { child, name: "archive" };
    let until = Instant::now() + Duration::from_secs(30);
    loop {
        let text = fs::read_to_string(&log).unwrap_or_default();
        if text.contains("database unreachable") {
            assert!(text.contains("database \"no_such_db\" does not exist"), "{text}");
            break;
        }
        assert!(p.alive() && Instant::now() < until, "{text}");
        std::thread::sleep(Duration::from_millis(50));
    }
    p.kill();
}

/// Two runs with one fixed test id (a run and its restart): both are kept, the second as
/// run 2 (`<test>#2` in feed_lines), and the archive warns.
#[test]
fn a_restarted_run_with_the_same_test_id_is_kept_as_a_second_run() {
    let dir = tempfile::tempdir().unwrap();
    let broker = LocalMosquitto::start().unwrap();
    let pg = LocalPostgres::start(false).unwrap();
    let alog = dir.path().join("archive.log");
    let mut archive = start_archive(&broker.url(), &pg.url(), "archive-rr", &alog);
    let (cfg, feed_path) = demo_config(dir.path(), &broker.url(), "rr", "fixed", 10_000);
    let mut first = start_demo(&cfg, 4.0, &dir.path().join("run1.log"));
    assert!(first.wait(Duration::from_secs(60)).success());
    let n1 = read_feed(&feed_path).len();
    let rows1 = wait_rows(&pg.url(), "rr", "fixed", n1, Duration::from_secs(30));
    assert_eq!(rows1.len(), n1);
    let mut second = start_demo(&cfg, 4.0, &dir.path().join("run2.log"));
    assert!(second.wait(Duration::from_secs(60)).success());
    // The feed file holds both runs, appended.
    let feed = read_feed(&feed_path);
    let (run1, run2) = feed.split_at(n1);
    assert_eq!(run2[0]["seq"], run1[0]["seq"], "the restart numbers its lines from the start again");
    let rows2 = wait_rows(&pg.url(), "rr", "fixed#2", run2.len(), Duration::from_secs(30));
    let logs = || logs_of(dir.path(), &["run1.log", "run2.log", "archive.log"]);
    assert_eq!(rows2.len(), run2.len(), "run 2: archived {} of {}\n{}", rows2.len(), run2.len(), logs());
    assert_rows_equal_feed(&rows2, run2);
    let rows1 = archived(&pg.url(), "rr", "fixed");
    assert_eq!(rows1.len(), run1.len(), "run 1 kept as it was");
    assert_rows_equal_feed(&rows1, run1);
    assert!(fs::read_to_string(&alog).unwrap().contains("a new run 2"), "{}", logs());
    let run2_log = fs::read_to_string(dir.path().join("run2.log")).unwrap();
    assert!(run2_log.contains("the archive confirmed every feed line"), "{}", logs());
    assert!(archive.alive());
}
