//! The audit trail of a tests folder, `<tests>/audit.jsonl` (docs/audit.md): one JSON object a
//! line, appended and fsync'd, never rewritten, each line chained to the one before it by the
//! SHA-256 of that line, so an edited, deleted, reordered or forged line is found by
//! [`verify_chain`] and named by its line number.
//!
//! A line's `sha256` is the SHA-256 of the line serialised without its `sha256` key (the
//! fields in [`AuditEntry`]'s order, `serde_json` compact); its `prev_sha256` is the previous
//! line's `sha256`, or [`GENESIS_SHA256`] (64 zeros) on the first line; `seq` counts from 0.

use std::fs::File;
use std::io::{BufRead, BufReader, Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use sha2::Digest;

/// The `prev_sha256` of the first line: 64 zeros.
pub const GENESIS_SHA256: &str = "0000000000000000000000000000000000000000000000000000000000000000";

/// The longest line read back, bytes (an entry is a few hundred bytes; a longer line is not ours).
pub const MAX_LINE_BYTES: usize = 1 << 20;

/// One action as the code that did it describes it: [`AuditLog::append`] numbers, links and
/// seals it into an [`AuditEntry`].
#[derive(Debug, Clone, PartialEq)]
pub struct AuditAction {
    /// When, ns since the Unix epoch.
    pub t_ns: i64,
    /// Who (a user's name, `shared-token` for the one shared token, `auto` for the automatic
    /// start and stop).
    pub user: String,
    /// Their role: `operator`, `reviewer` or `admin`.
    pub role: String,
    /// `start`, `stop`, `mark`, `zero`, `crack`, `method`, `specimens`, `reanalysis`, `sign`, `user`.
    pub action: String,
    /// The test it concerns, if any.
    pub test: Option<String>,
    /// What else belongs to it (a JSON object: a mark's note, test.json's hash, a reason).
    pub detail: serde_json::Value,
}

/// One line of `audit.jsonl`, as written.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AuditEntry {
    /// The line's number in the chain, from 0.
    pub seq: u64,
    /// When, ns since the Unix epoch.
    pub t_ns: i64,
    /// Who.
    pub user: String,
    /// Their role.
    pub role: String,
    /// What (see [`AuditAction::action`]).
    pub action: String,
    /// The test it concerns (`null` when none).
    pub test: Option<String>,
    /// What else belongs to it.
    pub detail: serde_json::Value,
    /// The previous line's `sha256` ([`GENESIS_SHA256`] on the first line).
    pub prev_sha256: String,
    /// This line's hash: SHA-256 of the line without this key.
    pub sha256: String,
}

/// The fields that are hashed: an [`AuditEntry`] without its `sha256`, in the same order.
#[derive(Serialize)]
struct Sealed<'a> {
    seq: u64,
    t_ns: i64,
    user: &'a str,
    role: &'a str,
    action: &'a str,
    test: &'a Option<String>,
    detail: &'a serde_json::Value,
    prev_sha256: &'a str,
}

impl AuditEntry {
    /// The SHA-256 (hex) this entry's `sha256` must hold: of its JSON without `sha256`.
    pub fn expected_sha256(&self) -> String {
        let sealed = Sealed {
            seq: self.seq,
            t_ns: self.t_ns,
            user: &self.user,
            role: &self.role,
            action: &self.action,
            test: &self.test,
            detail: &self.detail,
            prev_sha256: &self.prev_sha256,
        };
        let bytes = serde_json::to_vec(&sealed).expect("an audit entry serialises");
        hex(&sha2::Sha256::digest(bytes))
    }
}

/// Lower-case hex of `bytes`.
pub fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// What a whole, unbroken chain holds.
#[derive(Debug, Clone, PartialEq)]
pub struct ChainSummary {
    /// Its lines.
    pub entries: u64,
    /// The last line's `sha256` ([`GENESIS_SHA256`] for an empty log).
    pub last_sha256: String,
    /// The last line's time, if any.
    pub last_t_ns: Option<i64>,
}

