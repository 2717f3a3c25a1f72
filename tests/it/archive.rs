//! `demo` → Mosquitto → `archive` → PostgreSQL against the real servers (Debian's
//! `mosquitto` and `postgresql`, started here on loopback in temporary folders and stopped
//! by guards): the round trip, a malformed message, and the three outages (broker, archive,
//! database).

use std::collections::BTreeMap;
use std::fs;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use tagdeflect_archive::local::{LocalMosquitto, LocalPostgres};
use tagdeflect_sim::{SimParams, SimRig};

/// A child process killed (and reaped) when dropped.
pub(crate) struct Proc {
    child: Child,
    name: &'static str,
}

impl Proc {
    pub(crate) fn alive(&mut self) -> bool {
        matches!(self.child.try_wait(), Ok(None))
    }
    /// Waits for the process to end by itself; panics after `timeout`.
    pub(crate) fn wait(&mut self, timeout: Duration) -> std::process::ExitStatus {
        let until = Instant::now() + timeout;
        loop {
            if let Some(s) = self.child.try_wait().unwrap() {
                return s;
            }
            assert!(Instant::now() < until, "{} did not end within {timeout:?}", self.name);
            std::thread::sleep(Duration::from_millis(50));
        }
    }
    fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        self.kill();
    }
}

/// GET `path` from the daemon's page: the body.
fn http_get(addr: std::net::SocketAddr, path: &str) -> String {
    use std::io::{Read, Write};
    let mut s = std::net::TcpStream::connect_timeout(&addr, Duration::from_secs(5)).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    write!(s, "GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n").unwrap();
    let mut raw = String::new();
    s.read_to_string(&mut raw).unwrap();
    raw.split_once("\r\n\r\n").map(|(_, b)| b.to_string()).unwrap_or_default()
}

fn bin() -> &'static str {
    env!("CARGO_BIN_EXE_tagdeflect")
}

/// Starts `tagdeflect archive` logging into `log`.
pub(crate) fn start_archive(broker: &str, pg: &str, client_id: &str, log: &Path) -> Proc {
    let skip = fs::metadata(log).map_or(0, |m| m.len() as usize);
    let log_file = fs::OpenOptions::new().create(true).append(true).open(log).unwrap();
    let child = Command::new(bin())
        .args(["archive", "--mqtt", broker, "--postgres", pg, "--client-id", client_id])
        .env("TAGDEFLECT_LOG", "info")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(log_file)
        .spawn()
        .unwrap();
    let mut p = Proc { child, name: "archive" };
    // Ready once subscribed (messages published before would not reach its session) and
    // its schema is in place.
    let until = Instant::now() + Duration::from_secs(30);
    loop {
        let text = fs::read_to_string(log).unwrap_or_default().get(skip..).unwrap_or_default().to_string();
        if text.matches("archive: subscribed").count() >= 3 && text.contains("archive: database ready") {
            break;
        }
        assert!(p.alive(), "the archive exited: {text}");
        assert!(Instant::now() < until, "the archive did not subscribe within 30 s: {text}");
        std::thread::sleep(Duration::from_millis(50));
    }
    p
}

/// A small live demo rig (one 480x360 camera at 10 fps, the simulated UTM) publishing to
/// `broker` as `rig`/`test` with a buffer of `buffer` lines; the feed also goes to
/// `<dir>/<rig>.jsonl`.
fn demo_config(dir: &Path, broker: &str, rig: &str, test: &str, buffer: usize) -> (PathBuf, PathBuf) {
    demo_config_with(dir, broker, rig, test, buffer, true, 60)
}

/// [`demo_config`] with or without the feed file (without: the feed goes to the demo's
/// stdout, and the publisher has nothing to read lines back from) and `frame_sets` lines.
fn demo_config_with(
    dir: &Path,
    broker: &str,
    rig: &str,
    test: &str,
    buffer: usize,
    feed_file: bool,
    frame_sets: u32,
) -> (PathBuf, PathBuf) {
    let params =
        SimParams { cameras: 1, width: 480, height: 360, fps: 10.0, frame_sets, rest_frames: 5, subsamples: 2, ..SimParams::default() };
    let mut config = tagdeflect::config::Config::from_sim(&SimRig::new(&params).unwrap());
    config.utm = tagdeflect::config::Config::demo().utm;
    let feed = dir.join(format!("{rig}.jsonl"));
    config.output.feed = feed_file.then(|| feed.display().to_string());
    let mut text = config.to_toml_string();
    text.push_str(&format!(
        "\n[output.mqtt]\nurl = \"{broker}\"\nrig = \"{rig}\"\ntest = \"{test}\"\nbuffer_lines = {buffer}\nstatus_interval_s = 1.0\n"
    ));
    let path = dir.join(format!("{rig}.toml"));
    fs::write(&path, text).unwrap();
    (path, feed)
}

pub(crate) fn start_demo(config: &Path, seconds: f64, log: &Path) -> Proc {
    start_demo_to(config, seconds, log, None)
}

/// [`start_demo`] with its stdout (the feed, when the config has no feed file) into `out`.
fn start_demo_to(config: &Path, seconds: f64, log: &Path, out: Option<&Path>) -> Proc {
    let child = Command::new(bin())
        .args(["demo", "--no-http", "--config"])
        .arg(config)
        .args(["--duration-s", &seconds.to_string()])
        .stdin(Stdio::null())
        .stdout(out.map_or_else(Stdio::null, |p| fs::File::create(p).unwrap().into()))
        .stderr(fs::File::create(log).unwrap())
        .spawn()
        .unwrap();
    Proc { child, name: "demo" }
}

