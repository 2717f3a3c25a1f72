//! `tagdeflect report verify DIR`: the inputs `report.json` lists (`inputs.files`, each with
//! its SHA-256) hashed again; what changed, went missing or stayed the same.

use std::path::Path;

use crate::error::ReportError;
use crate::output::sha256_file;

/// The state of one input.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum InputState {
    /// Same SHA-256 as when the report was made.
    Same,
    /// Different content.
    Changed,
    /// The file is gone (or unreadable).
    Missing(String),
}

/// One input checked.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Checked {
    /// Its role (`feed`, `utm`, `config`, `calibration`).
    pub role: String,
    /// Its path as `report.json` gives it.
    pub path: String,
    /// What was found.
    pub state: InputState,
}

/// Checks the inputs of the report in `dir`; also the software version it was made with.
pub fn verify(dir: &Path) -> Result<(Vec<Checked>, String), ReportError> {
    let p = dir.join("report.json");
    let text = std::fs::read_to_string(&p).map_err(|e| ReportError::Io { path: p.clone(), message: format!("cannot read: {e}") })?;
    let v: serde_json::Value =
        serde_json::from_str(&text).map_err(|e| ReportError::Data { path: p.clone(), message: format!("not a report: {e}") })?;
    let files = v["inputs"]["files"].as_array().ok_or_else(|| ReportError::Data {
        path: p.clone(),
        message: "no `inputs.files`: a report made before inputs were recorded".into(),
    })?;
    let mut out = Vec::new();
    for f in files {
        let (Some(role), Some(path), Some(sha)) = (f["role"].as_str(), f["path"].as_str(), f["sha256"].as_str()) else {
            return Err(ReportError::Data { path: p.clone(), message: format!("an input without role, path or sha256: {f}") });
        };
        let state = match sha256_file(Path::new(path)) {
            Ok(h) if h == sha => InputState::Same,
            Ok(_) => InputState::Changed,
            Err(e) => InputState::Missing(e.to_string()),
        };
        out.push(Checked { role: role.to_string(), path: path.to_string(), state });
    }
    Ok((out, v["inputs"]["software"]["version"].as_str().unwrap_or("unknown").to_string()))
}
