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

pub use tagdeflect_core::lab_test::TestRecord;
use tagdeflect_core::lab_test::{CrackEntry, TestMeta};
use tagdeflect_core::method::MethodRef;

use crate::config::{BeamConfig, ReportConfig};
use crate::error::ReportError;
use crate::report::TestRig;
use crate::standard::Standard;

/// Reads `test.json` as the daemon writes it (core's [`TestRecord`]: keys added since the
/// first version may be absent) and range-checks it; a key of the wrong type or a value out of
/// range is one error naming the file and the key (`measured.width_mm`, `events[1].t_ns`).
pub fn read_record(path: &Path) -> Result<TestRecord, ReportError> {
    let data = |message: String| ReportError::Data { path: path.to_path_buf(), message };
    let text =
        std::fs::read_to_string(path).map_err(|e| ReportError::Io { path: path.to_path_buf(), message: format!("cannot read: {e}") })?;
    let value: serde_json::Value = serde_json::from_str(&text).map_err(|e| data(format!("not JSON: {e}")))?;
    // What the test was started with is flattened into the record, where a wrong type would
    // lose its key: it is read on its own first, so its key is named.
    let started_with = value.as_object().map(|o| o.iter().filter(|(k, _)| META_KEYS.contains(&k.as_str())));
    let started_with = serde_json::Value::Object(started_with.into_iter().flatten().map(|(k, v)| (k.clone(), v.clone())).collect());
    serde_path_to_error::deserialize::<_, TestMeta>(started_with).map_err(|e| data(key_error(e)))?;
    let record: TestRecord = serde_path_to_error::deserialize(value).map_err(|e| data(key_error(e)))?;
    checked(&record, path)?;
    Ok(record)
}

/// The keys of [`TestMeta`], flattened into `test.json`.
const META_KEYS: [&str; 5] = ["specimen", "operator", "standard", "notes", "measured"];

/// `measured.width_mm: invalid type: string "150.2", expected f64`.
fn key_error(e: serde_path_to_error::Error<serde_json::Error>) -> String {
    let key = e.path().to_string();
    let at = if key == "." { String::new() } else { format!("{key}: ") };
    format!("{at}{}", e.into_inner())
}

/// The checks of a test's start ([`TestMeta::validate`]) on a record's values (read, or held
/// in memory at the stop); `path` names it in errors. The specimen id is not checked as a
/// folder name here: the report only shows it (escaped) and a series makes its folder name safe.
pub fn checked(record: &TestRecord, path: &Path) -> Result<(), ReportError> {
    let meta = TestMeta { specimen: "specimen".into(), ..record.meta.clone() };
    meta.validate().map_err(|p| ReportError::Data { path: path.to_path_buf(), message: format!("{}: {}", p.key, p.message) })
}

