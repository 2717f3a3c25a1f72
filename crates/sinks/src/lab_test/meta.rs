//! What a test is started with ([`TestMeta`], checked as an operator typed it) and why a
//! command is refused ([`TestError`]).

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};
use tagdeflect_core::Problem;

/// What a test is started with (the control API's JSON body).
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TestMeta {
    /// The specimen's id (required; letters, digits, `_`, `-`, `.`).
    pub specimen: String,
    /// Who runs the test.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub operator: Option<String>,
    /// `astm-c1609`, `astm-c1856` or `en-14651`: the report made at stop.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub standard: Option<String>,
    /// Free text.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub notes: Option<String>,
    /// Measured dimensions and other values the lab records (`{"width_mm": 150.2}`).
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub measured: BTreeMap<String, f64>,
}

/// Standards a test may name.
pub const STANDARDS: [&str; 3] = ["astm-c1609", "astm-c1856", "en-14651"];

impl TestMeta {
    /// Checks what an operator typed: the specimen id is a folder name and text on the page.
    /// The problem's key is the field's (`specimen`, `standard`, `operator`, `notes`,
    /// `measured.NAME`); its message names the field itself, as it is answered to the operator
    /// as is ([`TestError::Bad`]).
    pub fn validate(&self) -> Result<(), Problem> {
        let ok = |c: char| c.is_alphanumeric() || matches!(c, '_' | '-' | '.');
        let sp = self.specimen.trim();
        if sp.is_empty() || sp.chars().count() > 64 || sp.starts_with('.') || !sp.chars().all(ok) {
            return Err(Problem::new(
                "specimen",
                format!("specimen \"{}\": 1 to 64 letters, digits, `_`, `-` and `.` (not first)", self.specimen.escape_debug()),
            ));
        }
        if let Some(s) = &self.standard {
            if !STANDARDS.contains(&s.as_str()) {
                return Err(Problem::new("standard", format!("standard \"{}\": one of {}", s.escape_debug(), STANDARDS.join(", "))));
            }
        }
        for (k, text) in [("operator", &self.operator), ("notes", &self.notes)] {
            if text.as_ref().is_some_and(|t| t.len() > 4096 || t.chars().any(|c| c.is_control() && c != '\n')) {
                return Err(Problem::new(k, format!("{k}: at most 4096 characters, no control characters")));
            }
        }
        if let Some((k, v)) = self.measured.iter().find(|(k, v)| !v.is_finite() || k.len() > 64) {
            return Err(Problem::new(format!("measured.{k}"), format!("measured.{k} = {v}: a finite number under a short name")));
        }
        Ok(())
    }
}

/// Why a command was refused.
#[derive(Debug, thiserror::Error)]
pub enum TestError {
    /// The command does not fit the state (start while running, stop while idle): HTTP 409.
    #[error("{0}")]
    Conflict(String),
    /// The request is malformed: HTTP 400.
    #[error("{0}")]
    Bad(String),
    /// The folder could not be written: HTTP 500.
    #[error("{0}")]
    Io(String),
}

impl From<Problem> for TestError {
    /// A request that does not pass [`TestMeta::validate`]: malformed (its message as is).
    fn from(p: Problem) -> Self {
        TestError::Bad(p.message)
    }
}
