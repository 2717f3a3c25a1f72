//! The tests' folder on disk: the running test's state (`TESTS/.running.json`) kept and
//! resumed, today's stopped tests read back, and a stopped test's folder completed (config,
//! report, `test.json` with the SHA-256 of every file).

use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use sha2::Digest;
use tagdeflect_core::feed::FeedEvent;
use tagdeflect_core::feed_file::FeedWriter;

use super::record::{day_of, read_curve};
use super::state::{LabTests, Running};
use super::zero::{Mean, MeanParts, Zero};
use super::{EarlierTest, TestError, TestRecord, EARLIER_TESTS};

impl LabTests {
    pub(super) fn state_file(&self) -> PathBuf {
        self.dir.join(".running.json")
    }

    /// Keeps the running test's state on disk (see the module doc); a failure is logged.
    pub(super) fn persist(&self, r: &Running) {
        if let Err(e) = self.persist_as(r, Phase::Running) {
            tracing::error!(test = %r.record.id, "{e}");
        }
    }

    /// Writes the test's state as `phase` (a temporary file, synced, renamed over the state,
    /// the folder synced): the state on disk is always a whole one, the old or the new.
    pub(super) fn persist_as(&self, r: &Running, phase: Phase) -> std::io::Result<()> {
        let p = Persisted {
            phase,
            record: r.record.clone(),
            folder: r.folder.clone(),
            zero_n: r.zero.n,
            tags: r.zero.tags.iter().map(|(k, m)| (*k, m.to_parts())).collect(),
            net: r.zero.net.to_parts(),
            gauges: r.zero.gauges.iter().map(|(k, m)| (k.clone(), m.to_parts())).collect(),
            last_line_t_ns: r.written_t_ns,
        };
        let path = self.state_file();
        let bytes = serde_json::to_vec(&p).map_err(std::io::Error::other)?;
        write_durably(&path, &bytes)
            .map_err(|e| std::io::Error::new(e.kind(), format!("cannot keep the running test's state in {}: {e}", path.display())))
    }

    /// The curves of today's stopped tests in the folder (once, at start).
    pub(super) fn read_earlier(&self) {
        let today = day_of(tagdeflect_core::clock::now_epoch_ns());
        let Ok(entries) = std::fs::read_dir(&self.dir) else { return };
        let mut found: Vec<EarlierTest> = Vec::new();
        for e in entries.flatten() {
            let folder = e.path();
            let Ok(text) = std::fs::read_to_string(folder.join("test.json")) else { continue };
            let Ok(record) = serde_json::from_str::<TestRecord>(&text) else { continue };
            if day_of(record.started_t_ns) != today {
                continue;
            }
            match read_curve(&folder.join("feed.jsonl")) {
                Ok(curve) => found.push(EarlierTest::new(&record, &curve)),
                Err(e) => tracing::warn!(test = %record.id, "the curve of an earlier test cannot be read: {e}"),
            }
        }
        found.sort_by_key(|t| t.started_t_ns);
        let skip = found.len().saturating_sub(EARLIER_TESTS);
        self.lock().earlier = found.split_off(skip);
    }