/// Where and how a chain is broken.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ChainBroken {
    /// The file cannot be read.
    #[error("{path}: cannot read the audit log: {message}")]
    Unreadable {
        /// The log.
        path: PathBuf,
        /// The system's words.
        message: String,
    },
    /// A line is not an audit entry (edited into something else, or torn by a crash).
    #[error("{path}:{line}: not an audit entry: {message}")]
    NotAnEntry {
        /// The log.
        path: PathBuf,
        /// 1-based line number.
        line: u64,
        /// What the parser said.
        message: String,
    },
    /// The last line has no end: a write torn by a crash (or a cut file).
    #[error("{path}:{line}: the last line is torn (no line end): a write cut short; nothing is appended after it until it is looked at")]
    TornTail {
        /// The log.
        path: PathBuf,
        /// 1-based line number.
        line: u64,
    },
    /// A line's own hash does not match its content (a field edited).
    #[error("{path}:{line}: sha256 {found} does not match the line's content (expected {expected}): the line was changed")]
    HashMismatch {
        /// The log.
        path: PathBuf,
        /// 1-based line number.
        line: u64,
        /// The hash written.
        found: String,
        /// The hash of the content.
        expected: String,
    },
    /// A line's `seq` is not the one after the previous line's (a line deleted or moved).
    #[error("{path}:{line}: seq {found} where {expected} follows: a line was deleted, inserted or moved")]
    SeqGap {
        /// The log.
        path: PathBuf,
        /// 1-based line number.
        line: u64,
        /// The `seq` written.
        found: u64,
        /// The `seq` expected.
        expected: u64,
    },
    /// A line's `prev_sha256` is not the previous line's `sha256` (a line replaced or forged).
    #[error("{path}:{line}: prev_sha256 {found} is not the previous line's sha256 {expected}: the chain is broken here")]
    PrevLink {
        /// The log.
        path: PathBuf,
        /// 1-based line number.
        line: u64,
        /// The link written.
        found: String,
        /// The previous line's hash.
        expected: String,
    },
}

impl ChainBroken {
    /// The 1-based line number where the chain breaks (`None` when the file is unreadable).
    pub fn line(&self) -> Option<u64> {
        match self {
            ChainBroken::Unreadable { .. } => None,
            ChainBroken::NotAnEntry { line, .. }
            | ChainBroken::TornTail { line, .. }
            | ChainBroken::HashMismatch { line, .. }
            | ChainBroken::SeqGap { line, .. }
            | ChainBroken::PrevLink { line, .. } => Some(*line),
        }
    }
}

/// The end of the chain an append continues from.
#[derive(Debug, Clone, PartialEq)]
struct Tail {
    next_seq: u64,
    last_sha256: String,
    /// The file's length when the tail was read: a longer file was appended to by another
    /// process and its tail is read again.
    len: u64,
}

/// Checks one parsed line against the chain so far (`None` before the first line).
fn check_link(path: &Path, line: u64, entry: &AuditEntry, prev: Option<(u64, &str)>) -> Result<(), ChainBroken> {
    let expected = entry.expected_sha256();
    if entry.sha256 != expected {
        let found = entry.sha256.clone();
        return Err(ChainBroken::HashMismatch { path: path.into(), line, found, expected });
    }
    let (want_seq, want_prev) = match prev {
        None => (0, GENESIS_SHA256),
        Some((seq, sha)) => (seq + 1, sha),
    };
    if entry.seq != want_seq {
        return Err(ChainBroken::SeqGap { path: path.into(), line, found: entry.seq, expected: want_seq });
    }
    if entry.prev_sha256 != want_prev {
        let (found, expected) = (entry.prev_sha256.clone(), want_prev.to_string());
        return Err(ChainBroken::PrevLink { path: path.into(), line, found, expected });
    }
    Ok(())
}

/// Reads the log's lines, calling `each(line_number, entry)`; a line without its end is
/// [`ChainBroken::TornTail`], a line that is not an entry [`ChainBroken::NotAnEntry`].
fn read_entries(path: &Path, file: &File, mut each: impl FnMut(u64, AuditEntry) -> Result<(), ChainBroken>) -> Result<u64, ChainBroken> {
    let unreadable = |e: std::io::Error| ChainBroken::Unreadable { path: path.into(), message: e.to_string() };
    let mut reader = BufReader::new(file);
    reader.seek(SeekFrom::Start(0)).map_err(unreadable)?;
    let (mut buf, mut line, mut len) = (Vec::new(), 0u64, 0u64);
    loop {
        buf.clear();
        let n = (&mut reader).take(MAX_LINE_BYTES as u64 + 1).read_until(b'\n', &mut buf).map_err(unreadable)?;
        if n == 0 {
            return Ok(len);
        }
        line += 1;
        len += n as u64;
        if buf.last() != Some(&b'\n') {
            if n > MAX_LINE_BYTES {
                let message = format!("longer than {MAX_LINE_BYTES} bytes");
                return Err(ChainBroken::NotAnEntry { path: path.into(), line, message });
            }
            return Err(ChainBroken::TornTail { path: path.into(), line });
        }
        let entry: AuditEntry = serde_json::from_slice(&buf[..n - 1]).map_err(|e| ChainBroken::NotAnEntry {
            path: path.into(),
            line,
            message: e.to_string(),
        })?;
        each(line, entry)?;
    }
}

