//! A lab test's record, `test.json` (SPEC "Tests"): what it was started with ([`TestMeta`]),
//! its events, counts and file hashes ([`TestRecord`]). Written by the lab-test sink, sent to
//! the broker inside the lab-test message (`tagdeflect_wire::lab_test`) and read back by the
//! archive.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use crate::feed::FeedEvent;
use crate::limits;
use crate::method::MethodRef;
use crate::specimen::SpecimenInfo;
use crate::Problem;

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

/// The measured dimensions the report computes with and their accepted ranges, mm (a beam of
/// 10 mm to 1 m in section, 50 mm to 6 m in span; a notch up to 500 mm).
pub const MEASURED_RANGES_MM: [(&str, f64, f64); 4] =
    [("width_mm", 10.0, 1000.0), ("depth_mm", 10.0, 1000.0), ("span_mm", 50.0, 6000.0), ("notch_mm", 0.0, 500.0)];

/// `v` as typed: plain, or in exponent form when very large or small (`1e308`, not 309 digits).
fn short(v: f64) -> String {
    if v != 0.0 && !(1e-3..1e7).contains(&v.abs()) {
        format!("{v:e}")
    } else {
        format!("{v}")
    }
}

/// Standards a test may name.
pub const STANDARDS: [&str; 3] = ["astm-c1609", "astm-c1856", "en-14651"];

impl TestMeta {
    /// What an operator typed, as it is kept: the specimen id and the operator's name without
    /// the blanks around them (`" B12"` is `B12`).
    pub fn trimmed(mut self) -> TestMeta {
        let trim = |s: &mut String| {
            if s.trim().len() != s.len() {
                *s = s.trim().to_string();
            }
        };
        trim(&mut self.specimen);
        if let Some(o) = self.operator.as_mut() {
            trim(o);
        }
        self
    }

    /// Checks what an operator typed, within [`limits`](crate::limits): the specimen id is a
    /// folder name and text on the page.
    /// The problem's key is the field's (`specimen`, `standard`, `operator`, `notes`,
    /// `measured.NAME`); its message names the field itself, as it is answered to the operator
    /// as is (`TestError::Bad` of the lab-test sink).
    pub fn validate(&self) -> Result<(), Problem> {
        // Blanks around the id are taken off when it is kept ([`TestMeta::trimmed`]).
        limits::check_specimen(self.specimen.trim())?;
        if let Some(s) = &self.standard {
            if !STANDARDS.contains(&s.as_str()) {
                return Err(Problem::new("standard", format!("standard \"{}\": one of {}", s.escape_debug(), STANDARDS.join(", "))));
            }
        }
        if let Some(o) = &self.operator {
            limits::check_text("operator", o, true)?;
        }
        if let Some(n) = &self.notes {
            limits::check_text("notes", n, true)?;
        }
        if self.measured.len() > limits::MEASURED_MAX {
            return Err(Problem::new("measured", format!("measured: at most {} values", limits::MEASURED_MAX)));
        }
        for (k, v) in &self.measured {
            limits::check_measured_key(k)?;
            if !v.is_finite() {
                return Err(Problem::new(format!("measured.{k}"), format!("measured.{k} = {v}: a finite number")));
            }
        }
        self.validate_dimensions()
    }

    /// The beam's measured dimensions within [`MEASURED_RANGES_MM`], the notch shallower than
    /// the depth: a typing slip (`0.001`, `1e308`, metres for millimetres) is refused here
    /// rather than computed into the report.
    fn validate_dimensions(&self) -> Result<(), Problem> {
        for (k, lo, hi) in MEASURED_RANGES_MM {
            if let Some(&v) = self.measured.get(k) {
                if !(lo..=hi).contains(&v) {
                    return Err(Problem::new(
                        format!("measured.{k}"),
                        format!("measured.{k} = {}: a beam's {k} is {lo} to {hi} mm", short(v)),
                    ));
                }
            }
        }
        if let (Some(&n), Some(&d)) = (self.measured.get("notch_mm"), self.measured.get("depth_mm")) {
            if n >= d {
                return Err(Problem::new(
                    "measured.notch_mm",
                    format!("measured.notch_mm = {n}: the notch must be shallower than depth_mm = {d}"),
                ));
            }
        }
        Ok(())
    }
}