fn read_feed(path: &Path) -> Vec<serde_json::Value> {
    fs::read_to_string(path).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect()
}

fn query<T: Send + 'static>(
    url: &str,
    f: impl FnOnce(tokio_postgres::Client) -> std::pin::Pin<Box<dyn std::future::Future<Output = T> + Send>> + Send + 'static,
) -> T {
    let url = url.to_string();
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
    rt.block_on(async move {
        let (client, conn) = tokio_postgres::connect(&url, tokio_postgres::NoTls).await.unwrap();
        let h = tokio::spawn(conn);
        let out = f(client).await;
        h.abort();
        out
    })
}

/// The archived lines of a rig and test: seq → (t_ns, line).
fn archived(pg: &str, rig: &str, test: &str) -> BTreeMap<i64, (i64, serde_json::Value)> {
    let (rig, test) = (rig.to_string(), test.to_string());
    query(pg, move |c| {
        Box::pin(async move {
            let rows =
                c.query("SELECT seq, t_ns, line FROM feed_lines WHERE rig = $1 AND test = $2 ORDER BY seq", &[&rig, &test]).await.unwrap();
            let mut out = BTreeMap::new();
            for r in rows {
                let prev = out.insert(r.get::<_, i64>(0), (r.get::<_, i64>(1), r.get::<_, serde_json::Value>(2)));
                assert!(prev.is_none(), "feed_lines has a duplicate (rig, test, seq)");
            }
            out
        })
    })
}

fn count(pg: &str, sql: &'static str, test: &str) -> i64 {
    let test = test.to_string();
    query(pg, move |c| Box::pin(async move { c.query_one(sql, &[&test]).await.unwrap().get::<_, i64>(0) }))
}

/// Waits until the archive holds `n` lines of the test.
pub(crate) fn wait_rows(pg: &str, rig: &str, test: &str, n: usize, timeout: Duration) -> BTreeMap<i64, (i64, serde_json::Value)> {
    let until = Instant::now() + timeout;
    loop {
        let rows = archived(pg, rig, test);
        if rows.len() >= n || Instant::now() >= until {
            return rows;
        }
        std::thread::sleep(Duration::from_millis(200));
    }
}

/// Every archived line equals the feed line with its seq (as JSON values).
pub(crate) fn assert_rows_equal_feed(rows: &BTreeMap<i64, (i64, serde_json::Value)>, feed: &[serde_json::Value]) {
    let by_seq: BTreeMap<i64, &serde_json::Value> = feed.iter().map(|l| (l["seq"].as_i64().unwrap(), l)).collect();
    for (seq, (t_ns, line)) in rows {
        let f = by_seq.get(seq).unwrap_or_else(|| panic!("archived seq {seq} is not in the feed"));
        assert_eq!(line, *f, "archived line {seq} differs from the feed line");
        assert_eq!(Some(*t_ns), f["t_ns"].as_i64(), "t_ns of line {seq}");
    }
}

fn tag_count(feed: &[serde_json::Value]) -> i64 {
    feed.iter().map(|l| l["tags"].as_array().map_or(0, |t| t.len()) as i64).sum()
}

const TAG_ROWS: &str = "SELECT count(*) FROM tag_samples s JOIN tests t ON t.id = s.test_id WHERE t.name = $1";
const LINE_ROWS: &str = "SELECT count(*) FROM frame_sets f JOIN tests t ON t.id = f.test_id WHERE t.name = $1";

#[test]
fn demo_to_postgres_round_trip_and_a_malformed_message_is_skipped() {
    let dir = tempfile::tempdir().unwrap();
    let broker = LocalMosquitto::start().unwrap();
    let pg = LocalPostgres::start(false).unwrap();
    let alog = dir.path().join("archive.log");
    let mut archive = start_archive(&broker.url(), &pg.url(), "archive-rt", &alog);

    // Malformed messages first: not JSON, JSON that is no feed line, a bad gauge.
    {
        let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
        rt.block_on(async {
            let (c, mut el) = rumqttc::AsyncClient::new(rumqttc::MqttOptions::new("bad-rig", "127.0.0.1", broker.port()), 16);
            for p in [
                &b"{not json"[..],
                br#"{"seq": "x", "t_ns": 1, "tags": []}"#,
                br#"{"seq": 1, "t_ns": 1, "tags": [], "gauges": {"g": {"value": "big"}}}"#,
            ] {
                c.publish("tagdeflect/bad/t0/feed", rumqttc::QoS::AtLeastOnce, false, p.to_vec()).await.unwrap();
            }
            let mut acked = 0;
            while acked < 3 {
                if let rumqttc::Event::Incoming(rumqttc::Packet::PubAck(_)) = el.poll().await.unwrap() {
                    acked += 1;
                }
            }
        });
    }

    let (cfg, feed_path) = demo_config(dir.path(), &broker.url(), "frame-1", "rt", 10_000);
    let mut demo = start_demo(&cfg, 6.0, &dir.path().join("demo.log"));
    assert!(demo.wait(Duration::from_secs(60)).success(), "{}", fs::read_to_string(dir.path().join("demo.log")).unwrap());
    let feed = read_feed(&feed_path);
    assert!(feed.len() >= 20, "the demo made only {} lines", feed.len());
    assert!(tag_count(&feed) > 0, "the demo solved no tags");
    let rows = wait_rows(&pg.url(), "frame-1", "rt", feed.len(), Duration::from_secs(30));
    assert_eq!(rows.len(), feed.len(), "archived {} of {} lines", rows.len(), feed.len());
    assert_rows_equal_feed(&rows, &feed);
    assert_eq!(count(&pg.url(), TAG_ROWS, "rt"), tag_count(&feed), "tag samples");
    assert!(feed.iter().all(|l| l["mqtt_dropped"] == 0), "no line may be dropped with the broker up");

    let log = fs::read_to_string(&alog).unwrap();
    assert_eq!(log.matches("malformed message skipped").count(), 3, "{log}");
    assert!(archived(&pg.url(), "bad", "t0").is_empty());
    assert!(archive.alive(), "the archive stopped: {log}");
    // The retained status went through too and ended "offline".
    let state = query(&pg.url(), |c| {
        Box::pin(async move {
            c.query_one("SELECT status->>'state', status->>'rig' FROM tests WHERE name = 'rt'", &[])
                .await
                .map(|r| (r.get::<_, Option<String>>(0), r.get::<_, Option<String>>(1)))
                .unwrap()
        })
    });
    assert_eq!(state, (Some("offline".into()), Some("frame-1".into())));
    archive.kill();
}

