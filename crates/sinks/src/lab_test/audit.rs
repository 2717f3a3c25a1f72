//! The tests folder's audit log (`<tests>/audit.jsonl`, [`tagdeflect_core::audit`]): every
//! action of a user appended with their name and role; the sign-off of a stopped test's report
//! (`tests/<id>/signatures.jsonl`, linked to report.json's SHA-256 and to its audit line) and
//! the re-analysis of a stopped test (the previous report kept as `report.prev-N/`).

use std::io::Write;
use std::path::{Path, PathBuf};

use tagdeflect_core::audit::{verify_chain, AuditAction, AuditEntry};
use tagdeflect_core::feed::FeedEvent;
use tagdeflect_core::users::Actor;

use super::folder::{hash_folder, sha256_file};
use super::{LabTests, Stopped, TestError, TestRecord};

/// The audit log's file name in the tests folder.
pub const AUDIT_FILE: &str = "audit.jsonl";
/// A test's signatures, in its folder.
pub const SIGNATURES_FILE: &str = "signatures.jsonl";
/// The report's JSON, relative to a test's folder (what a signature is linked to).
pub const REPORT_JSON: &str = "report/report.json";

/// One line of `signatures.jsonl`.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Signature {
    /// Who signed.
    pub by: String,
    /// Their role.
    pub role: String,
    /// When, ns since the Unix epoch.
    pub t_ns: i64,
    /// What the signature means ("reviewed and approved").
    pub meaning: String,
    /// SHA-256 of `report/report.json` as signed.
    pub report_json_sha256: String,
    /// The `seq` of the audit log's `sign` line.
    pub audit_seq: u64,
}

/// Text a user typed (a meaning, a reason): 1 to 4096 characters, no control characters.
fn check_text(what: &str, text: &str) -> Result<(), TestError> {
    if text.trim().is_empty() || text.len() > 4096 || text.chars().any(|c| c.is_control()) {
        return Err(TestError::Bad(format!("{what}: 1 to 4096 characters, no control characters")));
    }
    Ok(())
}

impl LabTests {
    /// The audit log's path.
    pub fn audit_path(&self) -> PathBuf {
        self.dir.join(AUDIT_FILE)
    }

    /// Appends `action` by `actor` (about `test`) to the audit log, fsync'd.
    pub fn audit(&self, actor: &Actor, action: &str, test: Option<&str>, detail: serde_json::Value) -> Result<AuditEntry, TestError> {
        let mut log = self.audit.lock().unwrap_or_else(|p| p.into_inner());
        self.audit_locked(&mut log, actor, action, test, detail)
    }

    fn audit_locked(
        &self,
        log: &mut tagdeflect_core::audit::AuditLog,
        actor: &Actor,
        action: &str,
        test: Option<&str>,
        detail: serde_json::Value,
    ) -> Result<AuditEntry, TestError> {
        let a = AuditAction {
            t_ns: tagdeflect_core::clock::now_epoch_ns(),
            user: actor.user.clone(),
            role: actor.role.as_str().into(),
            action: action.into(),
            test: test.map(String::from),
            detail,
        };
        log.append(a).map_err(|e| {
            tracing::error!("{e}");
            TestError::Io(format!("the action was done but could not be written to the audit log: {e}"))
        })
    }

    /// The audit entry of a stop: the folder and test.json's SHA-256.
    pub fn audit_stop(&self, actor: &Actor, stopped: &Stopped) -> Result<AuditEntry, TestError> {
        let sha = sha256_file(&stopped.folder.join("test.json")).map_err(|e| TestError::Io(format!("test.json: {e}")))?;
        let detail = serde_json::json!({"folder": stopped.folder, "test_json_sha256": sha});
        self.audit(actor, "stop", Some(&stopped.id), detail)
    }

