//! `tagdeflect report verify DIR`: the folder it is given checked, not the paths a report
//! recorded — a copied folder verifies where it lies, a tampered one names what changed:
//!
//! * every input `report.json` lists (`inputs.files`), found by its `name` relative to the
//!   report folder's parent (a test folder's `report/` → the test folder): the first `bytes`
//!   bytes it had when the report hashed it; a feed or UTM stream longer now (still being
//!   written when the report was made) is [`InputState::Grown`], which verifies;
//! * every output of the report (`outputs`: name → SHA-256; `report.json` itself aside);
//! * the test folder's `test.json` `sha256` map against the folder's files (changed,
//!   missing, extra);
//! * each signature of `signatures.jsonl` against `report.json`'s SHA-256;
//! * the tests folder's audit chain (`<test folder>/../audit.jsonl`), checked by the caller
//!   ([`Chain`]) with `tagdeflect_core::audit::verify_chain`.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use crate::error::ReportError;
use crate::output::{sha256_file, sha256_prefix};

/// The state of one file.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum InputState {
    /// Same SHA-256 as recorded.
    Same,
    /// Different content.
    Changed,
    /// The file is gone (or unreadable).
    Missing(String),
    /// A file of the folder that the record does not list.
    Extra,
    /// A feed or UTM stream longer than when the report hashed it (written to since), its
    /// first `then` bytes (all the report read) unchanged: it verifies.
    Grown {
        /// Its length when hashed.
        then: u64,
        /// Its length now.
        now: u64,
    },
}

/// One file checked.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Checked {
    /// What it is: an input's role (`feed`, `utm`, `config`, `calibration`), `output`,
    /// `test.json`, `signature`, `audit`.
    pub role: String,
    /// Its path as checked.
    pub path: String,
    /// What was found.
    pub state: InputState,
}

impl Checked {
    /// True when nothing the record covers changed (a stream grown after it counts as same).
    pub fn same(&self) -> bool {
        matches!(self.state, InputState::Same | InputState::Grown { .. })
    }
}

/// The folders `verify` works on: the report's and the test folder around it (if any).
#[derive(Debug, Clone, PartialEq)]
pub struct Folders {
    /// Holds `report.json`.
    pub report: PathBuf,
    /// What input names are relative to: the report folder's parent.
    pub base: PathBuf,
    /// The test folder (holding `test.json`), when there is one.
    pub test: Option<PathBuf>,
}

/// DIR as given: a test folder (its `report/`), or a report folder.
pub fn folders(dir: &Path) -> Result<Folders, ReportError> {
    let (report, test) = if dir.join("test.json").is_file() && !dir.join("report.json").is_file() {
        (dir.join("report"), Some(dir.to_path_buf()))
    } else {
        let parent = dir.parent().filter(|p| p.join("test.json").is_file()).map(Path::to_path_buf);
        (dir.to_path_buf(), parent)
    };
    if !report.join("report.json").is_file() {
        return Err(ReportError::Io { path: report.join("report.json"), message: "no report.json: not a report or test folder".into() });
    }
    let base = report.parent().map_or_else(|| PathBuf::from("."), Path::to_path_buf);
    let base = if base.as_os_str().is_empty() { PathBuf::from(".") } else { base };
    Ok(Folders { report, base, test })
}

fn state_of(path: &Path, sha: &str) -> InputState {
    match sha256_file(path) {
        Ok(h) if h == sha => InputState::Same,
        Ok(_) => InputState::Changed,
        Err(e) => InputState::Missing(e.to_string()),
    }
}

/// The inputs written while a report may be made from them (appended to, never rewritten).
const GROWS: [&str; 2] = ["feed", "utm"];

/// An input recorded with its length: its first `bytes` bytes against `sha`; longer now is
/// [`InputState::Grown`] when `grows`, else changed; shorter is changed.
fn prefix_state(path: &Path, sha: &str, bytes: u64, grows: bool) -> InputState {
    let now = match std::fs::metadata(path) {
        Ok(m) => m.len(),
        Err(e) => return InputState::Missing(e.to_string()),
    };
    match sha256_prefix(path, Some(bytes)) {
        Ok((h, n)) if h == sha && n == bytes && now == bytes => InputState::Same,
        Ok((h, n)) if h == sha && n == bytes && grows => InputState::Grown { then: bytes, now },
        Ok(_) => InputState::Changed,
        Err(e) => InputState::Missing(e.to_string()),
    }
}

