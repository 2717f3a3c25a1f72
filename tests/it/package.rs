//! The Debian package: `scripts/package.sh` builds it from the test binary, and its contents,
//! control data and installed configuration are checked (the install into a fresh Debian is
//! `scripts/debian-install-test.sh`, which needs root and network).

use std::path::Path;
use std::process::Command;

fn run(cmd: &mut Command) -> String {
    let o = cmd.output().unwrap_or_else(|e| panic!("{cmd:?}: {e}"));
    assert!(o.status.success(), "{cmd:?}: {}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
    String::from_utf8_lossy(&o.stdout).into_owned()
}

#[test]
fn package_holds_binary_unit_conffile_man_pages_and_completions() {
    let repo = Path::new(env!("CARGO_MANIFEST_DIR"));
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("deb");
    let printed = run(Command::new(repo.join("scripts/package.sh")).args(["--bin", env!("CARGO_BIN_EXE_tagdeflect"), "--out"]).arg(&out));
    let deb = Path::new(printed.lines().last().unwrap().trim()).to_path_buf();
    let arch = run(Command::new("dpkg").arg("--print-architecture")).trim().to_string();
    assert_eq!(deb, out.join(format!("tagdeflect_{}_{arch}.deb", env!("CARGO_PKG_VERSION"))));

    // Control data: the version of the crate, dependencies computed from the linked libraries.
    let field = |f: &str| run(Command::new("dpkg-deb").arg("-f").arg(&deb).arg(f)).trim().to_string();
    assert_eq!(field("Package"), "tagdeflect");
    assert_eq!(field("Version"), env!("CARGO_PKG_VERSION"));
    let depends = field("Depends");
    eprintln!("Depends: {depends}");
    assert!(depends.contains("libc6 (>=") && depends.contains("libglib2.0-0"), "{depends}");
    // The report's plots read a TrueType font from a file (no library names it): without it
    // a test's stop makes no report.
    assert!(depends.contains("fonts-dejavu-core | fonts-liberation | fonts-noto-core"), "{depends}");
    if cfg!(feature = "aravis") {
        assert!(depends.contains("libaravis-0.8-0"), "{depends}");
    }
    let files = run(Command::new("dpkg-deb").arg("-c").arg(&deb));
    for f in [
        "./usr/bin/tagdeflect",
        "./lib/systemd/system/tagdeflect.service",
        // The lab's group and folder the unit names.
        "./usr/lib/sysusers.d/tagdeflect.conf",
        "./usr/lib/tmpfiles.d/tagdeflect.conf",
        "./etc/tagdeflect/tagdeflect.toml",
        "./usr/share/man/man1/tagdeflect.1.gz",
        "./usr/share/man/man1/tagdeflect-calibrate.1.gz",
        "./usr/share/man/man1/tagdeflect-run.1.gz",
        "./usr/share/bash-completion/completions/tagdeflect",
        "./usr/share/zsh/vendor-completions/_tagdeflect",
        "./usr/share/fish/vendor_completions.d/tagdeflect.fish",
        "./usr/share/doc/tagdeflect/copyright",
        "./usr/share/doc/tagdeflect/docs/calibration.md",
    ] {
        assert!(files.lines().any(|l| l.ends_with(f)), "{f} not in the package:\n{files}");
    }
    assert!(!files.contains("tagdeflect-assets.1"), "the hidden command has no page");

    // Unpacked: the unit runs the packaged binary on the packaged config; the config is a
    // conffile and is the simulated rig, writing where the sandbox allows.
    let x = dir.path().join("x");
    run(Command::new("dpkg-deb").arg("-R").arg(&deb).arg(&x));
    let unit = std::fs::read_to_string(x.join("lib/systemd/system/tagdeflect.service")).unwrap();
    assert!(unit.contains("\nExecStart=/usr/bin/tagdeflect run --config /etc/tagdeflect/tagdeflect.toml\n"));
    assert!(!unit.contains("/usr/local/bin"), "the package's paths only");
    assert_eq!(std::fs::read_to_string(x.join("DEBIAN/conffiles")).unwrap().trim(), "/etc/tagdeflect/tagdeflect.toml");
    let postinst = std::fs::read_to_string(x.join("DEBIAN/postinst")).unwrap();
    assert!(
        postinst.contains("systemd-sysusers tagdeflect.conf") && postinst.contains("systemd-tmpfiles --create tagdeflect.conf"),
        "{postinst}"
    );
    let commands: Vec<&str> = postinst.lines().map(str::trim).filter(|l| l.starts_with("systemctl")).collect();
    assert!(
        !commands.is_empty() && commands.iter().all(|l| l.starts_with("systemctl daemon-reload")),
        "postinst only reloads: {commands:?}"
    );
    let cfg = tagdeflect::config::Config::load(&x.join("etc/tagdeflect/tagdeflect.toml")).unwrap();
    assert_eq!(cfg.cameras.len(), 3);
    assert_eq!(cfg.output.feed.as_deref(), Some("/var/lib/tagdeflect/feed.jsonl"));
    assert_eq!(cfg.output.http.as_deref(), Some("127.0.0.1:8080"));
    let installed = std::fs::read_to_string(x.join("etc/tagdeflect/tagdeflect.toml")).unwrap();
    assert_eq!(installed, std::fs::read_to_string(repo.join("config/tagdeflect.toml")).unwrap());
    assert!(installed.contains("systemctl start tagdeflect") && installed.contains("v4l2:/dev/v4l/by-id/"));

    // Man pages and completions come from the command line: the calibrate page has its flags.
    let page = run(Command::new("gzip").arg("-dc").arg(x.join("usr/share/man/man1/tagdeflect-calibrate.1.gz")));
    assert!(page.contains("fix\\-k3") && page.contains("force"), "{page}");
    let bash = std::fs::read_to_string(x.join("usr/share/bash-completion/completions/tagdeflect")).unwrap();
    assert!(bash.contains("calibrate") && bash.contains("--fix-k3"));
}