    /// `GET /api/audit?test=ID`: the chain's state and its entries (of one test, or all).
    pub fn audit_entries(&self, test: Option<&str>) -> Result<serde_json::Value, TestError> {
        let _log = self.audit.lock().unwrap_or_else(|p| p.into_inner());
        let path = self.audit_path();
        let chain = match verify_chain(&path) {
            Ok(s) => serde_json::json!({"ok": true, "entries": s.entries, "last_sha256": s.last_sha256}),
            Err(e) => serde_json::json!({"ok": false, "line": e.line(), "error": e.to_string()}),
        };
        let text = match std::fs::read_to_string(&path) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => String::new(),
            Err(e) => return Err(TestError::Io(format!("{}: {e}", path.display()))),
        };
        let entries: Vec<serde_json::Value> = text
            .lines()
            .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
            .filter(|e| test.is_none_or(|t| e.get("test").and_then(|v| v.as_str()) == Some(t)))
            .collect();
        Ok(serde_json::json!({"chain": chain, "entries": entries}))
    }

    /// A stopped test's folder by its id (one folder name of this tests folder).
    fn stopped_folder(&self, id: &str) -> Result<(PathBuf, TestRecord), TestError> {
        let ok = !id.is_empty() && !id.starts_with('.') && id.len() <= 128 && !id.contains(['/', '\\']);
        if !ok {
            return Err(TestError::Bad(format!("test \"{}\": a test's id, as GET /api/tests names it", id.escape_debug())));
        }
        let folder = self.dir.join(id);
        let text = std::fs::read_to_string(folder.join("test.json"))
            .map_err(|_| TestError::Conflict(format!("test {id}: no stopped test of that id here (no test.json)")))?;
        let record: TestRecord =
            serde_json::from_str(&text).map_err(|e| TestError::Conflict(format!("test {id}: its test.json cannot be read: {e}")))?;
        Ok((folder, record))
    }

    /// `POST /api/test/sign`: `actor` signs the report of the stopped test `id` with `meaning`.
    /// Refused (409) when the test has no report or report.json is not the one test.json
    /// hashed. Writes the audit `sign` line, then the signature naming it.
    pub fn sign(&self, actor: &Actor, id: &str, meaning: &str) -> Result<serde_json::Value, TestError> {
        check_text("meaning", meaning)?;
        let mut log = self.audit.lock().unwrap_or_else(|p| p.into_inner());
        let (folder, record) = self.stopped_folder(id)?;
        let report = folder.join(REPORT_JSON);
        let Ok(now_sha) = sha256_file(&report) else {
            return Err(TestError::Conflict(format!("test {id} has no report ({REPORT_JSON}): nothing to sign")));
        };
        match record.sha256.get(REPORT_JSON) {
            Some(h) if *h == now_sha => {}
            Some(h) => {
                return Err(TestError::Conflict(format!(
                    "test {id}: {REPORT_JSON} changed since test.json hashed it ({h}, now {now_sha}): not signed"
                )))
            }
            None => return Err(TestError::Conflict(format!("test {id}: test.json holds no hash of {REPORT_JSON}: not signed"))),
        }
        let detail = serde_json::json!({"meaning": meaning, "report_json_sha256": now_sha});
        let entry = self.audit_locked(&mut log, actor, "sign", Some(id), detail)?;
        let sig = Signature {
            by: actor.user.clone(),
            role: actor.role.as_str().into(),
            t_ns: entry.t_ns,
            meaning: meaning.into(),
            report_json_sha256: now_sha,
            audit_seq: entry.seq,
        };
        append_line(&folder.join(SIGNATURES_FILE), &sig)
            .map_err(|e| TestError::Io(format!("{}: {e}", folder.join(SIGNATURES_FILE).display())))?;
        Ok(serde_json::to_value(&sig).expect("a signature serialises"))
    }

    /// `POST /api/test/reanalyse`: makes the report of the stopped test `id` again from its
    /// folder, the previous one kept as `report.prev-N/`; test.json gets a `reanalysis` event
    /// and the folder's new hashes; the audit line names the reason and both test.json hashes.
    pub fn reanalyse(&self, actor: &Actor, id: &str, reason: &str) -> Result<serde_json::Value, TestError> {
        check_text("reason", reason)?;
        let mut log = self.audit.lock().unwrap_or_else(|p| p.into_inner());
        let (folder, mut record) = self.stopped_folder(id)?;
        let (Some(hook), Some(_)) = (&self.report, record.meta.standard.as_ref()) else {
            return Err(TestError::Conflict(format!("test {id}: no report to make again (no standard, or no report here)")));
        };
        let io = |what: &str, e: std::io::Error| TestError::Io(format!("{}: {what}: {e}", folder.display()));
        let before = sha256_file(&folder.join("test.json")).map_err(|e| io("test.json", e))?;
        let previous = if folder.join("report").is_dir() {
            let n = (1..).find(|n| !folder.join(format!("report.prev-{n}")).exists()).expect("a free name");
            let prev = format!("report.prev-{n}");
            std::fs::rename(folder.join("report"), folder.join(&prev)).map_err(|e| io("report", e))?;
            Some(prev)
        } else {
            None
        };
        hook(&folder, &record).map_err(|e| TestError::Conflict(format!("test {id}: the report could not be made again: {e}")))?;
        let now = tagdeflect_core::clock::now_epoch_ns();
        record.events.push(FeedEvent { kind: "reanalysis".into(), t_ns: now, note: Some(reason.into()), user: Some(actor.user.clone()) });
        let calibration: Vec<_> =
            record.sha256.iter().filter(|(k, _)| Path::new(k).is_absolute()).map(|(k, v)| (k.clone(), v.clone())).collect();
        record.sha256 = hash_folder(&folder).map_err(|e| io("hashing", e))?;
        record.sha256.extend(calibration);
        let text = serde_json::to_string_pretty(&record).map_err(|e| TestError::Io(e.to_string()))?;
        let tmp = folder.join("test.json.tmp");
        std::fs::write(&tmp, text + "\n").map_err(|e| io("test.json", e))?;
        std::fs::rename(&tmp, folder.join("test.json")).map_err(|e| io("test.json", e))?;
        let after = sha256_file(&folder.join("test.json")).map_err(|e| io("test.json", e))?;
        let report_sha = sha256_file(&folder.join(REPORT_JSON)).ok();
        let detail = serde_json::json!({"reason": reason, "previous": previous, "test_json_sha256_before": before,
            "test_json_sha256": after, "report_json_sha256": report_sha});
        let entry = self.audit_locked(&mut log, actor, "reanalysis", Some(id), detail)?;
        Ok(serde_json::json!({"id": id, "previous": previous, "report_json_sha256": report_sha, "audit_seq": entry.seq}))
    }
}

/// Who the automatic start and stop (`[output.auto_test]`) are in the audit log: user `auto`,
/// role `operator`.
pub fn auto_actor() -> Actor {
    Actor { user: "auto".into(), role: tagdeflect_core::users::Role::Operator }
}

impl LabTests {
    /// The audit line of an automatic start, on a short thread of its own (the start is made
    /// on the solver's thread, which an fsync must not hold up).
    pub(super) fn audit_auto_start(self: &std::sync::Arc<Self>, id: String, why: String) {
        let me = self.clone();
        let spawned = std::thread::Builder::new().name("audit".into()).spawn(move || {
            let _ = me.audit(&auto_actor(), "start", Some(&id), serde_json::json!({ "why": why }));
        });
        if let Err(e) = spawned {
            tracing::error!("cannot write the automatic start to the audit log: {e}");
        }
    }
}

/// Appends one JSON line to `path`, fsync'd.
fn append_line(path: &Path, value: &impl serde::Serialize) -> std::io::Result<()> {
    let mut line = serde_json::to_vec(value).map_err(std::io::Error::other)?;
    line.push(b'\n');
    let mut f = std::fs::OpenOptions::new().create(true).append(true).open(path)?;
    f.write_all(&line)?;
    f.sync_data()
}