    /// Resumes the test of `TESTS/.running.json`, if there is one.
    /// A state that cannot be resumed (unreadable, not a state, its folder gone) is moved aside
    /// to `.running.json.stale-<UTC time>` with a warning naming it, and the daemon starts
    /// idle: a stale file must not keep the rig down (the unit does not restart on exit 2).
    ///
    /// A state that says "stopping" (the daemon stopped while the test's folder was being
    /// completed) is not resumed: the stopped test is returned, for its folder to be completed.
    pub(super) fn resume(&self) -> std::io::Result<Option<Running>> {
        let path = self.state_file();
        if std::fs::symlink_metadata(&path).is_err() {
            return Ok(None);
        }
        let e = match self.resume_from(&path) {
            Ok(stopping) => return Ok(stopping),
            Err(e) => e,
        };
        let stamp = chrono::DateTime::from_timestamp_nanos(tagdeflect_core::clock::now_epoch_ns()).format("%Y%m%dT%H%M%SZ");
        let mut aside = path.with_file_name(format!(".running.json.stale-{stamp}"));
        for k in 2.. {
            if std::fs::symlink_metadata(&aside).is_err() {
                break;
            }
            aside = path.with_file_name(format!(".running.json.stale-{stamp}-{k}"));
        }
        std::fs::rename(&path, &aside).map_err(|r| {
            std::io::Error::new(
                r.kind(),
                format!("{}: cannot be resumed ({e}) nor moved aside to {}: {r}", path.display(), aside.display()),
            )
        })?;
        tracing::warn!(
            "the running test's state {} cannot be resumed: {e}; moved aside to {}, starting without a running test",
            path.display(),
            aside.display()
        );
        Ok(None)
    }

    fn resume_from(&self, path: &Path) -> std::io::Result<Option<Running>> {
        let text = std::fs::read_to_string(path)?;
        let p: Persisted = serde_json::from_str(&text).map_err(|e| std::io::Error::new(std::io::ErrorKind::InvalidData, e.to_string()))?;
        if !p.folder.is_dir() {
            let message = format!("its test folder {} is gone", p.folder.display());
            return Err(std::io::Error::new(std::io::ErrorKind::NotFound, message));
        }
        // A crash may have cut the last line of the test's files: cut back to whole lines.
        let (feed, utm) = Self::open_files(&p.folder)?;
        let zero = Zero {
            n: p.zero_n,
            tags: p.tags.into_iter().map(|(k, v)| (k, Mean::from_parts(&v))).collect(),
            net: Mean::from_parts(&p.net),
            gauges: p.gauges.into_iter().map(|(k, v)| (k, Mean::from_parts(&v))).collect(),
            loads_kn: None,
        };
        let curve = read_curve(&p.folder.join("feed.jsonl")).unwrap_or_default();
        let mut r = Running {
            record: p.record,
            folder: p.folder,
            feed,
            utm,
            zero,
            written_t_ns: p.last_line_t_ns,
            curve,
            ends: Default::default(),
            preload_kn: None,
        };
        if p.phase == Phase::Stopping {
            return Ok(Some(r));
        }
        // The counts are the files' (the state was kept at the last event, lines later), and
        // the gap runs from the last line written before the stop to the first one after
        // (its note is completed there, `steps`).
        let feed_path = r.folder.join("feed.jsonl");
        r.record.lines = count_lines(&feed_path)?;
        r.record.utm_samples = count_lines(&r.folder.join("utm.jsonl"))?;
        if let Some(t) = last_line_t_ns(&feed_path) {
            r.written_t_ns = t;
        }
        r.ends.resumed_after_t_ns = (r.written_t_ns > i64::MIN).then_some(r.written_t_ns);
        let now = tagdeflect_core::clock::now_epoch_ns();
        let ev = FeedEvent { kind: "resume".into(), t_ns: now, note: Some(RESUME_NOTE.into()), user: None };
        r.record.events.push(ev.clone());
        let away_s = r.ends.resumed_after_t_ns.map_or(f64::NAN, |t| (now as i128 - t as i128) as f64 * 1e-9);
        tracing::warn!(test = %r.record.id, away_s = format!("{away_s:.1}"), "a test was running when the daemon stopped: resumed from its zero");
        self.persist(&r);
        let mut g = self.lock();
        g.pending.push(ev);
        g.running = Some(r);
        Ok(None)
    }

    /// The test's `feed.jsonl` and `utm.jsonl` in `folder`, opened to append (made when absent,
    /// a partial last line cut off).
    pub(super) fn open_files(folder: &Path) -> std::io::Result<(FeedWriter, FeedWriter)> {
        Ok((FeedWriter::append(&folder.join("feed.jsonl"))?, FeedWriter::append(&folder.join("utm.jsonl"))?))
    }

