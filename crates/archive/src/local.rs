//! Throwaway local servers for `archive-bench` and the tests: a Mosquitto broker and a
//! PostgreSQL cluster in a temporary folder, on loopback and a free port, stopped (and the
//! folder removed) when the guard is dropped. Both come from Debian's packages
//! (`mosquitto`, `postgresql`; see `scripts/setup.sh`). Run as root, each server runs as
//! its own system user (`mosquitto`, `postgres`): PostgreSQL refuses to run as root.

use std::io;
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// A TCP port on 127.0.0.1 that was free a moment ago (bound once and released). Neither
/// Mosquitto nor PostgreSQL can listen on port 0 and say which port it took, so a server
/// started on it is checked with [`process_listens_on`] and started again on another port
/// when another program took this one in between.
fn free_port() -> io::Result<u16> {
    Ok(TcpListener::bind("127.0.0.1:0")?.local_addr()?.port())
}

/// Whether process `pid` itself listens on TCP 127.0.0.1:`port` (or on every address): the
/// listening socket's inode in `/proc/net/tcp` is among the process's open files. A port
/// that another program listens on is not taken for the server's.
pub fn process_listens_on(pid: u32, port: u16) -> bool {
    let Ok(table) = std::fs::read_to_string("/proc/net/tcp") else { return false };
    let inodes: Vec<String> = table
        .lines()
        .skip(1)
        .filter_map(|l| {
            let f: Vec<&str> = l.split_whitespace().collect();
            let (ip, p) = f.get(1)?.split_once(':')?;
            let listening = f.get(3) == Some(&"0A");
            let ours = u16::from_str_radix(p, 16).ok()? == port && (ip == "0100007F" || ip == "00000000");
            (listening && ours).then(|| f.get(9).map(|s| format!("socket:[{s}]"))).flatten()
        })
        .collect();
    if inodes.is_empty() {
        return false;
    }
    let Ok(fds) = std::fs::read_dir(format!("/proc/{pid}/fd")) else { return false };
    fds.flatten().any(|fd| std::fs::read_link(fd.path()).is_ok_and(|l| inodes.iter().any(|i| l.as_os_str() == i.as_str())))
}