pub(crate) fn logs_of(dir: &Path, files: &[&str]) -> String {
    files.iter().map(|f| format!("--- {f}\n{}", fs::read_to_string(dir.join(f)).unwrap_or_default())).collect()
}

/// Waits until the archive holds every line of the feed file and checks it holds each once,
/// equal to the feed line.
fn assert_converged(pg: &str, rig: &str, test: &str, feed_path: &Path, logs: impl Fn() -> String) -> usize {
    let feed = read_feed(feed_path);
    let rows = wait_rows(pg, rig, test, feed.len(), Duration::from_secs(40));
    let missing: Vec<i64> = feed.iter().map(|l| l["seq"].as_i64().unwrap()).filter(|s| !rows.contains_key(s)).collect();
    assert_eq!(rows.len(), feed.len(), "rig {rig}: archived {} of {} lines; missing {missing:?}\n{}", rows.len(), feed.len(), logs());
    assert_rows_equal_feed(&rows, &feed);
    feed.len()
}

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

/// The archive knows the lab's tests: a demo rig keeping tests (started and stopped by the
/// load, `[output.auto_test]`) publishes each test's record on `<topic>/labtest/<id>`; the
/// archive keeps it in `lab_tests` (specimen, events, the hashes of the stopped test's files:
/// test.json's own) and `lab_test_lines` holds every line of the test's folder. A record
/// forged onto another rig's topic is skipped.
#[test]
fn the_archive_keeps_each_lab_test_with_its_record_and_its_lines() {
    let dir = tempfile::tempdir().unwrap();
    let broker = LocalMosquitto::start().unwrap();
    let pg = LocalPostgres::start(false).unwrap();
    let alog = dir.path().join("archive.log");
    let mut archive = start_archive(&broker.url(), &pg.url(), "archive-lab", &alog);
    let (cfg, _) = demo_config(dir.path(), &broker.url(), "lab-1", "day", 10_000);
    let mut text = fs::read_to_string(&cfg).unwrap();
    text.push_str("\n[output.auto_test]\nstart_load_kn = 5.0\n");
    fs::write(&cfg, text).unwrap();
    let tests_dir = dir.path().join("tests");
    let log = dir.path().join("demo.log");
    let child = Command::new(bin())
        .args(["demo", "--http", "127.0.0.1:0", "--tests"])
        .arg(&tests_dir)
        .arg("--config")
        .arg(&cfg)
        .args(["--duration-s", "26"])
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(fs::File::create(&log).unwrap())
        .spawn()
        .unwrap();
    let mut demo = Proc { child, name: "demo" };
    // While it runs, the page and /metrics show the archive's lag of this rig.
    let until = Instant::now() + Duration::from_secs(30);
    let addr = loop {
        let text = fs::read_to_string(&log).unwrap_or_default();
        if let Some(a) = text.split("http://").nth(1).and_then(|r| r.split('/').next()).and_then(|a| a.parse::<std::net::SocketAddr>().ok())
        {
            break a;
        }
        assert!(Instant::now() < until && demo.alive(), "no page address in the demo's log:\n{text}");
        std::thread::sleep(Duration::from_millis(100));
    };
    let archive_seen = loop {
        let st: serde_json::Value = serde_json::from_str(&http_get(addr, "/api/status")).unwrap();
        if st["archive"]["heard"] == true {
            break st["archive"].clone();
        }
        assert!(Instant::now() < until, "the page never heard of the archive: {st}");
        std::thread::sleep(Duration::from_millis(200));
    };
    println!("archive on the page: {archive_seen}");
    assert_eq!(archive_seen["connected"], true);
    assert!(archive_seen["lag_lines"].as_u64().unwrap() < 100, "the archive keeps up: {archive_seen}");
    let metrics = http_get(addr, "/metrics");
    assert!(metrics.lines().any(|l| l.starts_with("tagdeflect_archive_lag_lines ")), "{metrics}");
    assert!(metrics.lines().any(|l| l.starts_with("tagdeflect_mqtt_connected 1")), "{metrics}");
    assert!(demo.wait(Duration::from_secs(90)).success(), "{}", fs::read_to_string(&log).unwrap());
    let logs = || logs_of(dir.path(), &["demo.log", "archive.log"]);
    // The stopped tests of the folder, with their records.
    let mut stopped: Vec<(serde_json::Value, usize)> = Vec::new();
    for e in fs::read_dir(&tests_dir).unwrap().flatten() {
        if let Ok(t) = fs::read_to_string(e.path().join("test.json")) {
            let lines = fs::read_to_string(e.path().join("feed.jsonl")).unwrap().lines().count();
            stopped.push((serde_json::from_str(&t).unwrap(), lines));
        }
    }
    assert!(!stopped.is_empty(), "no test started and stopped by itself in 26 s\n{}", logs());
    for (record, lines) in &stopped {
        let id = record["id"].as_str().unwrap().to_string();
        let until = Instant::now() + Duration::from_secs(30);
        let (row, held) = loop {
            let i = id.clone();
            let row = query(&pg.url(), move |c| {
                Box::pin(async move {
                    let r = c
                        .query_opt(
                            "SELECT lt.specimen, lt.stopped_t_ns, lt.events, lt.sha256, r.name, t.name,
                                    (SELECT count(*) FROM lab_test_lines l WHERE l.lab_test = lt.id AND l.rig = r.name)
                             FROM lab_tests lt JOIN rigs r ON r.id = lt.rig_id JOIN tests t ON t.id = lt.run_test_id WHERE lt.id = $1",
                            &[&i],
                        )
                        .await
                        .unwrap();
                    r.map(|r| {
                        let v: (String, Option<i64>, serde_json::Value, serde_json::Value, String, String) =
                            (r.get(0), r.get(1), r.get(2), r.get(3), r.get(4), r.get(5));
                        (v, r.get::<_, i64>(6))
                    })
                })
            });
            match row {
                Some((v, n)) if v.1.is_some() && n as usize >= *lines => break (v, n),
                _ if Instant::now() < until => std::thread::sleep(Duration::from_millis(200)),
                other => panic!("lab test {id} not archived whole within 30 s: {other:?} of {lines} lines\n{}", logs()),
            }
        };
        assert_eq!(row.0, "auto");
        assert_eq!(row.1, record["stopped_t_ns"].as_i64());
        assert_eq!(row.2, record["events"], "the events as in test.json");
        assert_eq!(row.3, record["sha256"], "the files' hashes as in test.json");
        assert_eq!((row.4.as_str(), row.5.as_str()), ("lab-1", "day"));
        assert_eq!(held as usize, *lines, "every line of the test's folder is in lab_test_lines");
        let kinds: Vec<&str> = record["events"].as_array().unwrap().iter().map(|e| e["kind"].as_str().unwrap()).collect();
        assert_eq!(kinds, ["start", "stop"], "{record}");
    }

    // A record forged onto another rig's topic: skipped, the archive goes on.
    let (record, _) = &stopped[0];
    let mut forged = record.clone();
    forged["rig"] = "lab-1".into();
    forged["test"] = "day".into();
    let topic = format!("tagdeflect/other/day/labtest/{}", record["id"].as_str().unwrap());
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
    rt.block_on(async {
        let (c, mut el) = rumqttc::AsyncClient::new(rumqttc::MqttOptions::new("forger", "127.0.0.1", broker.port()), 16);
        c.publish(topic, rumqttc::QoS::AtLeastOnce, false, serde_json::to_vec(&forged).unwrap()).await.unwrap();
        loop {
            if let rumqttc::Event::Incoming(rumqttc::Packet::PubAck(_)) = el.poll().await.unwrap() {
                break;
            }
        }
    });
    let until = Instant::now() + Duration::from_secs(20);
    while !fs::read_to_string(&alog).unwrap().contains("a lab test record with rig \"lab-1\" on the topic of rig \"other\"") {
        assert!(Instant::now() < until, "the forged record was not refused\n{}", logs());
        std::thread::sleep(Duration::from_millis(100));
    }
    let others = query(&pg.url(), |c| {
        Box::pin(async move {
            c.query_one("SELECT count(*) FROM lab_tests lt JOIN rigs r ON r.id = lt.rig_id WHERE r.name = 'other'", &[])
                .await
                .unwrap()
                .get::<_, i64>(0)
        })
    });
    assert_eq!(others, 0);
    assert!(archive.alive(), "{}", logs());
}

