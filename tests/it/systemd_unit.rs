//! The systemd unit `systemd/tagdeflect.service`: verified clean by `systemd-analyze verify`
//! (which exits 0 on unknown keys and only warns on stderr, so any stderr line about our
//! unit fails the test), checked for the directives the daemon relies on, and scored by
//! `systemd-analyze security --offline=true` (the exposure score is printed and bounded).

use std::path::{Path, PathBuf};
use std::process::Command;

const INSTALLED_BIN: &str = "/usr/local/bin/tagdeflect";

fn unit_text() -> String {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("systemd/tagdeflect.service");
    std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("cannot read {}: {e}", path.display()))
}

fn systemd_analyze(args: &[&str]) -> std::process::Output {
    Command::new("systemd-analyze")
        .args(args)
        .output()
        .unwrap_or_else(|e| panic!("cannot run systemd-analyze ({e}): install systemd (run scripts/setup.sh)"))
}

/// A copy of the unit whose ExecStart runs the freshly built binary (verify needs it to exist).
fn unit_copy(dir: &Path, extra_service_line: Option<&str>) -> PathBuf {
    let bin = env!("CARGO_BIN_EXE_tagdeflect");
    let mut text = unit_text().replace(&format!("ExecStart={INSTALLED_BIN} "), &format!("ExecStart={bin} "));
    assert!(text.contains(&format!("ExecStart={bin} run --config /etc/tagdeflect/tagdeflect.toml")), "ExecStart not as expected");
    if let Some(line) = extra_service_line {
        text = text.replace("[Service]\n", &format!("[Service]\n{line}\n"));
    }
    let path = dir.join("tagdeflect.service");
    std::fs::write(&path, text).expect("write unit copy");
    path
}

/// Lines of `systemd-analyze verify` output about our unit.
fn verify_complaints(unit: &Path) -> (Vec<String>, Vec<String>) {
    verify_complaints_with_path(unit, None)
}

/// As [`verify_complaints`], with `extra_path` first on `PATH` (to stand in for a machine
/// whose tools differ).
fn verify_complaints_with_path(unit: &Path, extra_path: Option<&Path>) -> (Vec<String>, Vec<String>) {
    // `--man=no`: verify otherwise checks that the unit's `Documentation=` man pages exist,
    // which fails on a machine without `man` (a minimal Debian) and is not about the unit.
    let mut cmd = Command::new("systemd-analyze");
    cmd.args(["verify", "--man=no", unit.to_str().expect("utf-8 path")]);
    if let Some(dir) = extra_path {
        cmd.env("PATH", format!("{}:{}", dir.display(), std::env::var("PATH").unwrap_or_default()));
    }
    let out = cmd.output().unwrap_or_else(|e| panic!("cannot run systemd-analyze ({e}): install systemd (run scripts/setup.sh)"));
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned() + &String::from_utf8_lossy(&out.stdout);
    let (ours, other): (Vec<String>, Vec<String>) =
        stderr.lines().filter(|l| !l.trim().is_empty()).map(str::to_string).partition(|l| l.contains("tagdeflect"));
    assert!(out.status.success() || !ours.is_empty(), "systemd-analyze verify failed without a message: {:?}", out.status);
    (ours, other)
}

#[test]
fn unit_verifies_without_any_warning() {
    let dir = tempfile::tempdir().expect("temp dir");
    let unit = unit_copy(dir.path(), None);
    let (ours, other) = verify_complaints(&unit);
    for l in &other {
        println!("(not about our unit) {l}");
    }
    assert!(ours.is_empty(), "systemd-analyze verify complains about the unit:\n{}", ours.join("\n"));
}

#[test]
fn unit_verifies_on_a_machine_without_man_pages() {
    // A minimal Debian has no `man`: there, `verify` used to print "Command 'man
    // systemd.exec(5)' failed with code 1" for our unit. A `man` that always fails stands in.
    let dir = tempfile::tempdir().expect("temp dir");
    let bin = dir.path().join("bin");
    std::fs::create_dir(&bin).expect("bin dir");
    let man = bin.join("man");
    std::fs::write(&man, "#!/bin/sh\nexit 1\n").expect("write fake man");
    std::fs::set_permissions(&man, std::os::unix::fs::PermissionsExt::from_mode(0o755)).expect("chmod");
    let unit = unit_copy(dir.path(), None);
    let (ours, _) = verify_complaints_with_path(&unit, Some(&bin));
    assert!(ours.is_empty(), "systemd-analyze verify complains without man pages:\n{}", ours.join("\n"));
}