/// What was found, and the software version the report was made with.
#[derive(Debug, Clone, PartialEq)]
pub struct Verified {
    /// Every file checked.
    pub checked: Vec<Checked>,
    /// The version that made the report.
    pub version: String,
    /// The folders.
    pub folders: Folders,
}

impl Verified {
    /// Everything that is not as recorded.
    pub fn changes(&self) -> Vec<&Checked> {
        self.checked.iter().filter(|c| !c.same()).collect()
    }
}

/// Checks the report (and test) folder `dir` as it lies.
pub fn verify(dir: &Path) -> Result<Verified, ReportError> {
    let folders = folders(dir)?;
    let p = folders.report.join("report.json");
    let text = std::fs::read_to_string(&p).map_err(|e| ReportError::Io { path: p.clone(), message: format!("cannot read: {e}") })?;
    let v: serde_json::Value =
        serde_json::from_str(&text).map_err(|e| ReportError::Data { path: p.clone(), message: format!("not a report: {e}") })?;
    let mut checked = inputs(&v, &folders, &p)?;
    checked.extend(outputs(&v, &folders));
    let report_sha = sha256_file(&p).map_err(|e| ReportError::Io { path: p.clone(), message: e.to_string() })?;
    if let Some(t) = &folders.test {
        checked.extend(test_record(t)?);
        checked.extend(record_vs_report(t, &v));
        checked.extend(signatures(t, &report_sha));
    }
    let version = v["inputs"]["software"]["version"].as_str().unwrap_or("unknown").to_string();
    Ok(Verified { checked, version, folders })
}

/// The inputs, each by its name relative to the base (reports made before names were
/// recorded: the file name of the recorded path).
fn inputs(v: &serde_json::Value, f: &Folders, p: &Path) -> Result<Vec<Checked>, ReportError> {
    let files = v["inputs"]["files"].as_array().ok_or_else(|| ReportError::Data {
        path: p.to_path_buf(),
        message: "no `inputs.files`: a report made before inputs were recorded".into(),
    })?;
    let mut out = Vec::new();
    for file in files {
        let (Some(role), Some(path), Some(sha)) = (file["role"].as_str(), file["path"].as_str(), file["sha256"].as_str()) else {
            return Err(ReportError::Data { path: p.to_path_buf(), message: format!("an input without role, path or sha256: {file}") });
        };
        let name =
            file["name"].as_str().map(PathBuf::from).unwrap_or_else(|| Path::new(path).file_name().map(PathBuf::from).unwrap_or_default());
        let here = f.base.join(&name);
        let state = match file["bytes"].as_u64() {
            Some(bytes) => prefix_state(&here, sha, bytes, GROWS.contains(&role)),
            None => state_of(&here, sha),
        };
        out.push(Checked { role: role.to_string(), path: here.display().to_string(), state });
    }
    Ok(out)
}

/// Every output the report lists, in its folder.
fn outputs(v: &serde_json::Value, f: &Folders) -> Vec<Checked> {
    let Some(map) = v["outputs"].as_object() else {
        return vec![Checked {
            role: "output".into(),
            path: f.report.join("report.json").display().to_string(),
            state: InputState::Missing("no `outputs` in report.json: a report made before its outputs were hashed".into()),
        }];
    };
    map.iter()
        .map(|(name, sha)| {
            let here = f.report.join(name);
            Checked { role: "output".into(), path: here.display().to_string(), state: state_of(&here, sha.as_str().unwrap_or_default()) }
        })
        .collect()
}

/// `test.json`'s `sha256` map against the test folder's files: changed, missing, extra.
fn test_record(t: &Path) -> Result<Vec<Checked>, ReportError> {
    let p = t.join("test.json");
    let text = std::fs::read_to_string(&p).map_err(|e| ReportError::Io { path: p.clone(), message: e.to_string() })?;
    let v: serde_json::Value =
        serde_json::from_str(&text).map_err(|e| ReportError::Data { path: p.clone(), message: format!("not a test record: {e}") })?;
    let map: BTreeMap<String, String> =
        serde_json::from_value(v["sha256"].clone()).map_err(|e| ReportError::Data { path: p.clone(), message: format!("sha256: {e}") })?;
    let mut out: Vec<Checked> = map
        .iter()
        .map(|(name, sha)| {
            let here = if Path::new(name).is_absolute() { PathBuf::from(name) } else { t.join(name) };
            Checked { role: "test.json".into(), path: here.display().to_string(), state: state_of(&here, sha) }
        })
        .collect();
    for rel in folder_files(t) {
        let skip = rel == "test.json" || rel == "signatures.jsonl" || rel.ends_with(".tmp");
        if !skip && !map.contains_key(&rel) {
            out.push(Checked { role: "test.json".into(), path: t.join(&rel).display().to_string(), state: InputState::Extra });
        }
    }
    Ok(out)
}

