//! A test folder as the report reads it (SPEC "Tests" and "Report"): one function,
//! [`prepare`], turns a test's record (`test.json`, or the record in memory at the test's
//! stop) and the config's rig and `[report]` into the report's inputs, so the report made at
//! the stop, `report DIR` and `report --series` compute from the same values.
//!
//! The rule: `test.json`'s measured dimensions (`measured`: `width_mm`, `depth_mm`, `span_mm`,
//! `notch_mm`), `specimen`, `operator`, `notes`, `events`, `method`, `specimen_info` and
//! `crack` win over the config; its values are range-checked as at the test's start
//! ([`TestMeta::validate`]) and a value out of range is one error naming the file and key.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use tagdeflect_core::feed::FeedEvent;
use tagdeflect_core::lab_test::TestMeta;

use crate::config::{BeamConfig, ReportConfig};
use crate::error::ReportError;
use crate::report::TestRig;
use crate::standard::Standard;

/// A review of a method by the lab (`test.json` `method.review`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MethodReview {
    /// Who reviewed it.
    pub by: String,
    /// When (RFC 3339).
    pub at: String,
    /// What the review means (e.g. "reviewed against C1609-19 §§ 8–9").
    #[serde(default)]
    pub meaning: String,
}

/// The method a test ran under, as `test.json` names it (`method`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MethodInfo {
    /// Its name (e.g. `C1609-19`).
    pub name: String,
    /// Its version.
    pub version: serde_json::Value,
    /// The standard it follows (`astm-c1609`, ...).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub standard: Option<String>,
    /// SHA-256 of the method file as used.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sha256: Option<String>,
    /// The lab's review, absent when the method was not reviewed (or changed since).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub review: Option<MethodReview>,
}

impl MethodInfo {
    /// `C1609-19 v2`.
    pub fn label(&self) -> String {
        let v = match &self.version {
            serde_json::Value::String(s) => s.clone(),
            other => other.to_string(),
        };
        format!("{} v{v}", self.name)
    }
}

/// The operator's crack entry (`test.json` `crack`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CrackInfo {
    /// Where the crack is, from mid-span (signed), mm.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub position_mm: Option<f64>,
    /// Inside the middle third of the span, as the operator entered it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub inside_middle_third: Option<bool>,
    /// When it was entered.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub t_ns: Option<i64>,
}

impl CrackInfo {
    /// Inside the middle third: the operator's word, else |position| ≤ span/6.
    pub fn inside(&self, span_mm: f64) -> Option<bool> {
        self.inside_middle_third.or_else(|| self.position_mm.map(|p| p.abs() <= span_mm / 6.0))
    }
}

/// What the report takes from a test's record (read tolerantly: every key optional, unknown
/// keys ignored, so records of every version read).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct TestView {
    /// The test's id.
    #[serde(default)]
    pub id: String,
    /// The specimen's id.
    #[serde(default)]
    pub specimen: String,
    /// Who ran the test.
    #[serde(default)]
    pub operator: Option<String>,
    /// The standard of the report made at the stop.
    #[serde(default)]
    pub standard: Option<String>,
    /// The operator's notes.
    #[serde(default)]
    pub notes: Option<String>,
    /// Measured dimensions, mm.
    #[serde(default)]
    pub measured: BTreeMap<String, f64>,
    /// Start, marks, zeros, cracks, stop.
    #[serde(default)]
    pub events: Vec<FeedEvent>,
    /// The method the test ran under.
    #[serde(default)]
    pub method: Option<MethodInfo>,
    /// The specimen's row from the table entered beforehand.
    #[serde(default)]
    pub specimen_info: Option<serde_json::Map<String, serde_json::Value>>,
    /// The operator's crack entry.
    #[serde(default)]
    pub crack: Option<CrackInfo>,
    /// The verification in force when the test ran (`[verification]`).
    #[serde(default)]
    pub verification: Option<tagdeflect_core::verification::InForce>,
}

impl TestView {
    /// Reads `test.json` and range-checks it; an error names the file and the key.
    pub fn read(path: &Path) -> Result<TestView, ReportError> {
        let text = std::fs::read_to_string(path)
            .map_err(|e| ReportError::Io { path: path.to_path_buf(), message: format!("cannot read: {e}") })?;
        let view: TestView = serde_json::from_str(&text)
            .map_err(|e| ReportError::Data { path: path.to_path_buf(), message: format!("not a test record: {e}") })?;
        view.checked(path)
    }

    /// The view of a record held in memory (any type serialising as `test.json`), checked
    /// like [`TestView::read`]; `path` names it in errors.
    pub fn of_record<T: Serialize>(record: &T, path: &Path) -> Result<TestView, ReportError> {
        let err = |e: serde_json::Error| ReportError::Data { path: path.to_path_buf(), message: format!("not a test record: {e}") };
        let view: TestView = serde_json::from_value(serde_json::to_value(record).map_err(err)?).map_err(err)?;
        view.checked(path)
    }

