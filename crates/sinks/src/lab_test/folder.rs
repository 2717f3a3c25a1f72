//! The tests' folder on disk: the running test's state (`TESTS/.running.json`) kept and
//! resumed, today's stopped tests read back, and a stopped test's folder completed (config,
//! report, `test.json` with the SHA-256 of every file).

use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use sha2::Digest;
use tagdeflect_core::feed::FeedEvent;

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
        let p = Persisted {
            record: r.record.clone(),
            folder: r.folder.clone(),
            zero_n: r.zero.n,
            tags: r.zero.tags.iter().map(|(k, m)| (*k, m.to_parts())).collect(),
            net: r.zero.net.to_parts(),
            gauges: r.zero.gauges.iter().map(|(k, m)| (k.clone(), m.to_parts())).collect(),
            last_line_t_ns: r.written_t_ns,
        };
        let path = self.state_file();
        let tmp = path.with_extension("json.tmp");
        let result = serde_json::to_vec(&p)
            .map_err(std::io::Error::other)
            .and_then(|bytes| {
                let mut f = std::fs::File::create(&tmp)?;
                f.write_all(&bytes)?;
                f.sync_all()
            })
            .and_then(|()| std::fs::rename(&tmp, &path));
        if let Err(e) = result {
            tracing::error!(test = %r.record.id, "cannot keep the running test's state in {}: {e}", path.display());
        }
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
    pub(super) fn resume(&self) -> std::io::Result<()> {
        let path = self.state_file();
        if std::fs::symlink_metadata(&path).is_err() {
            return Ok(());
        }
        let Err(e) = self.resume_from(&path) else { return Ok(()) };
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
        Ok(())
    }

    fn resume_from(&self, path: &Path) -> std::io::Result<()> {
        let text = std::fs::read_to_string(path)?;
        let p: Persisted = serde_json::from_str(&text).map_err(|e| std::io::Error::new(std::io::ErrorKind::InvalidData, e.to_string()))?;
        if !p.folder.is_dir() {
            let message = format!("its test folder {} is gone", p.folder.display());
            return Err(std::io::Error::new(std::io::ErrorKind::NotFound, message));
        }
        // A crash may have cut the last line of the test's files: cut back to whole lines.
        for name in ["feed.jsonl", "utm.jsonl"] {
            tagdeflect_core::linefile::LineFile::open_append(&p.folder.join(name))?;
        }
        let open = |name: &str| std::fs::OpenOptions::new().append(true).open(p.folder.join(name));
        let (feed, utm) = (open("feed.jsonl")?, open("utm.jsonl")?);
        let now = tagdeflect_core::clock::now_epoch_ns();
        let gap_s = if p.last_line_t_ns > i64::MIN { (now as i128 - p.last_line_t_ns as i128) as f64 * 1e-9 } else { f64::NAN };
        let ev = FeedEvent {
            kind: "resume".into(),
            t_ns: now,
            note: Some(format!("the daemon restarted; the test goes on from its zero (no lines for {gap_s:.1} s)")),
            user: None,
        };
        let mut record = p.record;
        record.events.push(ev.clone());
        let zero = Zero {
            n: p.zero_n,
            tags: p.tags.into_iter().map(|(k, v)| (k, Mean::from_parts(&v))).collect(),
            net: Mean::from_parts(&p.net),
            gauges: p.gauges.into_iter().map(|(k, v)| (k, Mean::from_parts(&v))).collect(),
        };
        tracing::warn!(test = %record.id, gap_s = format!("{gap_s:.1}"), "a test was running when the daemon stopped: resumed from its zero");
        let curve = read_curve(&p.folder.join("feed.jsonl")).unwrap_or_default();
        let r = Running { record, folder: p.folder, feed, utm, zero, written_t_ns: p.last_line_t_ns, curve };
        self.persist(&r);
        let mut g = self.lock();
        g.pending.push(ev);
        g.running = Some(r);
        Ok(())
    }

    /// Writes the config, the report and `test.json` of a stopped test.
    pub(super) fn complete(&self, r: Running) -> Result<(), TestError> {
        let Running { mut record, folder, feed, utm, .. } = r;
        let io = |what: &str, e: std::io::Error| TestError::Io(format!("{}: {what}: {e}", folder.display()));
        feed.sync_all().map_err(|e| io("feed.jsonl", e))?;
        utm.sync_all().map_err(|e| io("utm.jsonl", e))?;
        std::fs::write(folder.join("tagdeflect.toml"), &self.config_text).map_err(|e| io("tagdeflect.toml", e))?;
        if record.meta.standard.is_some() {
            if let Some(hook) = &self.report {
                if let Err(e) = hook(&folder, &record) {
                    tracing::error!(test = %record.id, "the test's report could not be made: {e}");
                }
            }
        }
        record.sha256 = hash_folder(&folder).map_err(|e| io("hashing", e))?;
        record.sha256.extend(self.calibration_sha256.clone());
        let text = serde_json::to_string_pretty(&record).map_err(|e| TestError::Io(e.to_string()))?;
        let tmp = folder.join("test.json.tmp");
        std::fs::write(&tmp, text + "\n").map_err(|e| io("test.json", e))?;
        std::fs::rename(&tmp, folder.join("test.json")).map_err(|e| io("test.json", e))?;
        self.publish(&record);
        Ok(())
    }
}

/// The running test's state on disk (`TESTS/.running.json`).
#[derive(Serialize, Deserialize)]
struct Persisted {
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
            out.insert(rel, hex(&sha2::Sha256::digest(std::fs::read(&p)?)));
        }
    }
    Ok(out)
}
