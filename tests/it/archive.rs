//! `demo` → Mosquitto → `archive` → PostgreSQL against the real servers (Debian's
//! `mosquitto` and `postgresql`, started here on loopback in temporary folders and stopped
//! by guards): the round trip, a malformed message, and the three outages (broker, archive,
//! database).

use std::collections::BTreeMap;
use std::fs;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use tagdeflect::archive::local::{LocalMosquitto, LocalPostgres};
use tagdeflect::sim::{SimParams, SimRig};

/// A child process killed (and reaped) when dropped.
struct Proc {
    child: Child,
    name: &'static str,
}

impl Proc {
    fn alive(&mut self) -> bool {
        matches!(self.child.try_wait(), Ok(None))
    }
    /// Waits for the process to end by itself; panics after `timeout`.
    fn wait(&mut self, timeout: Duration) -> std::process::ExitStatus {
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

fn bin() -> &'static str {
    env!("CARGO_BIN_EXE_tagdeflect")
}

/// Starts `tagdeflect archive` logging into `log`.
fn start_archive(broker: &str, pg: &str, client_id: &str, log: &Path) -> Proc {
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
    // Ready once subscribed: messages published before would not reach its session.
    let until = Instant::now() + Duration::from_secs(30);
    loop {
        let text = fs::read_to_string(log).unwrap_or_default().get(skip..).unwrap_or_default().to_string();
        if text.matches("archive: subscribed").count() >= 2 {
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
    let params =
        SimParams { cameras: 1, width: 480, height: 360, fps: 10.0, frame_sets: 60, rest_frames: 5, subsamples: 2, ..SimParams::default() };
    let mut config = tagdeflect::config::Config::from_sim(&SimRig::new(&params).unwrap());
    config.utm = tagdeflect::config::Config::demo().utm;
    let feed = dir.join(format!("{rig}.jsonl"));
    config.output.feed = Some(feed.display().to_string());
    let mut text = config.to_toml_string();
    text.push_str(&format!(
        "\n[output.mqtt]\nurl = \"{broker}\"\nrig = \"{rig}\"\ntest = \"{test}\"\nbuffer_lines = {buffer}\nstatus_interval_s = 1.0\n"
    ));
    let path = dir.join(format!("{rig}.toml"));
    fs::write(&path, text).unwrap();
    (path, feed)
}

fn start_demo(config: &Path, seconds: f64, log: &Path) -> Proc {
    let child = Command::new(bin())
        .args(["demo", "--config"])
        .arg(config)
        .args(["--duration-s", &seconds.to_string()])
        .stdin(Stdio::null())
        .stdout(Stdio::null())
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
fn wait_rows(pg: &str, rig: &str, test: &str, n: usize, timeout: Duration) -> BTreeMap<i64, (i64, serde_json::Value)> {
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
fn assert_rows_equal_feed(rows: &BTreeMap<i64, (i64, serde_json::Value)>, feed: &[serde_json::Value]) {
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

#[test]
fn broker_down_for_10_s_loses_nothing_within_the_buffer_and_counts_the_drops() {
    let dir = tempfile::tempdir().unwrap();
    let mut broker = LocalMosquitto::start().unwrap();
    let pg = LocalPostgres::start(false).unwrap();
    let mut archive = start_archive(&broker.url(), &pg.url(), "archive-bo", &dir.path().join("archive.log"));
    // Rig "big" buffers 10 000 lines (the outage fits), rig "small" 15 (it does not).
    let (cfg_big, feed_big) = demo_config(dir.path(), &broker.url(), "big", "bo", 10_000);
    let (cfg_small, feed_small) = demo_config(dir.path(), &broker.url(), "small", "bo", 15);
    let mut big = start_demo(&cfg_big, 22.0, &dir.path().join("big.log"));
    let mut small = start_demo(&cfg_small, 22.0, &dir.path().join("small.log"));
    std::thread::sleep(Duration::from_secs(5));
    broker.stop();
    std::thread::sleep(Duration::from_secs(10));
    broker.start_again().unwrap();
    assert!(big.wait(Duration::from_secs(60)).success(), "{}", fs::read_to_string(dir.path().join("big.log")).unwrap());
    assert!(small.wait(Duration::from_secs(60)).success(), "{}", fs::read_to_string(dir.path().join("small.log")).unwrap());

    let feed = read_feed(&feed_big);
    let rows = wait_rows(&pg.url(), "big", "bo", feed.len(), Duration::from_secs(30));
    assert_eq!(feed.last().unwrap()["mqtt_dropped"], 0, "the big buffer held the whole outage");
    let logs = || {
        ["big.log", "small.log", "archive.log"]
            .iter()
            .map(|f| format!("--- {f}\n{}", fs::read_to_string(dir.path().join(f)).unwrap_or_default()))
            .collect::<String>()
    };
    assert_eq!(rows.len(), feed.len(), "rig big: archived {} of {} lines\n{}", rows.len(), feed.len(), logs());
    assert_rows_equal_feed(&rows, &feed);

    let feed = read_feed(&feed_small);
    let dropped = feed.last().unwrap()["mqtt_dropped"].as_u64().unwrap() as usize;
    // ~100 lines made during the outage, 15 kept.
    assert!(dropped >= 50, "only {dropped} lines dropped from a 15-line buffer during a 10 s outage");
    // A dropped line was never acknowledged, but one on its way when the broker stopped
    // (sent, its acknowledgement not yet back) may have reached it: `mqtt_dropped` bounds
    // the loss from above, by at most the lines in flight (on loopback at ~10 lines/s, one
    // or two).
    const IN_FLIGHT: usize = 2;
    let rows = wait_rows(&pg.url(), "small", "bo", feed.len() - dropped, Duration::from_secs(30));
    std::thread::sleep(Duration::from_millis(500));
    let rows_again = archived(&pg.url(), "small", "bo");
    assert_eq!(rows.len(), rows_again.len(), "more lines arrived than the feed says were kept");
    assert!(
        rows.len() + dropped >= feed.len() && rows.len() + dropped <= feed.len() + IN_FLIGHT,
        "rig small: {} archived + {dropped} dropped vs {} made\n{}",
        rows.len(),
        feed.len(),
        logs()
    );
    assert_rows_equal_feed(&rows, &feed);
    // What is missing is one run of consecutive lines: the oldest of the outage.
    let missing: Vec<i64> = feed.iter().map(|l| l["seq"].as_i64().unwrap()).filter(|s| !rows.contains_key(s)).collect();
    assert_eq!(missing.len(), feed.len() - rows.len());
    // Where the feed counted its drops (the seq of each line whose making dropped one).
    let drops_at: Vec<i64> =
        feed.windows(2).filter(|w| w[1]["mqtt_dropped"] != w[0]["mqtt_dropped"]).map(|w| w[1]["seq"].as_i64().unwrap()).collect();
    assert_eq!(
        missing.last().unwrap() - missing[0] + 1,
        missing.len() as i64,
        "missing lines are not consecutive: {missing:?}; drops counted at {drops_at:?}\n{}",
        logs()
    );
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
    std::thread::sleep(Duration::from_secs(4));
    let before = archived(&pg.url(), "frame-2", "ar").len();
    assert!(before > 0, "nothing archived in 4 s");
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
    std::thread::sleep(Duration::from_secs(3));
    pg.stop().unwrap();
    std::thread::sleep(Duration::from_secs(10));
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
    use tagdeflect::archive::{Kind, TopicLayout};
    use tagdeflect::sinks::mqtt::{check_level_name, check_topic_template, topic_for, BrokerUrl};
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