/// `test.json` (SPEC "Tests"), as the daemon writes it and every reader (the report, the
/// archive) reads it. Keys added since the first version are optional, so older records
/// read: besides `id` and `specimen`, a key may be absent (its default), never of another type.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TestRecord {
    /// The test's id.
    pub id: String,
    /// What it was started with.
    #[serde(flatten)]
    pub meta: TestMeta,
    /// When it started and stopped, ns since the Unix epoch.
    #[serde(default)]
    pub started_t_ns: i64,
    /// When it stopped (absent while it runs).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stopped_t_ns: Option<i64>,
    /// Start, marks, zeros, stop.
    #[serde(default)]
    pub events: Vec<FeedEvent>,
    /// Feed lines and UTM samples in the folder.
    #[serde(default)]
    pub lines: u64,
    /// UTM samples kept.
    #[serde(default)]
    pub utm_samples: u64,
    /// SHA-256 (hex) of every file of the folder (but `test.json`) and of the calibration files.
    #[serde(default)]
    pub sha256: BTreeMap<String, String>,
    /// The method the test was run with (absent: none).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub method: Option<MethodRef>,
    /// The specimen's row from the table entered beforehand (absent: none).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub specimen_info: Option<SpecimenInfo>,
    /// The operator's crack entry.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub crack: Option<CrackEntry>,
    /// The load at which the test's zero was taken.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub preload: Option<Preload>,
    /// The verification in force (`[verification]`): assessed at the start, again at the stop.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub verification: Option<crate::verification::InForce>,
    /// (`[output] record_tests`) When the test's frames stopped being recorded before its stop
    /// to keep the disk's reserve for the lines (absent: recorded to the stop, or not at all).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frames_stopped: Option<FramesStopped>,
    /// Whether the test records its frames into its folder, decided at its start: its
    /// method's `record_frames` where set, else the rig's `[output] record_tests` (absent in
    /// a `test.json` older than the option: the rig's).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub record_frames: Option<bool>,
}

/// The test's frames stopped before its stop: the free space under its folder fell below the
/// reserve (`[output] record_tests_reserve_mb`); its lines go on.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FramesStopped {
    /// When the frames stopped, ns since the Unix epoch: every frame recorded is older, none
    /// from this time on is recorded (the first frame not recorded, or just after the newest
    /// frame of another camera already recorded).
    pub t_ns: i64,
    /// The recording it ended (`frames`, `frames-2`, ...), relative to the test folder.
    pub folder: String,
    /// Free space under the folder then, MB (10⁶ bytes).
    pub free_mb: f64,
    /// The reserve, MB.
    pub reserve_mb: f64,
}

/// The operator's crack entry: where the beam cracked.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CrackEntry {
    /// From mid-span, signed, mm.
    pub position_mm: f64,
    /// Whether the crack is inside the middle third of the span (from the position and the
    /// span when the operator does not say).
    pub inside_middle_third: bool,
    /// When it was entered, ns since the Unix epoch.
    pub t_ns: i64,
}

impl CrackEntry {
    /// The entry's words on the page and the report: `at +12 mm from mid-span`.
    pub fn at(&self) -> String {
        format!(" at {:+.0} mm from mid-span", self.position_mm)
    }
}

/// The load at which a test's zero was taken (tare and preload).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Preload {
    /// The UTM's load, kN.
    pub load_kn: f64,
    /// When, ns since the Unix epoch.
    pub t_ns: i64,
    /// The lowest and the highest load of the zero's frame sets, kN (absent in records of
    /// earlier versions, or when no set of the zero carried a load).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub zero_loads_kn: Option<[f64; 2]>,
    /// Why the zero may not stand for the preload: its sets spanned much load (a machine
    /// loading fast while it was taken; docs/report.md "A zero taken while the load climbs").
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub warning: Option<String>,
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A test.json written before methods, specimens, cracks and preloads existed.
    const OLD: &str = r#"{
  "id": "20261202T013000Z-B12",
  "specimen": "B12",
  "operator": "Ann",
  "standard": "astm-c1609",
  "measured": {"width_mm": 150.2},
  "started_t_ns": 1764639000000000000,
  "stopped_t_ns": 1764639600000000000,
  "events": [{"kind": "start", "t_ns": 1764639000000000000}, {"kind": "mark", "t_ns": 1764639100000000000, "note": "first crack seen"}],
  "lines": 12,
  "utm_samples": 40,
  "sha256": {"feed.jsonl": "00"}
}"#;

    #[test]
    fn an_old_test_json_reads_back_unchanged_and_the_new_keys_round_trip() {
        let old: TestRecord = serde_json::from_str(OLD).unwrap();
        assert!(old.method.is_none() && old.specimen_info.is_none() && old.crack.is_none() && old.preload.is_none());
        assert!(old.events.iter().all(|e| e.user.is_none()));
        let again: serde_json::Value = serde_json::to_value(&old).unwrap();
        assert_eq!(again, serde_json::from_str::<serde_json::Value>(OLD).unwrap(), "written back as it was");
        let mut new = old.clone();
        new.crack = Some(CrackEntry { position_mm: -12.0, inside_middle_third: true, t_ns: 5 });
        new.preload = Some(Preload { load_kn: 0.52, t_ns: 4, zero_loads_kn: Some([0.5, 0.52]), warning: None });
        new.events[1].user = Some("ann".into());
        let text = serde_json::to_string(&new).unwrap();
        assert_eq!(serde_json::from_str::<TestRecord>(&text).unwrap(), new);
    }
}