/// `test.json` against what the report took from it (specimen, operator, events, the
/// measured dimensions it used): test.json hashes every other file but not itself, so an
/// edit of it shows here.
fn record_vs_report(t: &Path, report: &serde_json::Value) -> Vec<Checked> {
    let p = t.join("test.json");
    let Ok(rec) = std::fs::read_to_string(&p).map_err(|_| ()).and_then(|s| serde_json::from_str::<serde_json::Value>(&s).map_err(|_| ()))
    else {
        return Vec::new();
    };
    let spec = &report["specimen"];
    let mut pairs =
        vec![("specimen", rec["specimen"].clone(), spec["id"].clone()), ("operator", rec["operator"].clone(), report["operator"].clone())];
    if report.get("events").is_some() {
        // The report adds each mark's load (`load_kN`, from the curve): the rest is test.json's.
        let mut taken = report["events"].clone();
        for e in taken.as_array_mut().into_iter().flatten() {
            if let Some(o) = e.as_object_mut() {
                o.remove("load_kN");
            }
        }
        pairs.push(("events", rec["events"].clone(), taken));
    }
    if let Some(src) = spec["dimension_sources"].as_object() {
        for (k, from) in src {
            if from == "test.json" {
                pairs.push(("measured", rec["measured"][k].clone(), spec[k].clone()));
            }
        }
    }
    pairs
        .into_iter()
        .filter(|(_, a, b)| !a.is_null() || !b.is_null())
        .map(|(key, in_record, in_report)| {
            let same = in_record == in_report || (in_record.as_f64().is_some() && in_record.as_f64() == in_report.as_f64());
            let path = if same {
                format!("{} `{key}` as the report took it", p.display())
            } else {
                format!("{} `{key}` is {in_record}, the report took {in_report}", p.display())
            };
            Checked { role: "test.json".into(), path, state: if same { InputState::Same } else { InputState::Changed } }
        })
        .collect()
}

/// Every file under `dir`, by path relative to it.
fn folder_files(dir: &Path) -> Vec<String> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        let Ok(rd) = std::fs::read_dir(&d) else { continue };
        for e in rd.flatten() {
            let p = e.path();
            if p.is_dir() {
                stack.push(p);
            } else if let Ok(rel) = p.strip_prefix(dir) {
                out.push(rel.to_string_lossy().into_owned());
            }
        }
    }
    out.sort();
    out
}

/// Each signature (`signatures.jsonl`) against the report it signed.
fn signatures(t: &Path, report_sha: &str) -> Vec<Checked> {
    let p = t.join("signatures.jsonl");
    let Ok(text) = std::fs::read_to_string(&p) else { return Vec::new() };
    text.lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty())
        .map(|(i, l)| {
            let v: serde_json::Value = serde_json::from_str(l).unwrap_or_default();
            let who = format!("{}:{} by {} ({})", p.display(), i + 1, v["by"].as_str().unwrap_or("?"), v["meaning"].as_str().unwrap_or(""));
            let state = match v["report_json_sha256"].as_str() {
                Some(s) if s == report_sha => InputState::Same,
                Some(_) => InputState::Changed,
                None => InputState::Missing("not a signature line".into()),
            };
            Checked { role: "signature".into(), path: who, state }
        })
        .collect()
}

/// The audit chain's result as the caller found it (`tagdeflect_core::audit::verify_chain`
/// on `<test folder>/../audit.jsonl`): `Ok(entries)` or `Err(what is broken)`.
pub type Chain = Result<u64, String>;

/// The audit chain's result as a checked item.
pub fn chain_checked(path: &Path, chain: Chain) -> Checked {
    match chain {
        Ok(n) => Checked { role: "audit".into(), path: format!("{} ({n} entries, chain whole)", path.display()), state: InputState::Same },
        Err(why) => Checked { role: "audit".into(), path: format!("{}: {why}", path.display()), state: InputState::Changed },
    }
}

/// Where the audit log of the test folder `t` lies: `<t>/../audit.jsonl`.
pub fn audit_log_of(t: &Path) -> PathBuf {
    t.parent().map_or_else(|| PathBuf::from("audit.jsonl"), |p| p.join("audit.jsonl"))
}