/// `archive backfill`: a rig that never reached the broker; the gap view and the gap log;
/// idempotent; a bad line is bad input naming file and line.
#[test]
fn backfill_loads_a_feed_file_once_and_the_gap_view_shows_what_is_missing() {
    let dir = tempfile::tempdir().unwrap();
    let pg = LocalPostgres::start(false).unwrap();
    // A rig whose broker is not there at all.
    let dead = format!("mqtt://127.0.0.1:{}", crate::common::unused_port());
    let (cfg, feed_path) = demo_config(dir.path(), &dead, "bf", "bf", 10_000);
    let mut demo = start_demo(&cfg, 4.0, &dir.path().join("demo.log"));
    assert!(demo.wait(Duration::from_secs(60)).success());
    let feed_text = fs::read_to_string(&feed_path).unwrap();
    let lines: Vec<&str> = feed_text.lines().collect();
    assert!(lines.len() >= 20, "only {} lines", lines.len());
    // First a file without seq 5..=9 and a partial last line, then the whole file.
    let holed = dir.path().join("holed.jsonl");
    let mut text: String = lines.iter().enumerate().filter(|(i, _)| !(5..=9).contains(i)).map(|(_, l)| format!("{l}\n")).collect();
    text.push_str("{\"seq\": 99, \"t_n");
    fs::write(&holed, text).unwrap();
    let backfill = |file: &Path| {
        Command::new(bin())
            .args(["archive", "backfill"])
            .arg(file)
            .args(["--rig", "bf", "--test", "bf", "--postgres", &pg.url()])
            .env("TAGDEFLECT_LOG", "info")
            .output()
            .unwrap()
    };
    let out = backfill(&holed);
    let err = String::from_utf8_lossy(&out.stderr).to_string();
    assert!(out.status.success(), "{err}");
    assert!(err.contains("partial last line skipped"), "{err}");
    // The hole: from after line 4 to before line 10 (frame sets the rig dropped have seqs too).
    let seq_of = |i: usize| serde_json::from_str::<serde_json::Value>(lines[i]).unwrap()["seq"].as_i64().unwrap();
    let (first, last) = (seq_of(4) + 1, seq_of(10) - 1);
    assert!(err.contains("gap opened") && err.contains(&format!("seq {first}..={last}")), "{err}");
    let gaps_of = |pg: String| {
        query(&pg, |c| {
            Box::pin(async move {
                c.query("SELECT first_seq, last_seq, missing FROM feed_gaps WHERE rig = 'bf' AND test = 'bf'", &[])
                    .await
                    .unwrap()
                    .iter()
                    .map(|r| (r.get::<_, i64>(0), r.get::<_, i64>(1), r.get::<_, i64>(2)))
                    .collect::<Vec<_>>()
            })
        })
    };
    // On a failure, the seqs and the rig's own drops of the lines say which hole the view saw.
    let seqs_and_drops: Vec<(i64, i64)> = lines
        .iter()
        .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap())
        .map(|v| (v["seq"].as_i64().unwrap(), v["dropped_sets"].as_i64().unwrap_or(-1)))
        .collect();
    assert_eq!(gaps_of(pg.url()), vec![(first, last, 5)], "feed_gaps; the feed's (seq, dropped_sets): {seqs_and_drops:?}");
    let out = backfill(&feed_path);
    let err = String::from_utf8_lossy(&out.stderr).to_string();
    let said = String::from_utf8_lossy(&out.stdout).to_string();
    assert!(out.status.success(), "{err}");
    assert!(said.contains(&format!("{} feed lines", lines.len())) && said.contains("5 stored"), "{said}");
    assert!(err.contains("gap filled"), "{err}");
    assert_eq!(gaps_of(pg.url()), vec![], "feed_gaps after the whole file");
    let rows = archived(&pg.url(), "bf", "bf");
    assert_rows_equal_feed(&rows, &read_feed(&feed_path));
    assert_eq!(rows.len(), lines.len());
    // Again: nothing new.
    let out = backfill(&feed_path);
    let said = String::from_utf8_lossy(&out.stdout).to_string();
    assert!(said.contains("0 stored") && said.contains(&format!("{} already held", lines.len())), "{said}");
    assert_eq!(archived(&pg.url(), "bf", "bf").len(), lines.len());
    // A bad line in the middle: exit 2, file and line named, nothing written.
    let bad = dir.path().join("bad.jsonl");
    fs::write(&bad, format!("{}\n{{\"seq\": 1}}\n{}\n", lines[0], lines[1])).unwrap();
    let out = backfill(&bad);
    let err = String::from_utf8_lossy(&out.stderr).to_string();
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(err.contains("bad.jsonl:2"), "{err}");
}