#[test]
fn verify_check_catches_a_bad_key() {
    // The test above must be able to fail: an unknown key only warns (exit 0).
    let dir = tempfile::tempdir().expect("temp dir");
    let unit = unit_copy(dir.path(), Some("NoSuchSetting=yes"));
    let (ours, _) = verify_complaints(&unit);
    println!("{}", ours.join("\n"));
    assert!(ours.iter().any(|l| l.contains("NoSuchSetting")), "an unknown key went unnoticed: {ours:?}");
}

#[test]
fn unit_has_the_directives_the_daemon_relies_on() {
    let text = unit_text();
    let lines: Vec<&str> = text.lines().map(str::trim).filter(|l| !l.starts_with('#')).collect();
    for want in [
        "Type=notify",
        "NotifyAccess=main",
        "Restart=on-failure",
        "DynamicUser=yes",
        // The lab's group owns its folder; what the daemon writes there is the group's to read.
        "SupplementaryGroups=video tagdeflect",
        "ReadWritePaths=-/var/lib/tagdeflect-lab",
        "UMask=0027",
        "DeviceAllow=char-video4linux rw",
        "ProtectSystem=strict",
        "ProtectHome=yes",
        "PrivateTmp=yes",
        "NoNewPrivileges=yes",
        "StateDirectory=tagdeflect",
        "LogsDirectory=tagdeflect",
        "ConfigurationDirectory=tagdeflect",
        "CapabilityBoundingSet=",
        "KillSignal=SIGTERM",
        "RestartPreventExitStatus=2",
        // The live page's connections (capped) must not starve the recorder of descriptors:
        // the default 1 024 ran out with 1 100 idle page clients.
        "LimitNOFILE=16384",
        "After=network-online.target time-sync.target",
        "ExecStart=/usr/local/bin/tagdeflect run --config /etc/tagdeflect/tagdeflect.toml",
    ] {
        assert!(lines.contains(&want), "the unit lacks `{want}`");
    }
    assert!(lines.iter().any(|l| l.starts_with("WatchdogSec=")), "no WatchdogSec");
    // The group and the folder the unit names are made by the files the package installs.
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("systemd");
    let sysusers = std::fs::read_to_string(root.join("tagdeflect.sysusers")).unwrap();
    assert!(sysusers.lines().any(|l| l.split_whitespace().collect::<Vec<_>>() == ["g", "tagdeflect", "-"]), "{sysusers}");
    // A dynamic user's own group takes its name (User=, else the unit's): a static group of that
    // name makes the unit fail at start on a booted systemd (217/USER) — so it must be another.
    let user = lines.iter().find_map(|l| l.strip_prefix("User=")).unwrap_or("tagdeflect");
    for l in sysusers.lines().filter(|l| !l.trim_start().starts_with('#')) {
        let f: Vec<&str> = l.split_whitespace().collect();
        assert!(f.get(1) != Some(&user), "the dynamic user `{user}` collides with sysusers' `{l}`");
    }
    let tmpfiles = std::fs::read_to_string(root.join("tagdeflect.tmpfiles")).unwrap();
    let folder = ["d", "/var/lib/tagdeflect-lab", "2770", "root", "tagdeflect", "-"];
    assert!(tmpfiles.lines().any(|l| l.split_whitespace().collect::<Vec<_>>() == folder), "{tmpfiles}");
    assert!(lines.iter().any(|l| l.starts_with("SystemCallFilter=@system-service")), "no system call filter");
    // Modbus TCP and GigE Vision need IP sockets; sd_notify and journald need Unix sockets.
    let families = lines.iter().find(|l| l.starts_with("RestrictAddressFamilies=")).expect("RestrictAddressFamilies");
    for fam in ["AF_INET", "AF_INET6", "AF_UNIX"] {
        assert!(families.split([' ', '=']).any(|f| f == fam), "{families} lacks {fam}");
    }
}

#[test]
fn security_exposure_score_is_low() {
    let dir = tempfile::tempdir().expect("temp dir");
    let unit = unit_copy(dir.path(), None);
    let out = systemd_analyze(&["security", "--offline=true", "--no-pager", unit.to_str().expect("utf-8 path")]);
    let text = String::from_utf8_lossy(&out.stdout).into_owned() + &String::from_utf8_lossy(&out.stderr);
    for l in text.lines().filter(|l| l.contains('✗')) {
        println!("{}", l.split_whitespace().collect::<Vec<_>>().join(" "));
    }
    let line = text.lines().find(|l| l.contains("Overall exposure level")).unwrap_or_else(|| panic!("no exposure score in:\n{text}"));
    let score: f64 = line
        .split(':')
        .nth(1)
        .and_then(|s| s.split_whitespace().next())
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| panic!("cannot parse the exposure score from {line:?}"));
    println!("systemd-analyze security exposure score: {score} ({})", line.trim());
    assert!(score < 3.0, "exposure score {score} (systemd's scale: 0 safest … 10 unsafe); the unit scored 1.7 when written");
}
