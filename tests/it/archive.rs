//! `demo` → Mosquitto → `archive` → PostgreSQL against the real servers (Debian's
//! `mosquitto` and `postgresql`, started here on loopback in temporary folders and stopped
//! by guards): the harness the archive's tests share, the round trip, a malformed message,
//! the backfill of a feed file, broker URLs and config errors, a burst of four rigs. The
//! outages (broker, archive, database) are in `archive_outages.rs`; what the archive takes
//! and whom it trusts (lab tests' records, forgeries, ACLs) in `archive_trust.rs`.

use std::collections::BTreeMap;
use std::fs;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use tagdeflect_archive::local::{LocalMosquitto, LocalPostgres};
use tagdeflect_sim::{SimParams, SimRig};

/// A child process killed (and reaped) when dropped.
pub(crate) struct Proc {
    pub(crate) child: Child,
    pub(crate) name: &'static str,
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
    pub(crate) fn kill(&mut self) {
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
pub(crate) fn http_get(addr: std::net::SocketAddr, path: &str) -> String {
    use std::io::{Read, Write};
    let mut s = std::net::TcpStream::connect_timeout(&addr, Duration::from_secs(5)).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    write!(s, "GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n").unwrap();
    let mut raw = String::new();
    s.read_to_string(&mut raw).unwrap();
    raw.split_once("\r\n\r\n").map(|(_, b)| b.to_string()).unwrap_or_default()
}

pub(crate) fn bin() -> &'static str {
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
pub(crate) fn demo_config(dir: &Path, broker: &str, rig: &str, test: &str, buffer: usize) -> (PathBuf, PathBuf) {
    demo_config_with(dir, broker, rig, test, buffer, true, 60)
}

/// [`demo_config`] with or without the feed file (without: the feed goes to the demo's
/// stdout, and the publisher has nothing to read lines back from) and `frame_sets` lines.
pub(crate) fn demo_config_with(
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
pub(crate) fn start_demo_to(config: &Path, seconds: f64, log: &Path, out: Option<&Path>) -> Proc {
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

pub(crate) fn read_feed(path: &Path) -> Vec<serde_json::Value> {
    fs::read_to_string(path).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect()
}

pub(crate) fn query<T: Send + 'static>(
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
pub(crate) fn archived(pg: &str, rig: &str, test: &str) -> BTreeMap<i64, (i64, serde_json::Value)> {
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

pub(crate) fn count(pg: &str, sql: &'static str, test: &str) -> i64 {
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

pub(crate) fn tag_count(feed: &[serde_json::Value]) -> i64 {
    feed.iter().map(|l| l["tags"].as_array().map_or(0, |t| t.len()) as i64).sum()
}

pub(crate) const TAG_ROWS: &str = "SELECT count(*) FROM tag_samples s JOIN tests t ON t.id = s.test_id WHERE t.name = $1";
pub(crate) const LINE_ROWS: &str = "SELECT count(*) FROM frame_sets f JOIN tests t ON t.id = f.test_id WHERE t.name = $1";

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
pub(crate) fn assert_converged(pg: &str, rig: &str, test: &str, feed_path: &Path, logs: impl Fn() -> String) -> usize {
    let feed = read_feed(feed_path);
    let rows = wait_rows(pg, rig, test, feed.len(), Duration::from_secs(40));
    let missing: Vec<i64> = feed.iter().map(|l| l["seq"].as_i64().unwrap()).filter(|s| !rows.contains_key(s)).collect();
    assert_eq!(rows.len(), feed.len(), "rig {rig}: archived {} of {} lines; missing {missing:?}\n{}", rows.len(), feed.len(), logs());
    assert_rows_equal_feed(&rows, &feed);
    feed.len()
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
pub(crate) fn publish_all(port: u16, client: &str, messages: &[(String, Vec<u8>)]) {
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