    /// The checks of a test's start ([`TestMeta::validate`]) on the record's values. The
    /// specimen id is not checked as a folder name here: the report only shows it (escaped)
    /// and a series makes its folder name safe.
    fn checked(self, path: &Path) -> Result<TestView, ReportError> {
        let meta = TestMeta {
            specimen: "specimen".into(),
            operator: self.operator.clone(),
            standard: self.standard.clone(),
            notes: self.notes.clone(),
            measured: self.measured.clone(),
        };
        meta.validate().map_err(|p| ReportError::Data { path: path.to_path_buf(), message: format!("{}: {}", p.key, p.message) })?;
        Ok(self)
    }

    /// The standard the record names, if any.
    pub fn standard(&self, path: &Path) -> Result<Option<Standard>, ReportError> {
        self.standard
            .as_deref()
            .map(|s| {
                serde_json::from_value(serde_json::json!(s))
                    .map_err(|e| ReportError::Data { path: path.to_path_buf(), message: format!("standard: {e}") })
            })
            .transpose()
    }
}

/// Where each dimension the report computes with came from: `test.json` or `config`.
pub type DimensionSources = BTreeMap<String, String>;

/// The report's inputs from a test folder.
#[derive(Debug, Clone)]
pub struct Prepared {
    /// The rig with the measured dimensions in its `[specimen.beam]`.
    pub rig: TestRig,
    /// The report's options with the test's standard and identification.
    pub opts: ReportConfig,
    /// Where each dimension came from.
    pub sources: DimensionSources,
    /// Why the test's method could not be applied (its file not found, or changed since the
    /// test): the report then applies the standard's built-in rules and warns.
    pub method_warning: Option<String>,
}

/// The one function that builds the report's inputs of a test: `rig` and `opts` are the
/// config's (`[specimen.beam]`, `[report]`), `view` the test's record; `standard` an
/// explicit choice (the command line), else the record's, else `opts`'s. `config_path`
/// names the config in errors.
pub fn prepare(
    view: &TestView,
    rig: &TestRig,
    opts: &ReportConfig,
    standard: Option<Standard>,
    record_path: &Path,
    config_path: &Path,
) -> Result<Prepared, ReportError> {
    let mut rig = rig.clone();
    let mut opts = opts.clone();
    if let Some(s) = standard.or(view.standard(record_path)?) {
        opts.standard = s;
    }
    let sources = apply_dimensions(&mut rig, &view.measured, config_path)?;
    let lab = &mut opts.lab;
    if !view.specimen.trim().is_empty() {
        lab.specimen = Some(view.specimen.clone());
    }
    if view.operator.as_deref().is_some_and(|o| !o.trim().is_empty()) {
        lab.operator = view.operator.clone();
    }
    if let Some(cast) = view.specimen_info.as_ref().and_then(|i| i.get("cast_date")).and_then(|v| v.as_str()) {
        lab.cast_date = Some(cast.to_string());
    }
    let (method, method_warning) = match &view.method {
        Some(m) => method_of(m, record_path),
        None => (None, None),
    };
    opts.method = method;
    Ok(Prepared { rig, opts, sources, method_warning })
}

/// The method file a test ran under, found as at its start (the tests folder's `methods/`,
/// else the shipped ones) and only when it is the very file the record names (its SHA-256);
/// otherwise why not.
fn method_of(m: &MethodInfo, record_path: &Path) -> (Option<tagdeflect_core::method::Method>, Option<String>) {
    use tagdeflect_core::method::library;
    let tests = record_path.parent().and_then(Path::parent).unwrap_or(Path::new("."));
    match library::find(tests, &m.name) {
        Ok(l) if m.sha256.as_deref().is_none_or(|h| h == l.sha256) => (Some(l.method), None),
        Ok(l) => (
            None,
            Some(format!(
                "the method {} file ({}) is not the one the test ran under (its SHA-256 differs): the standard's built-in rates and end were applied",
                m.label(),
                l.origin()
            )),
        ),
        Err(e) => (None, Some(format!("the test's method {} was not found ({e}): the standard's built-in rates and end were applied", m.label()))),
    }
}

/// The record's measured dimensions into `[specimen.beam]` (a beam made of them when the
/// config has none and width, depth and span are measured); where each came from.
fn apply_dimensions(rig: &mut TestRig, measured: &BTreeMap<String, f64>, config_path: &Path) -> Result<DimensionSources, ReportError> {
    let m = |k: &str| measured.get(k).copied();
    if rig.specimen.beam.is_none() {
        if let (Some(w), Some(d), Some(s)) = (m("width_mm"), m("depth_mm"), m("span_mm")) {
            rig.specimen.beam = Some(BeamConfig { width_mm: w, depth_mm: d, span_mm: s, ..Default::default() });
        }
    }
    let mut sources = DimensionSources::new();
    let Some(beam) = rig.specimen.beam.as_mut() else { return Ok(sources) };
    for key in ["width_mm", "depth_mm", "span_mm", "notch_mm"] {
        let slot = match key {
            "width_mm" => Some(&mut beam.width_mm),
            "depth_mm" => Some(&mut beam.depth_mm),
            "span_mm" => Some(&mut beam.span_mm),
            _ => beam.notch_mm.as_mut(),
        };
        match (m(key), slot) {
            (Some(v), Some(slot)) => {
                *slot = v;
                sources.insert(key.into(), "test.json".into());
            }
            (Some(v), None) => {
                beam.notch_mm = Some(v);
                sources.insert(key.into(), "test.json".into());
            }
            (None, Some(_)) => {
                sources.insert(key.into(), "config".into());
            }
            (None, None) => {}
        }
    }
    beam.validate().map_err(|p| ReportError::Config {
        path: config_path.to_path_buf(),
        message: format!("[specimen.beam] {} with the test's measured dimensions: {}", p.key, p.message),
    })?;
    Ok(sources)
}