/// Waits until `child` listens on `port` itself: `Ok(true)`; `Ok(false)` when it exited
/// first (the port taken, a bad config) or did not listen within `timeout`.
fn wait_listening(child: &mut Child, port: u16, timeout: Duration) -> io::Result<bool> {
    let until = Instant::now() + timeout;
    while Instant::now() < until {
        if child.try_wait()?.is_some() {
            return Ok(false);
        }
        if process_listens_on(child.id(), port) {
            return Ok(true);
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    Ok(false)
}

fn temp_dir(what: &str) -> io::Result<PathBuf> {
    let d = std::env::temp_dir().join(format!("tagdeflect-{what}-{}-{:08x}", std::process::id(), rand::random::<u32>()));
    std::fs::create_dir_all(&d)?;
    Ok(d)
}

fn is_root() -> bool {
    // /proc/self belongs to the effective user of this process.
    std::fs::metadata("/proc/self").map(|m| std::os::unix::fs::MetadataExt::uid(&m) == 0).unwrap_or(false)
}

/// uid and gid of a system user from /etc/passwd.
fn user_ids(name: &str) -> Option<(u32, u32)> {
    let text = std::fs::read_to_string("/etc/passwd").ok()?;
    text.lines().find_map(|l| {
        let f: Vec<&str> = l.split(':').collect();
        (f.len() > 3 && f[0] == name).then(|| Some((f[2].parse().ok()?, f[3].parse().ok()?))).flatten()
    })
}

fn chown_tree(dir: &Path, uid: u32, gid: u32) -> io::Result<()> {
    std::os::unix::fs::chown(dir, Some(uid), Some(gid))?;
    for e in std::fs::read_dir(dir)? {
        let p = e?.path();
        if p.is_dir() {
            chown_tree(&p, uid, gid)?;
        } else {
            std::os::unix::fs::chown(&p, Some(uid), Some(gid))?;
        }
    }
    Ok(())
}

/// A Mosquitto broker on 127.0.0.1 with persistent sessions (sessions and queued messages
/// survive a stop/start), generous in-flight and queue limits.
pub struct LocalMosquitto {
    dir: PathBuf,
    conf: PathBuf,
    port: u16,
    child: Option<Child>,
}

impl LocalMosquitto {
    /// Starts the broker (`mosquitto` from Debian's package).
    pub fn start() -> io::Result<LocalMosquitto> {
        LocalMosquitto::start_with(true)
    }

    /// Starts the broker with or without persistence (without: a restart forgets every
    /// session, subscription, queued and retained message, as a broker run that way does).
    pub fn start_with(persistence: bool) -> io::Result<LocalMosquitto> {
        LocalMosquitto::start_configured(persistence, "allow_anonymous true\n")
    }

    /// Starts the broker with `auth` in place of `allow_anonymous true` (e.g. a
    /// `password_file` and an `acl_file`, with `allow_anonymous false`).
    pub fn start_configured(persistence: bool, auth: &str) -> io::Result<LocalMosquitto> {
        let dir = temp_dir("mosquitto")?;
        let user = if is_root() {
            match user_ids("mosquitto") {
                Some((uid, gid)) => {
                    std::os::unix::fs::chown(&dir, Some(uid), Some(gid))?;
                    "mosquitto"
                }
                None => "root",
            }
        } else {
            ""
        };
        let conf = dir.join("mosquitto.conf");
        let mut m = LocalMosquitto { dir, conf, port: 0, child: None };
        // A port free a moment ago may have been taken since: then another one.
        let mut last = None;
        for _ in 0..5 {
            m.port = free_port()?;
            let mut text = format!(
                "listener {} 127.0.0.1\n{auth}persistence {persistence}\npersistence_location {}/\n\
                 max_inflight_messages 1000\nmax_queued_messages 1000000\nmax_queued_bytes 0\n\
                 log_dest file {}/mosquitto.log\nlog_type error\nlog_type warning\nlog_type notice\n",
                m.port,
                m.dir.display(),
                m.dir.display()
            );
            if !user.is_empty() {
                text.push_str(&format!("user {user}\n"));
            }
            std::fs::write(&m.conf, text)?;
            match m.start_again() {
                Ok(()) => return Ok(m),
                Err(e) => last = Some(e),
            }
        }
        Err(last.unwrap_or_else(|| io::Error::other("mosquitto did not start")))
    }

    /// The broker's URL, `mqtt://127.0.0.1:PORT`.
    pub fn url(&self) -> String {
        format!("mqtt://127.0.0.1:{}", self.port)
    }

    /// The broker's port.
    pub fn port(&self) -> u16 {
        self.port
    }

    /// Stops the broker (SIGTERM: it saves its sessions) and waits for it to exit.
    pub fn stop(&mut self) {
        if let Some(mut c) = self.child.take() {
            let _ = Command::new("kill").arg("-TERM").arg(c.id().to_string()).status();
            let until = Instant::now() + Duration::from_secs(5);
            while Instant::now() < until {
                if let Ok(Some(_)) = c.try_wait() {
                    return;
                }
                std::thread::sleep(Duration::from_millis(20));
            }
            let _ = c.kill();
            let _ = c.wait();
        }
    }

    /// Starts the broker again on the same port with the same persistence.
    pub fn start_again(&mut self) -> io::Result<()> {
        let child = Command::new("mosquitto")
            .arg("-c")
            .arg(&self.conf)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .map_err(|e| io::Error::new(e.kind(), format!("cannot start mosquitto (run scripts/setup.sh): {e}")))?;
        let child = self.child.insert(child);
        if !wait_listening(child, self.port, Duration::from_secs(10))? {
            let _ = child.kill();
            let _ = child.wait();
            self.child = None;
            let log = std::fs::read_to_string(self.dir.join("mosquitto.log")).unwrap_or_default();
            return Err(io::Error::other(format!("mosquitto did not listen on port {}: {log}", self.port)));
        }
        Ok(())
    }
}

impl Drop for LocalMosquitto {
    fn drop(&mut self) {
        if let Some(mut c) = self.child.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

/// A PostgreSQL cluster in a temporary folder (`initdb` + `pg_ctl`), trust authentication
/// on 127.0.0.1 only.
pub struct LocalPostgres {
    dir: PathBuf,
    bin: PathBuf,
    port: u16,
    run_as: Option<&'static str>,
    options: String,
}

/// The newest PostgreSQL server binaries under /usr/lib/postgresql/*/bin.
fn postgres_bin() -> io::Result<PathBuf> {
    let mut versions: Vec<(u32, PathBuf)> = std::fs::read_dir("/usr/lib/postgresql")
        .map_err(|e| io::Error::new(e.kind(), format!("/usr/lib/postgresql: {e} (install the postgresql package: scripts/setup.sh)")))?
        .filter_map(|e| e.ok())
        .filter_map(|e| Some((e.file_name().to_str()?.parse::<u32>().ok()?, e.path().join("bin"))))
        .filter(|(_, p)| p.join("initdb").is_file())
        .collect();
    versions.sort();
    versions.pop().map(|v| v.1).ok_or_else(|| io::Error::other("no PostgreSQL server under /usr/lib/postgresql/*/bin"))
}

impl LocalPostgres {
    /// Creates and starts a cluster. `durable = false` turns fsync off (tests: faster, and
    /// a stop is always clean); benchmarks keep PostgreSQL's defaults.
    pub fn start(durable: bool) -> io::Result<LocalPostgres> {
        let bin = postgres_bin()?;
        let dir = temp_dir("postgres")?;
        let run_as = if is_root() {
            let (uid, gid) = user_ids("postgres").ok_or_else(|| io::Error::other("running as root needs the postgres system user"))?;
            chown_tree(&dir, uid, gid)?;
            Some("postgres")
        } else {
            None
        };
        let mut pg = LocalPostgres { dir, bin, port: 0, run_as, options: String::new() };
        let data = pg.dir.join("data");
        pg.run(
            "initdb",
            &["-D", data.to_str().unwrap_or_default(), "-A", "trust", "-U", "tagdeflect", "-E", "UTF8", "--no-sync", "--locale=C"],
        )?;
        // A port free a moment ago may have been taken since: PostgreSQL then fails to bind
        // (and `pg_ctl -w` says so), and it is started on another one.
        let mut last = None;
        for _ in 0..5 {
            pg.port = free_port()?;
            pg.options = format!("-p {} -c listen_addresses=127.0.0.1 -k {} -c max_connections=50", pg.port, pg.dir.display());
            if !durable {
                pg.options.push_str(" -c fsync=off -c synchronous_commit=off -c full_page_writes=off");
            }
            match pg.start_again() {
                Ok(()) => return Ok(pg),
                Err(e) => last = Some(e),
            }
        }
        Err(last.unwrap_or_else(|| io::Error::other("PostgreSQL did not start")))
    }

    fn command(&self, tool: &str) -> Command {
        let exe = self.bin.join(tool);
        match self.run_as {
            Some(user) => {
                let mut c = Command::new("runuser");
                c.arg("-u").arg(user).arg("--").arg(exe);
                c
            }
            None => Command::new(exe),
        }
    }

    fn run(&self, tool: &str, args: &[&str]) -> io::Result<()> {
        let out = self.command(tool).args(args).current_dir(&self.dir).stdin(Stdio::null()).output()?;
        if !out.status.success() {
            return Err(io::Error::other(format!(
                "{tool} failed: {}{}",
                String::from_utf8_lossy(&out.stdout),
                String::from_utf8_lossy(&out.stderr)
            )));
        }
        Ok(())
    }

    /// A URL for the cluster's `postgres` database.
    pub fn url(&self) -> String {
        format!("postgresql://tagdeflect@127.0.0.1:{}/postgres", self.port)
    }

    /// Stops the server (fast shutdown: clients are disconnected).
    pub fn stop(&self) -> io::Result<()> {
        let data = self.dir.join("data");
        self.run("pg_ctl", &["-D", data.to_str().unwrap_or_default(), "-m", "fast", "-w", "stop"])
    }

    /// Starts the server (again).
    pub fn start_again(&self) -> io::Result<()> {
        let data = self.dir.join("data");
        let log = self.dir.join("postgres.log");
        self.run(
            "pg_ctl",
            &[
                "-D",
                data.to_str().unwrap_or_default(),
                "-l",
                log.to_str().unwrap_or_default(),
                "-o",
                &self.options,
                "-w",
                "-t",
                "30",
                "start",
            ],
        )
    }
}

impl Drop for LocalPostgres {
    fn drop(&mut self) {
        let data = self.dir.join("data");
        let _ = self
            .command("pg_ctl")
            .args(["-D", data.to_str().unwrap_or_default(), "-m", "immediate", "-w", "stop"])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .status();
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}
