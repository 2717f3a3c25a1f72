//! Users, roles, the audit log and sign-off (issue "the test a lab signs", item 5) on a real
//! daemon over HTTP: users made by `tagdeflect user add`, each token with its role (401 for an
//! unknown token, 403 naming the role needed), a day's actions appended to the tests folder's
//! hash-chained `audit.jsonl` and verified, a report signed by a reviewer and linked to
//! report.json's hash, a re-analysis with its reason, a log edited by hand caught; without a
//! users file the one shared token works as before and is logged as `shared-token`.

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

use sha2::Digest;
use tagdeflect_core::audit::{verify_chain, AuditEntry, ChainBroken};

use crate::http::{demo_with_tests, get, post, rig_config, Daemon};

fn sha256_file(path: &Path) -> String {
    tagdeflect_core::audit::hex(&sha2::Sha256::digest(std::fs::read(path).unwrap()))
}

/// `tagdeflect user ARGS`: stdout, asserting success.
fn user(args: &[&str]) -> String {
    let o = Command::new(env!("CARGO_BIN_EXE_tagdeflect")).arg("user").args(args).output().unwrap();
    assert!(o.status.success(), "tagdeflect user {args:?}: {}", String::from_utf8_lossy(&o.stderr));
    String::from_utf8(o.stdout).unwrap()
}

/// A POST with `token` (JSON body): status and the answer as JSON.
fn post_as(addr: SocketAddr, token: &str, cmd: &str, body: serde_json::Value) -> (u16, serde_json::Value) {
    let bearer = format!("Bearer {token}");
    let (code, text) = post(
        addr,
        &format!("/api/test/{cmd}"),
        &[("Content-Type", "application/json"), ("Authorization", &bearer)],
        body.to_string().as_bytes(),
    );
    (code, serde_json::from_str(&text).unwrap_or_else(|e| panic!("{cmd}: {e}: {text}")))
}

/// `GET /api/audit?test=ID` with `token` (or none): status and body.
fn get_audit(addr: SocketAddr, token: Option<&str>, test: &str) -> (u16, serde_json::Value) {
    let mut s = TcpStream::connect_timeout(&addr, Duration::from_secs(5)).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(30))).unwrap();
    let auth = token.map(|t| format!("Authorization: Bearer {t}\r\n")).unwrap_or_default();
    write!(s, "GET /api/audit?test={test} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n{auth}\r\n").unwrap();
    let mut raw = String::new();
    s.read_to_string(&mut raw).unwrap();
    let code = raw.split_whitespace().nth(1).and_then(|c| c.parse().ok()).unwrap();
    (code, serde_json::from_str(raw.split("\r\n\r\n").nth(1).unwrap()).unwrap())
}

/// The audit log's entries.
fn entries(tests: &Path) -> Vec<AuditEntry> {
    std::fs::read_to_string(tests.join("audit.jsonl")).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect()
}

/// Waits until the daemon has written `n` more feed lines.
fn some_lines(d: &Daemon, n: usize) {
    d.wait_lines(d.lines().len() + n, Duration::from_secs(120));
}