/// The record of the test folder `dir` (`dir/test.json`), when there is one.
pub fn record_of(dir: &Path) -> Option<PathBuf> {
    Some(dir.join("test.json")).filter(|p| p.is_file())
}

/// The report of a test from its prepared inputs ([`prepare`]): the build, then what the
/// record adds — where the dimensions came from, its events, notes and method, and the
/// crack entry's part in the validity.
pub fn build_test(
    feed: &crate::Feed,
    utm: Option<&crate::UtmStream>,
    prepared: &Prepared,
    view: &TestView,
    config_path: &Path,
) -> Result<crate::Report, ReportError> {
    let mut r = crate::build(feed, utm, &prepared.rig, config_path, &prepared.opts)?;
    r.dimension_sources = prepared.sources.clone();
    let from_test: Vec<&str> = prepared.sources.iter().filter(|(_, s)| *s == "test.json").map(|(k, _)| k.as_str()).collect();
    if !from_test.is_empty() {
        let text = format!("test.json's measured {}, else the config ([specimen.beam])", from_test.join(", "));
        for n in &mut r.notes {
            *n = n.replace(crate::build::GEOMETRY_FROM_CONFIG, &text);
        }
        r.beam_source = text;
    }
    apply_crack(&mut r, view.crack.as_ref());
    r.qc.warnings.extend(prepared.method_warning.clone());
    if let Some(v) = view.verification.as_ref().filter(|v| !v.stale.is_empty()) {
        r.qc.warnings.push(format!("the verification in force is stale: {}", v.stale.join("; ")));
    }
    r.test = Some(view.clone());
    r.control = r.feed_path.parent().and_then(crate::control_section::read);
    Ok(r)
}

/// The reason a C1609/C1856 test with its crack outside the middle third is not valid.
pub const CRACK_OUTSIDE: &str = "fracture outside the middle third";

/// The crack entry's part in the validity (ASTM C1609 §9 / C78: a fracture outside the
/// middle third of the span makes the test invalid; EN 14651 notches its beams and ignores
/// the entry): outside → invalid with [`CRACK_OUTSIDE`]; no entry → a QC warning, not invalid.
fn apply_crack(r: &mut crate::Report, crack: Option<&CrackInfo>) {
    if r.standard == Standard::En14651 {
        return;
    }
    let span = r.beam.span_mm;
    let inside = crack.and_then(|c| c.inside(span));
    let at = crack.and_then(|c| c.position_mm).map_or(String::new(), |p| format!(" at {p:+.0} mm from mid-span"));
    match inside {
        None => r.qc.warnings.push(
            "crack position not entered: whether the beam broke inside the middle third of the span (ASTM C1609 §9, C78) was not checked"
                .into(),
        ),
        Some(true) => {
            r.lab.fracture.get_or_insert(format!("inside the middle third{at}"));
        }
        Some(false) => {
            r.validity.valid = false;
            r.validity.reasons.push(format!(
                "The operator entered the crack{at}: {CRACK_OUTSIDE} of the span (middle third: ±{:.0} mm from mid-span); ASTM C1609 §9 (as C78) takes such a test as invalid.",
                span / 6.0
            ));
            r.lab.fracture.get_or_insert(format!("outside the middle third{at}"));
        }
    }
}

/// The feed's runs (one unless `allow_restarts`) and the UTM's own samples of a test folder
/// (`feed.jsonl`, and `utm.jsonl` when it holds samples), read alike by every route.
pub fn read_streams(
    dir: &Path,
    opts: &ReportConfig,
    allow_restarts: bool,
) -> Result<(Vec<crate::Feed>, Option<crate::UtmStream>), ReportError> {
    let read = crate::ReadOptions { limits: opts.limits(), allow_restarts };
    let feeds = crate::Feed::read_runs(&dir.join("feed.jsonl"), &read)?;
    let utm_path = dir.join("utm.jsonl");
    let utm = match std::fs::metadata(&utm_path) {
        Ok(m) if m.len() > 0 => Some(crate::UtmStream::read(&utm_path, &opts.limits())?),
        _ => None,
    };
    Ok((feeds, utm))
}
