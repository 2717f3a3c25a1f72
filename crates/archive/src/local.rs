//! Throwaway local servers for `archive-bench` and the tests: a Mosquitto broker and a
//! PostgreSQL cluster in a temporary folder, on loopback and a free port, stopped (and the
//! folder removed) when the guard is dropped. Both come from Debian's packages
//! (`mosquitto`, `postgresql`; see `scripts/setup.sh`). Run as root, each server runs as
//! its own system user (`mosquitto`, `postgres`): PostgreSQL refuses to run as root.

use std::io;
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// A free TCP port on 127.0.0.1 (bound once and released).
fn free_port() -> io::Result<u16> {
    Ok(TcpListener::bind("127.0.0.1:0")?.local_addr()?.port())
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

fn wait_port(port: u16, timeout: Duration) -> bool {
    let until = Instant::now() + timeout;
    let addr = SocketAddr::from(([127, 0, 0, 1], port));
    while Instant::now() < until {
        if TcpStream::connect_timeout(&addr, Duration::from_millis(200)).is_ok() {
            return true;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    false
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
        let dir = temp_dir("mosquitto")?;
        let port = free_port()?;
        let conf = dir.join("mosquitto.conf");
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
        let mut text = format!(
            "listener {port} 127.0.0.1\nallow_anonymous true\npersistence {persistence}\npersistence_location {}/\n\
             max_inflight_messages 1000\nmax_queued_messages 1000000\nmax_queued_bytes 0\n\
             log_dest file {}/mosquitto.log\nlog_type error\nlog_type warning\nlog_type notice\n",
            dir.display(),
            dir.display()
        );
        if !user.is_empty() {
            text.push_str(&format!("user {user}\n"));
        }
        std::fs::write(&conf, text)?;
        let mut m = LocalMosquitto { dir, conf, port, child: None };
        m.start_again()?;
        Ok(m)
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
        self.child = Some(child);
        if !wait_port(self.port, Duration::from_secs(10)) {
            let log = std::fs::read_to_string(self.dir.join("mosquitto.log")).unwrap_or_default();
            return Err(io::Error::other(format!("mosquitto did not open port {}: {log}", self.port)));
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
        let port = free_port()?;
        let run_as = if is_root() {
            let (uid, gid) = user_ids("postgres").ok_or_else(|| io::Error::other("running as root needs the postgres system user"))?;
            chown_tree(&dir, uid, gid)?;
            Some("postgres")
        } else {
            None
        };
        let mut options = format!("-p {port} -c listen_addresses=127.0.0.1 -k {} -c max_connections=50", dir.display());
        if !durable {
            options.push_str(" -c fsync=off -c synchronous_commit=off -c full_page_writes=off");
        }
        let pg = LocalPostgres { dir, bin, port, run_as, options };
        let data = pg.dir.join("data");
        pg.run(
            "initdb",
            &["-D", data.to_str().unwrap_or_default(), "-A", "trust", "-U", "tagdeflect", "-E", "UTF8", "--no-sync", "--locale=C"],
        )?;
        pg.start_again()?;
        Ok(pg)
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
