//! `[output] http_token_file` that every user of the machine may read: `check --config` and
//! the daemon's start each say so, naming the file and its mode (docs/operations.md, "The
//! live page and the control API"); a file the lab's group may read (0640) is not warned of.

use std::os::unix::fs::PermissionsExt;
use std::process::Command;
use std::time::Duration;

use crate::http::{small_rig, Daemon};
use tagdeflect::config::Config;
use tagdeflect_sim::SimRig;

const WARNING: &str = "lets every user of this machine read (or write) the control token";

/// `check --config` on the rig's config: exit code and stdout.
fn check(cfg: &std::path::Path) -> (Option<i32>, String) {
    let o =
        Command::new(env!("CARGO_BIN_EXE_tagdeflect")).args(["check", "--config"]).arg(cfg).env("TAGDEFLECT_LOG", "warn").output().unwrap();
    (o.status.code(), format!("{}\n{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr)))
}

#[test]
fn a_token_file_every_user_may_read_is_warned_of_by_check_and_at_the_start() {
    let dir = tempfile::tempdir().unwrap();
    let token_file = dir.path().join("control.token");
    std::fs::write(&token_file, "0123456789abcdef0123456789abcdef\n").unwrap();
    std::fs::set_permissions(&token_file, std::fs::Permissions::from_mode(0o644)).unwrap();
    let mut cfg: Config = Config::from_sim(&SimRig::new(&small_rig()).unwrap());
    cfg.utm = Config::demo().utm;
    cfg.output.http_token_file = Some(token_file.clone());
    let cfg_path = dir.path().join("rig.toml");
    std::fs::write(&cfg_path, cfg.to_toml_string()).unwrap();
    let named = format!("http_token_file {}: mode 0644 {WARNING}", token_file.display());

    // `check`: a warning (the config is fine; exit 0), naming the file and its mode.
    let (code, out) = check(&cfg_path);
    assert_eq!(code, Some(0), "{out}");
    assert!(out.contains(&format!("warning: [output] {named}")), "{out}");

    // The daemon's start: the same warning in its log, and it starts (the token is taken).
    let tests_dir = dir.path().join("tests");
    let mut d =
        Daemon::start(&["demo", "--config", cfg_path.to_str().unwrap(), "--http", "127.0.0.1:0", "--tests", tests_dir.to_str().unwrap()]);
    d.addr();
    d.wait_stderr(&named, Duration::from_secs(60), "the token file's warning at the start");
    assert_eq!(d.stop(), Some(0));

    // Read by the lab's group only: no warning from either.
    std::fs::set_permissions(&token_file, std::fs::Permissions::from_mode(0o640)).unwrap();
    let (code, out) = check(&cfg_path);
    assert_eq!(code, Some(0), "{out}");
    assert!(!out.contains(WARNING), "{out}");
    let mut d =
        Daemon::start(&["demo", "--config", cfg_path.to_str().unwrap(), "--http", "127.0.0.1:0", "--tests", tests_dir.to_str().unwrap()]);
    d.addr();
    d.wait_stderr("control API", Duration::from_secs(60), "the control API's line");
    assert_eq!(d.stop(), Some(0));
    assert!(!d.stderr.lock().unwrap().contains(WARNING), "{}", d.stderr.lock().unwrap());
}