    /// Writes the config, the report and `test.json` of a stopped test (`test.json` last, under
    /// a temporary name, synced and renamed: a folder with `test.json` is complete); answers why the
    /// report could not be made, if it could not.
    pub(super) fn complete(&self, r: &mut Running) -> Result<Option<String>, TestError> {
        let Running { record, folder, feed, utm, .. } = r;
        let io = |what: &str, e: std::io::Error| TestError::Io(format!("{}: {what}: {e}", folder.display()));
        // The test's frames (`[output] record_tests`) written and closed before the hashes.
        if let Some(stopped) = self.close_frames(&record.id) {
            record.frames_stopped.get_or_insert(stopped);
        }
        // Every line held back (a full disk) written first; else the stop says so and keeps them.
        feed.flush_held().map_err(|e| io("feed.jsonl", e))?;
        utm.flush_held().map_err(|e| io("utm.jsonl", e))?;
        record.lines = count_lines(&folder.join("feed.jsonl")).map_err(|e| io("feed.jsonl", e))?;
        record.utm_samples = count_lines(&folder.join("utm.jsonl")).map_err(|e| io("utm.jsonl", e))?;
        write_durably(&folder.join("tagdeflect.toml"), self.config_text.as_bytes()).map_err(|e| io("tagdeflect.toml", e))?;
        if let Some(Err(e)) = self.folder_files.get().map(|hook| hook(folder, record)) {
            tracing::error!(test = %record.id, "{e}");
        }
        let mut report_error = None;
        if record.meta.standard.is_some() {
            if let Some(hook) = &self.report {
                hold_before_report(&record.id);
                if let Err(e) = hook(folder, record) {
                    tracing::error!(test = %record.id, "the test's report could not be made: {e}");
                    report_error = Some(format!("the report could not be made: {e}"));
                }
            }
        }
        record.sha256 = hash_folder(folder).map_err(|e| io("hashing", e))?;
        record.sha256.extend(self.calibration_sha256.clone());
        let text = serde_json::to_string_pretty(&*record).map_err(|e| TestError::Io(e.to_string()))? + "\n";
        write_durably(&folder.join("test.json"), text.as_bytes()).map_err(|e| io("test.json", e))?;
        self.publish(record);
        Ok(report_error)
    }
}

/// The resume event's note; the first line after the resume adds the gap (`(no lines for N s)`).
pub(super) const RESUME_NOTE: &str = "the daemon restarted; the test goes on from its zero";

/// The `t_ns` of the last whole line of a feed file (read from its last MiB), if any.
fn last_line_t_ns(path: &Path) -> Option<i64> {
    use std::io::{Read, Seek, SeekFrom};
    let mut f = std::fs::File::open(path).ok()?;
    let len = f.metadata().ok()?.len();
    f.seek(SeekFrom::Start(len.saturating_sub(1 << 20))).ok()?;
    let mut tail = Vec::new();
    f.read_to_end(&mut tail).ok()?;
    let text = String::from_utf8_lossy(&tail);
    let last = text.lines().rev().find(|l| !l.trim().is_empty())?;
    serde_json::from_str::<serde_json::Value>(last).ok()?.get("t_ns")?.as_i64()
}

/// Lines in a file (whole lines: the writers leave no partial one).
fn count_lines(path: &Path) -> std::io::Result<u64> {
    use std::io::Read;
    let mut f = std::fs::File::open(path)?;
    let mut buf = vec![0u8; 1 << 16];
    let mut n = 0u64;
    loop {
        match f.read(&mut buf)? {
            0 => return Ok(n),
            k => n += buf[..k].iter().filter(|&&b| b == b'\n').count() as u64,
        }
    }
}

