//! What the archive takes and whom it trusts (real `mosquitto` and `postgresql`, harness in
//! `archive.rs`): each lab test kept with its record and its lines, what the control API took
//! and the stop record against forgeries, oversized and forged messages skipped, the
//! documented ACLs keeping each rig to its own topics.

use std::fs;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use crate::archive::{
    archived, assert_converged, bin, demo_config, http_get, logs_of, publish_all, query, read_feed, start_archive, start_demo, wait_rows,
    Proc,
};
use tagdeflect_archive::local::{LocalMosquitto, LocalPostgres};

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