/// The standard the record names, if any.
pub fn standard_of(record: &TestRecord, path: &Path) -> Result<Option<Standard>, ReportError> {
    record
        .meta
        .standard
        .as_deref()
        .map(|s| {
            serde_json::from_value(serde_json::json!(s))
                .map_err(|e| ReportError::Data { path: path.to_path_buf(), message: format!("standard: {e}") })
        })
        .transpose()
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
    view: &TestRecord,
    rig: &TestRig,
    opts: &ReportConfig,
    standard: Option<Standard>,
    record_path: &Path,
    config_path: &Path,
) -> Result<Prepared, ReportError> {
    let mut rig = rig.clone();
    let mut opts = opts.clone();
    if let Some(s) = standard.or(standard_of(view, record_path)?) {
        opts.standard = s;
    }
    let sources = apply_dimensions(&mut rig, &view.meta.measured, config_path)?;
    let lab = &mut opts.lab;
    if !view.meta.specimen.trim().is_empty() {
        lab.specimen = Some(view.meta.specimen.clone());
    }
    if view.meta.operator.as_deref().is_some_and(|o| !o.trim().is_empty()) {
        lab.operator = view.meta.operator.clone();
    }
    if let Some(cast) = view.specimen_info.as_ref().and_then(|i| i.cast_date.as_ref()) {
        lab.cast_date = Some(cast.clone());
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
fn method_of(m: &MethodRef, record_path: &Path) -> (Option<tagdeflect_core::method::Method>, Option<String>) {
    use tagdeflect_core::method::library;
    let tests = record_path.parent().and_then(Path::parent).unwrap_or(Path::new("."));
    match library::find(tests, &m.name) {
        Ok(l) if m.sha256 == l.sha256 => (Some(l.method), None),
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
    view: &TestRecord,
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
    r.qc.warnings.extend(view.preload.as_ref().and_then(|p| p.warning.clone()));
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
fn apply_crack(r: &mut crate::Report, crack: Option<&CrackEntry>) {
    if r.standard == Standard::En14651 {
        return;
    }
    let span = r.beam.span_mm;
    let inside = crack.map(|c| c.inside_middle_third);
    let at = crack.map_or(String::new(), CrackEntry::at);
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
/// (`feed.jsonl`, and `utm.jsonl` when it holds samples), read alike by every route; the
/// feed read for the prepared rig (its tags' figures gathered in the same pass).
pub fn read_streams(
    dir: &Path,
    prepared: &Prepared,
    allow_restarts: bool,
) -> Result<(Vec<crate::Feed>, Option<crate::UtmStream>), ReportError> {
    let opts = &prepared.opts;
    let read = crate::ReadOptions { limits: opts.limits(), allow_restarts };
    let feeds = crate::Feed::read_runs_for(&dir.join("feed.jsonl"), &read, Some(&prepared.rig))?;
    let utm_path = dir.join("utm.jsonl");
    let utm = match std::fs::metadata(&utm_path) {
        Ok(m) if m.len() > 0 => Some(crate::UtmStream::read(&utm_path, &opts.limits())?),
        _ => None,
    };
    Ok((feeds, utm))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn read(text: &str) -> Result<TestRecord, ReportError> {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("test.json");
        std::fs::write(&path, text).unwrap();
        read_record(&path)
    }

    /// A record of the first versions (no hashes, counts, method, crack…) reads, its keys'
    /// defaults in place; one written now reads as the daemon wrote it.
    #[test]
    fn an_older_test_json_reads_with_its_absent_keys_defaulted() {
        let old = read(r#"{"id": "t1", "specimen": "B1", "operator": "A. Tester", "measured": {"width_mm": 150.2}}"#).unwrap();
        assert_eq!((old.meta.specimen.as_str(), old.meta.operator.as_deref()), ("B1", Some("A. Tester")));
        assert_eq!(old.meta.measured["width_mm"], 150.2);
        assert!(old.events.is_empty() && old.sha256.is_empty() && old.method.is_none() && old.crack.is_none());
        let text = serde_json::to_string(&old).unwrap();
        assert_eq!(read(&text).unwrap(), old);
    }

    /// A key of the wrong type is one error naming the file and the key, whether the key is
    /// the record's own or one of what the test was started with (flattened into it).
    #[test]
    fn a_wrong_type_is_named_by_file_and_key() {
        let cases = [
            (r#"{"id": "t1", "specimen": "B1", "measured": {"width_mm": "150.2"}}"#, "measured.width_mm: invalid type: string"),
            (r#"{"id": "t1", "specimen": "B1", "operator": 7}"#, "operator: invalid type: integer"),
            (r#"{"id": "t1", "specimen": "B1", "lines": "many"}"#, "lines: invalid type: string"),
            (r#"{"id": "t1", "specimen": "B1", "events": [{"kind": "start", "t_ns": "now"}]}"#, "events[0].t_ns: invalid type"),
            (
                r#"{"id": "t1", "specimen": "B1", "method": {"name": "C1609-19", "version": "two", "standard": "astm-c1609", "sha256": "00"}}"#,
                "method.version: invalid type: string",
            ),
        ];
        for (text, want) in cases {
            let e = read(text).unwrap_err().to_string();
            assert!(e.contains("test.json: ") && e.contains(want), "{text}: {e}");
        }
        let e = read(r#"{"id": "t1", "specimen": "B1", "measured": {"width_mm": 0.001}}"#).unwrap_err().to_string();
        assert!(e.contains("test.json: measured.width_mm"), "out of range: {e}");
    }
}