/// Writes `path` whole or not at all: a temporary file beside it, synced, renamed over it, and
/// the folder synced (the rename itself survives a power cut).
pub(super) fn write_durably(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let mut name = path.file_name().unwrap_or_default().to_os_string();
    name.push(".tmp");
    let tmp = path.with_file_name(name);
    let written = std::fs::File::create(&tmp).and_then(|mut f| {
        f.write_all(bytes)?;
        f.sync_all()
    });
    if let Err(e) = written.and_then(|()| std::fs::rename(&tmp, path)) {
        let _ = std::fs::remove_file(&tmp);
        return Err(e);
    }
    sync_dir(path.parent().unwrap_or(Path::new(".")))
}

/// `fsync` of a folder: the names made, renamed or removed in it survive a power cut.
pub(super) fn sync_dir(dir: &Path) -> std::io::Result<()> {
    std::fs::File::open(dir)?.sync_all()
}

/// The fault-injection hold of [`HOLD_REPORT_ENV`]: waits (at most 10 min) until the file it
/// names exists, having logged that it waits.
fn hold_before_report(id: &str) {
    let Some(file) = std::env::var_os(HOLD_REPORT_ENV) else { return };
    let file = PathBuf::from(file);
    tracing::warn!(test = %id, "{HOLD_REPORT_ENV}: the report waits until {} exists", file.display());
    let until = std::time::Instant::now() + std::time::Duration::from_secs(600);
    while !file.exists() && std::time::Instant::now() < until {
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
}

/// Fault injection for the tests of a crash during a stop: when set to a file's path, a
/// stopped test's report is made only once that file exists (the daemon's state says
/// "stopping" meanwhile). Never set in service.
const HOLD_REPORT_ENV: &str = "TAGDEFLECT_HOLD_REPORT";

/// What the state on disk says of its test.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub(super) enum Phase {
    /// The test runs: a daemon started resumes it.
    #[default]
    Running,
    /// The test was stopped (`record.stopped_t_ns`, its stop event in `record.events`) and its
    /// folder is being completed: a daemon started completes it.
    Stopping,
}

/// The running test's state on disk (`TESTS/.running.json`).
#[derive(Serialize, Deserialize)]
struct Persisted {
    /// Absent in a state written before stops were kept: running.
    #[serde(default, rename = "state")]
    phase: Phase,
    record: TestRecord,
    folder: PathBuf,
    zero_n: usize,
    tags: BTreeMap<u32, MeanParts>,
    net: MeanParts,
    gauges: BTreeMap<String, MeanParts>,
    last_line_t_ns: i64,
}

pub(super) fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// SHA-256 of every file under `folder` (but `test.json` and `signatures.jsonl`), by path
/// relative to it.
pub(super) fn hash_folder(folder: &Path) -> std::io::Result<BTreeMap<String, String>> {
    let mut out = BTreeMap::new();
    let mut stack = vec![folder.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d)? {
            let e = e?;
            let p = e.path();
            if e.file_type()?.is_dir() {
                stack.push(p);
                continue;
            }
            let rel = p.strip_prefix(folder).unwrap_or(&p).to_string_lossy().into_owned();
            // Signatures are added after the stop, each linked to its audit line.
            if rel == "test.json" || rel == super::audit::SIGNATURES_FILE || rel.ends_with(".tmp") {
                continue;
            }
            out.insert(rel, sha256_file(&p)?);
        }
    }
    Ok(out)
}

/// SHA-256 (lower-case hex) of a file, read through a buffer: a long test's `feed.jsonl`
/// (gigabytes) is never held whole (read whole, a 9-hour test's feed ran the daemon out of its
/// unit's `MemoryMax=2G` at the stop; docs/performance.md).
pub(super) fn sha256_file(path: &Path) -> std::io::Result<String> {
    use std::io::Read;
    let mut f = std::fs::File::open(path)?;
    let mut h = sha2::Sha256::new();
    let mut buf = vec![0u8; 1 << 16];
    loop {
        match f.read(&mut buf)? {
            0 => return Ok(hex(&h.finalize())),
            n => h.update(&buf[..n]),
        }
    }
}