/// A day with two users of two roles: an operator starts, marks and stops a C1609 test; a
/// reviewer may not start (403 naming the role), reads the trail, signs the report (linked to
/// report.json's hash and to its audit line) and asks a re-analysis; an operator may not sign;
/// an unknown token is 401. The log verifies; edited by hand, it is caught at the edited line.
#[test]
fn two_users_of_two_roles_an_audited_day_and_a_signed_report() {
    let dir = tempfile::tempdir().unwrap();
    let tests_dir = dir.path().join("tests");
    let users_file = dir.path().join("users.toml");
    let uf = users_file.to_str().unwrap();
    let td = tests_dir.to_str().unwrap();
    std::fs::create_dir_all(&tests_dir).unwrap();
    let ana = user(&["add", "ana", "--role", "operator", "--users-file", uf, "--tests", td]).trim().to_string();
    let rui = user(&["add", "rui", "--role", "reviewer", "--users-file", uf, "--tests", td]).trim().to_string();
    assert_eq!((ana.len(), rui.len()), (64, 64), "32 random bytes in hex");
    use std::os::unix::fs::PermissionsExt;
    assert_eq!(std::fs::metadata(&users_file).unwrap().permissions().mode() & 0o777, 0o600);
    let stored = std::fs::read_to_string(&users_file).unwrap();
    assert!(!stored.contains(&ana) && stored.contains(&tagdeflect_core::users::token_sha256(&ana)), "only the token's hash: {stored}");
    assert_eq!(user(&["list", "--users-file", uf]), "ana\toperator\nrui\treviewer\n");

    let cfg = rig_config(dir.path(), None);
    let mut table: toml::Table = std::fs::read_to_string(&cfg).unwrap().parse().unwrap();
    let output = table.entry("output").or_insert(toml::Value::Table(Default::default())).as_table_mut().unwrap();
    output.insert("users_file".into(), toml::Value::String("users.toml".into()));
    std::fs::write(&cfg, toml::to_string(&table).unwrap()).unwrap();
    let mut d = Daemon::start(&["demo", "--config", cfg.to_str().unwrap(), "--http", "127.0.0.1:0", "--tests", td]);
    let addr = d.addr();
    assert!(!tests_dir.join(".token").exists(), "no shared token with a users file");

    let start = serde_json::json!({"specimen": "B1", "operator": "ana", "standard": "astm-c1609"});
    assert_eq!(post_as(addr, &"0".repeat(64), "start", start.clone()).0, 401, "an unknown token");
    let (code, answer) = post_as(addr, &rui, "start", start.clone());
    assert_eq!(code, 403, "{answer}");
    assert!(answer["error"].as_str().unwrap().contains("start needs the role operator or admin"), "{answer}");
    let (code, st) = post_as(addr, &ana, "start", start);
    assert_eq!(code, 200, "{st}");
    let id = st["id"].as_str().unwrap().to_string();
    some_lines(&d, 20);
    assert_eq!(post_as(addr, &ana, "mark", serde_json::json!({"note": "first crack seen"})).0, 200);
    some_lines(&d, 40);
    let (code, stopped) = post_as(addr, &ana, "stop", serde_json::json!({}));
    assert_eq!(code, 200, "{stopped}");
    let folder = PathBuf::from(stopped["folder"].as_str().unwrap());
    let record: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(folder.join("test.json")).unwrap()).unwrap();
    let by: Vec<(&str, &str)> =
        record["events"].as_array().unwrap().iter().map(|e| (e["kind"].as_str().unwrap(), e["user"].as_str().unwrap_or("-"))).collect();
    assert_eq!(by, [("start", "ana"), ("mark", "ana"), ("stop", "ana")], "each event names its user");
    assert!(folder.join("report/report.json").is_file(), "the C1609 report made at stop");

    // The trail: a token of any role reads it; none gets 401.
    assert_eq!(get_audit(addr, None, &id).0, 401);
    let (code, trail) = get_audit(addr, Some(&rui), &id);
    assert_eq!(code, 200, "{trail}");
    assert_eq!(trail["chain"]["ok"], true, "{trail}");
    let actions: Vec<&str> = trail["entries"].as_array().unwrap().iter().map(|e| e["action"].as_str().unwrap()).collect();
    assert_eq!(actions, ["start", "mark", "stop"], "{trail}");
    assert_eq!(trail["entries"][2]["detail"]["test_json_sha256"], sha256_file(&folder.join("test.json")).as_str());
    assert_eq!(get(addr, "/api/test").0, 200, "the page's GET needs no token");

    // Sign-off: not by an operator; by the reviewer, linked to report.json's hash.
    let sign = serde_json::json!({"test": id, "meaning": "reviewed and approved"});
    let (code, answer) = post_as(addr, &ana, "sign", sign.clone());
    assert_eq!(code, 403, "{answer}");
    assert!(answer["error"].as_str().unwrap().contains("sign needs the role reviewer or admin"), "{answer}");
    let (code, sig) = post_as(addr, &rui, "sign", sign.clone());
    assert_eq!(code, 200, "{sig}");
    let report_sha = sha256_file(&folder.join("report/report.json"));
    let lines = std::fs::read_to_string(folder.join("signatures.jsonl")).unwrap();
    let written: serde_json::Value = serde_json::from_str(lines.lines().next().unwrap()).unwrap();
    assert_eq!(written, sig);
    assert_eq!((written["by"].as_str(), written["role"].as_str()), (Some("rui"), Some("reviewer")));
    assert_eq!(written["report_json_sha256"], report_sha.as_str());
    let log = entries(&tests_dir);
    let sign_entry = &log[written["audit_seq"].as_u64().unwrap() as usize];
    assert_eq!((sign_entry.action.as_str(), sign_entry.detail["report_json_sha256"].as_str()), ("sign", Some(report_sha.as_str())));

    // A re-analysis keeps the previous report and names its reason; a report.json edited since
    // test.json hashed it cannot be signed.
    let (code, re) = post_as(addr, &rui, "reanalyse", serde_json::json!({"test": id, "reason": "span re-measured"}));
    assert_eq!(code, 200, "{re}");
    assert!(folder.join("report.prev-1/report.json").is_file() && folder.join("report/report.json").is_file(), "{re}");
    assert_eq!(entries(&tests_dir).last().unwrap().detail["reason"], "span re-measured");
    let mut report = std::fs::read_to_string(folder.join("report/report.json")).unwrap();
    report.push(' ');
    std::fs::write(folder.join("report/report.json"), report).unwrap();
    let (code, answer) = post_as(addr, &rui, "sign", sign);
    assert_eq!(code, 409, "{answer}");
    assert!(answer["error"].as_str().unwrap().contains("changed since test.json hashed it"), "{answer}");
    assert_eq!(d.stop(), Some(0));

    // The day's log: 2 users, start, mark, stop, sign, reanalysis; chained and verified.
    let log = entries(&tests_dir);
    let actions: Vec<(&str, &str, &str)> = log.iter().map(|e| (e.action.as_str(), e.user.as_str(), e.role.as_str())).collect();
    let me = std::env::var("USER").unwrap_or_else(|_| "unknown".into());
    let me = if me.is_empty() { "unknown" } else { me.as_str() };
    assert_eq!(
        actions,
        [
            ("user", me, "admin"),
            ("user", me, "admin"),
            ("start", "ana", "operator"),
            ("mark", "ana", "operator"),
            ("stop", "ana", "operator"),
            ("sign", "rui", "reviewer"),
            ("reanalysis", "rui", "reviewer")
        ]
    );
    let path = tests_dir.join("audit.jsonl");
    assert_eq!(verify_chain(&path).unwrap().entries, 7);
    // Edited by hand: the mark made by someone else. Caught at its line.
    let text = std::fs::read_to_string(&path).unwrap();
    let edited: Vec<String> = text
        .lines()
        .enumerate()
        .map(|(i, l)| if i == 3 { l.replace("\"user\":\"ana\"", "\"user\":\"eve\"") } else { l.to_string() })
        .collect();
    std::fs::write(&path, edited.join("\n") + "\n").unwrap();
    let broken = verify_chain(&path).unwrap_err();
    assert!(matches!(broken, ChainBroken::HashMismatch { line: 4, .. }), "{broken}");
}