/// Verifies the whole chain of the log at `path`: every line an entry whose hash matches its
/// content, numbered from 0 without a gap, linked to the line before. A missing file is an
/// empty chain. The first break is named by its line number and what is wrong.
pub fn verify_chain(path: &Path) -> Result<ChainSummary, ChainBroken> {
    let file = match File::open(path) {
        Ok(f) => f,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            return Ok(ChainSummary { entries: 0, last_sha256: GENESIS_SHA256.into(), last_t_ns: None })
        }
        Err(e) => return Err(ChainBroken::Unreadable { path: path.into(), message: e.to_string() }),
    };
    let mut prev: Option<(u64, String, i64)> = None;
    read_entries(path, &file, |line, entry| {
        check_link(path, line, &entry, prev.as_ref().map(|(s, h, _)| (*s, h.as_str())))?;
        prev = Some((entry.seq, entry.sha256, entry.t_ns));
        Ok(())
    })?;
    Ok(match prev {
        None => ChainSummary { entries: 0, last_sha256: GENESIS_SHA256.into(), last_t_ns: None },
        Some((seq, sha, t)) => ChainSummary { entries: seq + 1, last_sha256: sha, last_t_ns: Some(t) },
    })
}

/// Why an action could not be appended.
#[derive(Debug, thiserror::Error)]
pub enum AuditError {
    /// The log's end is not a sound line (torn by a crash, or edited): nothing is appended
    /// after it until someone has looked.
    #[error("{0}")]
    Chain(#[from] ChainBroken),
    /// Writing failed.
    #[error("{path}: cannot append to the audit log: {source}")]
    Io {
        /// The log.
        path: PathBuf,
        /// The system's error.
        source: std::io::Error,
    },
}

/// An open audit log: the chain's tail read once at open and kept, each append one line
/// written and fsync'd under an exclusive lock on the file (another process that appended in
/// between — `tagdeflect user add` beside the daemon — is noticed by the file's length and its
/// tail read again).
#[derive(Debug)]
pub struct AuditLog {
    path: PathBuf,
    file: File,
    tail: Tail,
}

impl AuditLog {
    /// Opens (creates) the log at `path` and reads its tail. The last line must be a whole
    /// entry whose own hash matches: a torn or edited last line is reported, never extended.
    /// (The whole chain is checked by [`verify_chain`].)
    pub fn open(path: &Path) -> Result<AuditLog, AuditError> {
        let io = |source| AuditError::Io { path: path.into(), source };
        let file = std::fs::OpenOptions::new().read(true).append(true).create(true).open(path).map_err(io)?;
        file.lock_shared().map_err(io)?;
        let tail = read_tail(path, &file);
        file.unlock().map_err(io)?;
        Ok(AuditLog { path: path.into(), file, tail: tail? })
    }

    /// The log's path.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Appends `action` as the chain's next line (numbered, linked, hashed), fsync'd before it
    /// returns; gives the entry written.
    pub fn append(&mut self, action: AuditAction) -> Result<AuditEntry, AuditError> {
        let io = |source| AuditError::Io { path: self.path.clone(), source };
        self.file.lock().map_err(io)?;
        let written = self.append_locked(action);
        let unlocked = self.file.unlock().map_err(|source| AuditError::Io { path: self.path.clone(), source });
        let entry = written?;
        unlocked?;
        Ok(entry)
    }

    fn append_locked(&mut self, action: AuditAction) -> Result<AuditEntry, AuditError> {
        let io = |source| AuditError::Io { path: self.path.clone(), source };
        if self.file.metadata().map_err(io)?.len() != self.tail.len {
            self.tail = read_tail(&self.path, &self.file)?;
        }
        let mut entry = AuditEntry {
            seq: self.tail.next_seq,
            t_ns: action.t_ns,
            user: action.user,
            role: action.role,
            action: action.action,
            test: action.test,
            detail: action.detail,
            prev_sha256: self.tail.last_sha256.clone(),
            sha256: String::new(),
        };
        entry.sha256 = entry.expected_sha256();
        let mut line = serde_json::to_vec(&entry).expect("an audit entry serialises");
        line.push(b'\n');
        self.file.write_all(&line).map_err(io)?;
        self.file.sync_data().map_err(io)?;
        self.tail = Tail { next_seq: entry.seq + 1, last_sha256: entry.sha256.clone(), len: self.tail.len + line.len() as u64 };
        Ok(entry)
    }
}

/// Reads the log's last line into a [`Tail`], checking that it is whole and sealed.
fn read_tail(path: &Path, file: &File) -> Result<Tail, AuditError> {
    let mut last: Option<(u64, AuditEntry)> = None;
    let len = read_entries(path, file, |line, entry| {
        last = Some((line, entry));
        Ok(())
    })?;
    match last {
        None => Ok(Tail { next_seq: 0, last_sha256: GENESIS_SHA256.into(), len }),
        Some((line, entry)) => {
            let expected = entry.expected_sha256();
            if entry.sha256 != expected {
                let found = entry.sha256;
                return Err(ChainBroken::HashMismatch { path: path.into(), line, found, expected }.into());
            }
            Ok(Tail { next_seq: entry.seq + 1, last_sha256: entry.sha256, len })
        }
    }
}

/// Opens the log at `path`, appends `action` and closes it (one-off writers: the command line).
pub fn append(path: &Path, action: AuditAction) -> Result<AuditEntry, AuditError> {
    AuditLog::open(path)?.append(action)
}

#[cfg(test)]
mod tests;