/// Messages the archive cannot take are malformed, never a stop: a 2 MB feed message at
/// QoS 1, a retained 1.1 MB status, a status claiming another rig; lines behind them are stored.
#[test]
fn oversized_and_forged_messages_are_skipped_and_the_archive_goes_on() {
    let dir = tempfile::tempdir().unwrap();
    let broker = LocalMosquitto::start().unwrap();
    let pg = LocalPostgres::start(false).unwrap();
    // Published before the archive starts: the retained status reaches even a fresh archive.
    {
        let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
        rt.block_on(async {
            let mut mo = rumqttc::MqttOptions::new("big-sender", "127.0.0.1", broker.port());
            mo.set_max_packet_size(4 << 20, 4 << 20);
            let (c, mut el) = rumqttc::AsyncClient::new(mo, 16);
            let big_status = format!("{{\"rig\": \"huge\", \"pad\": \"{}\"}}", "x".repeat(1_100_000));
            c.publish("tagdeflect/huge/t0/status", rumqttc::QoS::AtLeastOnce, true, big_status).await.unwrap();
            c.publish("tagdeflect/victim/t0/status", rumqttc::QoS::AtLeastOnce, true, r#"{"rig": "intruder", "state": "offline"}"#)
                .await
                .unwrap();
            let mut acked = 0;
            while acked < 2 {
                if let rumqttc::Event::Incoming(rumqttc::Packet::PubAck(_)) = el.poll().await.unwrap() {
                    acked += 1;
                }
            }
        });
    }
    let alog = dir.path().join("archive.log");
    let mut archive = start_archive(&broker.url(), &pg.url(), "archive-big", &alog);
    {
        let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
        rt.block_on(async {
            let mut mo = rumqttc::MqttOptions::new("big-feed", "127.0.0.1", broker.port());
            mo.set_max_packet_size(4 << 20, 4 << 20);
            let (c, mut el) = rumqttc::AsyncClient::new(mo, 16);
            let big = format!("{{\"seq\": 0, \"t_ns\": 1, \"tags\": [], \"pad\": \"{}\"}}", "y".repeat(2_000_000));
            c.publish("tagdeflect/huge/t0/feed", rumqttc::QoS::AtLeastOnce, false, big).await.unwrap();
            loop {
                if let rumqttc::Event::Incoming(rumqttc::Packet::PubAck(_)) = el.poll().await.unwrap() {
                    break;
                }
            }
        });
    }
    let (cfg, feed_path) = demo_config(dir.path(), &broker.url(), "after", "big", 10_000);
    let mut demo = start_demo(&cfg, 4.0, &dir.path().join("demo.log"));
    assert!(demo.wait(Duration::from_secs(60)).success());
    assert_converged(&pg.url(), "after", "big", &feed_path, || logs_of(dir.path(), &["demo.log", "archive.log"]));
    let log = fs::read_to_string(&alog).unwrap();
    assert!(log.matches("more than the 1048576 a feed line or status may have").count() >= 2, "{log}");
    assert!(log.contains("topic tagdeflect/victim/t0/status") && log.contains("\"intruder\""), "{log}");
    assert!(!log.contains("payload size limit exceeded"), "{log}");
    let victim = query(&pg.url(), |c| Box::pin(async move { c.query("SELECT 1 FROM tests WHERE name = 't0'", &[]).await.unwrap().len() }));
    assert_eq!(victim, 0, "nothing of the rejected messages is stored");
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

#[test]
fn broker_urls_topic_templates_and_config_errors() {
    use tagdeflect_wire::{check_level_name, check_topic_template, topic_for, BrokerUrl, Kind, TopicLayout};
    let u = BrokerUrl::parse("mqtt://127.0.0.1:1884").unwrap();
    assert_eq!((u.tls, u.host.as_str(), u.port), (false, "127.0.0.1", 1884));
    let u = BrokerUrl::parse("mqtts://user:pw@broker.lab").unwrap();
    assert_eq!((u.tls, u.port, u.username.as_deref(), u.password.as_deref()), (true, 8883, Some("user"), Some("pw")));
    assert!(BrokerUrl::parse("http://x").is_err());
    assert!(BrokerUrl::parse("mqtt://x:port").is_err());
    assert!(check_topic_template("lab/{test}/x/{rig}").is_ok());
    assert!(check_topic_template("tagdeflect/{rig}").is_err());
    assert!(check_topic_template("tagdeflect/{rig}-{test}").is_err());
    assert!(check_topic_template("tagdeflect/+/{rig}/{test}").is_err());
    assert!(check_level_name("rig", "frame/1").is_err());
    assert_eq!(topic_for("t/{rig}/{test}", "a", "b"), "t/a/b");

    let l = TopicLayout::new("lab/{test}/x/{rig}").unwrap();
    assert_eq!(l.filter(Kind::Feed), "lab/+/x/+/feed");
    assert_eq!(l.parse("lab/t1/x/r1/status"), Some(("r1".into(), "t1".into(), Kind::Status)));
    assert_eq!(l.parse("lab/t1/y/r1/feed"), None);
    assert_eq!(l.parse("lab/t1/x/r1/other"), None);
    assert_eq!(l.filter(Kind::LabTest), "lab/+/x/+/labtest/+");
    assert_eq!(l.parse_lab("lab/t1/x/r1/labtest/20261202T101500Z-B1"), Some(("r1".into(), "t1".into(), "20261202T101500Z-B1".into())));
    assert_eq!(l.parse_lab("lab/t1/x/r1/labtest/"), None);
    assert_eq!(l.parse_lab("lab/t1/x/r1/labtest"), None);
    assert_eq!(l.parse_lab("lab/t1/y/r1/labtest/a"), None);
    assert_eq!(l.parse("lab/t1/x/r1/labtest/a"), None);

    // Config errors name the file, the line and the key.
    let dir = tempfile::tempdir().unwrap();
    let base = tagdeflect::config::Config::demo().to_toml_string();
    for (extra, key, line_has) in [
        ("qos = 3", "output.mqtt.qos", "qos = 3"),
        ("topic = \"x/{rig}\"", "output.mqtt.topic", "topic ="),
        ("buffer_lines = 0", "output.mqtt.buffer_lines", "buffer_lines"),
        ("ca_file = \"missing.pem\"", "output.mqtt.url", "url ="),
    ] {
        let text = format!("{base}\n[output.mqtt]\nurl = \"mqtt://127.0.0.1:1883\"\nrig = \"r\"\n{extra}\n");
        let path = dir.path().join("c.toml");
        fs::write(&path, &text).unwrap();
        let e = tagdeflect::config::Config::load(&path).unwrap_err();
        assert_eq!(e.key.as_deref(), Some(key), "{e}");
        let line = text.lines().nth(e.line.unwrap() - 1).unwrap();
        assert!(line.contains(line_has), "{e}: line {line:?}");
    }
    // Accepted: every line published carries the same fields; the password is never written back.
    let text = format!("{base}\n[output.mqtt]\nurl = \"mqtt://u@127.0.0.1\"\nrig = \"r\"\npassword = \"secret\"\n");
    let path = dir.path().join("ok.toml");
    fs::write(&path, &text).unwrap();
    let c = tagdeflect::config::Config::load(&path).unwrap();
    assert_eq!(c.output.mqtt.as_ref().unwrap().password.as_deref(), Some("secret"));
    assert!(!c.to_toml_string().contains("secret"));
}

/// The broker ACLs of docs/archive.md, as written there (read from the page): with them a
/// rig's feed reaches the archive, and another rig can neither write over its status nor slip a
/// line into its feed — while that rig's own topics still work.
#[test]
fn the_documented_acls_let_each_rig_write_only_its_own_topics() {
    use std::os::unix::fs::PermissionsExt;
    let docs = fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("docs/archive.md")).unwrap();
    let acl: String = docs
        .lines()
        .skip_while(|l| !l.trim_start().starts_with("# every rig:"))
        .take_while(|l| !l.trim_start().starts_with("```"))
        .map(|l| format!("{}\n", l.trim()))
        .collect();
    assert!(acl.contains("pattern write tagdeflect/%u/+/feed") && acl.contains("user archive"), "the ACL block of the docs: {acl}");
    // Files the broker's own user can read.
    let auth = std::env::temp_dir().join(format!("tagdeflect-acl-{}-{:08x}", std::process::id(), rand::random::<u32>()));
    fs::create_dir_all(&auth).unwrap();
    fs::set_permissions(&auth, fs::Permissions::from_mode(0o755)).unwrap();
    let (acl_file, pw_file) = (auth.join("acl"), auth.join("passwd"));
    fs::write(&acl_file, &acl).unwrap();
    for (k, (user, pw)) in [("archive", "apw"), ("rig-a", "pa"), ("rig-b", "pb")].iter().enumerate() {
        let mut c = Command::new("mosquitto_passwd");
        if k == 0 {
            c.arg("-c");
        }
        let ok = c.args(["-b"]).arg(&pw_file).args([user, pw]).stdout(Stdio::null()).stderr(Stdio::null()).status().unwrap();
        assert!(ok.success(), "mosquitto_passwd for {user}");
    }
    for f in [&acl_file, &pw_file] {
        fs::set_permissions(f, fs::Permissions::from_mode(0o644)).unwrap();
    }
    let conf = format!("allow_anonymous false\npassword_file {}\nacl_file {}\n", pw_file.display(), acl_file.display());
    let broker = LocalMosquitto::start_configured(true, &conf).unwrap();
    let pg = LocalPostgres::start(false).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let alog = dir.path().join("archive.log");
    let port = broker.port();
    let mut archive = start_archive(&format!("mqtt://archive:apw@127.0.0.1:{port}"), &pg.url(), "archive-acl", &alog);
    let (cfg, feed_path) = demo_config(dir.path(), &format!("mqtt://rig-a:pa@127.0.0.1:{port}"), "rig-a", "t1", 10_000);
    let mut demo = start_demo(&cfg, 4.0, &dir.path().join("demo.log"));
    assert!(demo.wait(Duration::from_secs(60)).success());
    let feed = read_feed(&feed_path);
    let logs = || logs_of(dir.path(), &["demo.log", "archive.log"]);
    let rows = wait_rows(&pg.url(), "rig-a", "t1", feed.len(), Duration::from_secs(30));
    assert_eq!(rows.len(), feed.len(), "rig-a's own feed through the ACLs\n{}", logs());

    // rig-b forges rig-a's status and a line of its feed, then writes a line of its own.
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
    rt.block_on(async {
        let mut o = rumqttc::MqttOptions::new("forger", "127.0.0.1", port);
        o.set_credentials("rig-b", "pb");
        let (c, mut el) = rumqttc::AsyncClient::new(o, 16);
        let forged_status = br#"{"state":"forged","rig":"rig-a","test":"t1"}"#.to_vec();
        let line = |seq: u64| format!(r#"{{"seq":{seq},"t_ns":1700000000000000000,"tags":[]}}"#).into_bytes();
        c.publish("tagdeflect/rig-a/t1/status", rumqttc::QoS::AtLeastOnce, true, forged_status).await.unwrap();
        c.publish("tagdeflect/rig-a/t1/feed", rumqttc::QoS::AtLeastOnce, false, line(999_999)).await.unwrap();
        c.publish("tagdeflect/rig-b/t9/feed", rumqttc::QoS::AtLeastOnce, false, line(0)).await.unwrap();
        let mut acked = 0;
        while acked < 3 {
            if let rumqttc::Event::Incoming(rumqttc::Packet::PubAck(_)) = el.poll().await.unwrap() {
                acked += 1;
            }
        }
    });
    let own = wait_rows(&pg.url(), "rig-b", "t9", 1, Duration::from_secs(30));
    assert_eq!(own.len(), 1, "rig-b's own topic is open to it\n{}", logs());
    assert_eq!(archived(&pg.url(), "rig-a", "t1").len(), feed.len(), "no forged line in rig-a's feed");
    let state = query(&pg.url(), |c| {
        Box::pin(async move {
            c.query_one("SELECT status->>'state' FROM tests WHERE name = 't1'", &[]).await.map(|r| r.get::<_, Option<String>>(0)).unwrap()
        })
    });
    assert_eq!(state.as_deref(), Some("offline"), "rig-a's status as rig-a left it\n{}", logs());
    assert!(archive.alive());
    let _ = fs::remove_dir_all(&auth);
}

/// A burst through one archive — 4 rigs × 3000 lines published at full speed, the
/// `archive-bench` scenario that once deadlocked the archive (its connection waited for room
/// for the write loop, the write loop for the connection to take its acknowledgements, until
/// the broker dropped the silent connection; 4 of 7 runs stalled): every line is committed,
/// none twice. The bench's rate is printed, not asserted.
#[test]
fn a_burst_of_four_rigs_at_full_speed_is_committed_whole() {
    let o = Command::new(bin()).args(["archive-bench", "--rigs", "4", "--lines", "3000"]).stdin(Stdio::null()).output().unwrap();
    let out = String::from_utf8_lossy(&o.stdout);
    println!("{out}");
    assert!(o.status.success(), "{out}\n{}", String::from_utf8_lossy(&o.stderr));
    assert!(out.contains("all 12000 lines committed") && out.contains(", 0 duplicates)"), "{out}");
}

/// Publishes `(topic, payload)`s at QoS 1, retained, as a rig (or a forger) would, each acknowledged.
fn publish_all(port: u16, client: &str, messages: &[(String, Vec<u8>)]) {
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
    rt.block_on(async {
        let mut mo = rumqttc::MqttOptions::new(client, "127.0.0.1", port);
        mo.set_max_packet_size(4 << 20, 4 << 20);
        let (c, mut el) = rumqttc::AsyncClient::new(mo, 64);
        for (topic, payload) in messages {
            c.publish(topic.clone(), rumqttc::QoS::AtLeastOnce, true, payload.clone()).await.unwrap();
            loop {
                if let rumqttc::Event::Incoming(rumqttc::Packet::PubAck(_)) = el.poll().await.unwrap() {
                    break;
                }
            }
        }
    });
}

/// One set of limits for the control API and the archive (`core::limits`), and the archive's
/// rule for a test's versions keyed on its stop and time: a test whose specimen is 32 four-byte
/// letters with marks until the API refuses one (a record of ~250 KB) reaches `lab_tests` whole;
/// a forged record with more events published before and after the genuine stop record never
/// replaces it; an older version neither; each refused version is one log line naming the test.
#[test]
fn the_archive_takes_what_the_api_took_and_keeps_the_stop_record_against_forgeries() {
    use tagdeflect_core::lab_test::{TestMeta, TestRecord};
    use tagdeflect_sinks::lab_test::LabTests;
    let dir = tempfile::tempdir().unwrap();
    let broker = LocalMosquitto::start().unwrap();
    let pg = LocalPostgres::start(false).unwrap();
    let alog = dir.path().join("archive.log");
    let mut archive = start_archive(&broker.url(), &pg.url(), "archive-versions", &alog);
    // The records as the control API made them (the daemon's own lab tests, in-process).
    let tests = LabTests::new(&dir.path().join("tests"), String::new(), Vec::new(), None).unwrap();
    let records = std::sync::Arc::new(std::sync::Mutex::new(Vec::<TestRecord>::new()));
    let r = records.clone();
    tests.set_on_record(Box::new(move |rec: &TestRecord| r.lock().unwrap().push(rec.clone())));
    let mut meta = TestMeta { specimen: format!(" {}", "𝐁".repeat(32)), ..TestMeta::default() };
    meta.measured.insert("mass_kg".into(), 25.0);
    tests.start(meta).unwrap();
    let note = "\"".repeat(4000);
    while tests.mark(Some(note.clone())).is_ok() {}
    let stopped = tests.stop().unwrap();
    let all = records.lock().unwrap().clone();
    let (running, stop) = (all[all.len() - 2].clone(), all.last().unwrap().clone());
    assert!(stop.stopped_t_ns.is_some() && running.stopped_t_ns.is_none());
    assert_eq!(stop.id, stopped.id);
    let id = stop.id.clone();
    let topic = format!("tagdeflect/lab-v/day/labtest/{id}");
    let msg = |rec: &TestRecord| serde_json::to_vec(&tagdeflect_wire::LabTestMessage::from_record("lab-v", "day", rec)).unwrap();
    println!("the largest record the API let through: {} bytes, {} events", msg(&running).len(), running.events.len());
    assert!(msg(&running).len() > 200_000, "the marks filled the record");
    // A forgery: the running version with more (later) events.
    let mut forged = running.clone();
    for k in 0..5 {
        let t = stop.stopped_t_ns.unwrap() + 1_000_000_000 * (k + 1);
        forged.events.push(tagdeflect_core::feed::FeedEvent { kind: "mark".into(), t_ns: t, note: Some("forged".into()), user: None });
    }
    let first = all[0].clone();
    publish_all(
        broker.port(),
        "rig-and-forger",
        &[(topic.clone(), msg(&forged)), (topic.clone(), msg(&stop)), (topic.clone(), msg(&forged)), (topic.clone(), msg(&first))],
    );
    let held = || {
        let i = id.clone();
        query(&pg.url(), move |c| {
            Box::pin(async move {
                c.query_opt("SELECT stopped_t_ns, events, specimen FROM lab_tests WHERE id = $1", &[&i]).await.unwrap().map(|r| {
                    let v: (Option<i64>, serde_json::Value, String) = (r.get(0), r.get(1), r.get(2));
                    v
                })
            })
        })
    };
    let until = Instant::now() + Duration::from_secs(30);
    loop {
        let log = fs::read_to_string(&alog).unwrap();
        if log.matches(&format!("lab test {id} of rig lab-v: version refused")).count() >= 2 {
            break;
        }
        assert!(Instant::now() < until, "the refusals were not logged:\n{log}");
        std::thread::sleep(Duration::from_millis(100));
    }
    let (stopped_t_ns, events, specimen) = held().expect("the test reached lab_tests");
    assert_eq!(stopped_t_ns, stop.stopped_t_ns, "the genuine stop record is held");
    assert_eq!(events, serde_json::to_value(&stop.events).unwrap());
    assert_eq!(specimen, "𝐁".repeat(32), "trimmed");
    let log = fs::read_to_string(&alog).unwrap();
    assert!(log.contains("a running version") && log.contains("after the test's stop record"), "{log}");
    assert!(!log.contains("more than the"), "nothing the API took is too large: {log}");
    assert!(archive.alive());
}