/// Without a users file the one shared token works as before (SPEC "Tests") and its actions
/// are logged as user `shared-token`, role `admin` (who may sign as well).
#[test]
fn the_shared_token_works_without_a_users_file_and_is_logged_as_such() {
    let dir = tempfile::tempdir().unwrap();
    let tests_dir = dir.path().join("tests");
    let cfg = rig_config(dir.path(), None);
    let (mut d, addr, token) = demo_with_tests(Some(&cfg), &tests_dir, &[]);
    assert_eq!(post_as(addr, "wrong-token-0123456789", "zero", serde_json::json!({})).0, 401);
    let (code, st) = post_as(addr, &token, "start", serde_json::json!({"specimen": "S1", "standard": "astm-c1609"}));
    assert_eq!(code, 200, "{st}");
    let id = st["id"].as_str().unwrap().to_string();
    some_lines(&d, 30);
    assert_eq!(post_as(addr, &token, "zero", serde_json::json!({})).0, 200);
    some_lines(&d, 45);
    let (code, stopped) = post_as(addr, &token, "stop", serde_json::json!({}));
    assert_eq!(code, 200, "{stopped}");
    let (code, sig) = post_as(addr, &token, "sign", serde_json::json!({"test": id, "meaning": "approved"}));
    assert_eq!(code, 200, "{sig}");
    assert_eq!(d.stop(), Some(0));
    let log = entries(&tests_dir);
    let actions: Vec<(&str, &str, &str)> = log.iter().map(|e| (e.action.as_str(), e.user.as_str(), e.role.as_str())).collect();
    assert_eq!(
        actions,
        [
            ("start", "shared-token", "admin"),
            ("zero", "shared-token", "admin"),
            ("stop", "shared-token", "admin"),
            ("sign", "shared-token", "admin")
        ]
    );
    assert!(log.iter().all(|e| e.test.as_deref() == Some(id.as_str())));
    assert_eq!(verify_chain(&tests_dir.join("audit.jsonl")).unwrap().entries, 4);
}
