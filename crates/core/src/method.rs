//! Test methods (issue "the test a lab signs"): a named, versioned definition of how a test is
//! run and reported — standard and edition, the geometry it needs, tare and preload, the rate
//! of each phase, the end criterion, the results — with the public source of every rule it
//! holds ([`Method`], written as a TOML file, docs/methods.md). A test started with a method
//! records it in `test.json` as a [`MethodRef`]: name, version, standard, the SHA-256 of the
//! file as used and, when the lab reviewed that very file, its [`MethodReview`].
//!
//! The shipped methods (`C1609-19`, `C1856-17`, `EN14651-05`) are built in ([`SHIPPED`]); a
//! lab's own methods and the reviews live in `<tests>/methods/` ([`library`]).

pub mod library;

use serde::{Deserialize, Serialize};

use crate::lab_test::{MEASURED_RANGES_MM, STANDARDS};
use crate::Problem;

/// The shipped methods: (name, the file's text).
pub const SHIPPED: [(&str, &str); 3] = [
    ("C1609-19", include_str!("../methods/C1609-19.toml")),
    ("C1856-17", include_str!("../methods/C1856-17.toml")),
    ("EN14651-05", include_str!("../methods/EN14651-05.toml")),
];

/// A method as its TOML file says it (see the module doc and docs/methods.md).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Method {
    /// Its name (letters, digits, `_`, `-`, `.`), e.g. `C1609-19`; the file is `NAME.toml`.
    pub name: String,
    /// Its version, raised by whoever changes it.
    pub version: u32,
    /// The report made at stop: one of [`STANDARDS`].
    pub standard: String,
    /// The standard's edition as cited, e.g. `ASTM C1609/C1609M-19a`.
    pub edition: String,
    /// One line saying what the method is for.
    #[serde(default)]
    pub title: String,
    /// The dimensions a report needs (`width_mm`, `depth_mm`, `span_mm`, `notch_mm`).
    pub requires: Vec<String>,
    /// The load at which the zero is taken, kN (tare and preload).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub preload_kn: Option<f64>,
    /// A start above this load is refused, kN.
    pub max_start_load_kn: f64,
    /// The phases of loading, in order, each with its rate window.
    #[serde(rename = "phase")]
    pub phases: Vec<Phase>,
    /// When the test ends.
    pub end: End,
    /// The results the report gives (report.json keys).
    pub results: Vec<String>,
    /// The specimen's details the printed report shows beside the standard's identification
    /// (which it always shows): any of [`REPORT_FIELDS`], in the report's order; absent: all
    /// the test holds. `report.json` keeps every detail whatever this says (it is the record).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub report_fields: Option<Vec<String>>,
    /// The public source of every rule above.
    #[serde(rename = "source")]
    pub sources: Vec<Source>,
    /// Whether a test of this method records its frames into its folder (`frames/`); absent:
    /// the rig's `[output] record_tests` decides. Copied into `test.json` at the start.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub record_frames: Option<bool>,
}

/// A phase of loading: the controlled quantity's rate window until the phase's end.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Phase {
    /// What the phase is, e.g. `up to L/900`.
    pub name: String,
    /// The controlled quantity: `net_deflection` or `cmod`.
    pub gauge: String,
    /// The phase applies to beams of this depth, `[low, high]` mm (absent: every beam).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub for_depth_mm: Option<[f64; 2]>,
    /// The phase ends at this value of the gauge, mm ...
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub until_mm: Option<f64>,
    /// ... or at the span over this divisor (`900`: L/900).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub until_span_over: Option<f64>,
    /// The rate window of the gauge, `[low, high]` mm/min.
    pub rate_mm_per_min: [f64; 2],
}

/// When a test of the method ends.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct End {
    /// The quantity: `net_deflection` or `cmod`.
    pub gauge: String,
    /// At this value, mm ...
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub at_mm: Option<f64>,
    /// ... or at the span over this divisor (`150`: L/150).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub at_span_over: Option<f64>,
}

/// The public source of a rule of the method.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Source {
    /// The rule it is the source of: `requires`, `preload_kn`, `max_start_load_kn`, `phase`,
    /// `end`, `results` or `validity`.
    pub rule: String,
    /// The document, e.g. `ASTM C1609/C1609M-19a`.
    pub document: String,
    /// Where in it (a section or clause reference; no text of the standard is copied).
    pub clause: String,
    /// Where the document is published, when public.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub url: Option<String>,
}

/// What a test records of the method it was run with (`test.json`'s `method`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MethodRef {
    /// The method's name.
    pub name: String,
    /// Its version.
    pub version: u32,
    /// Its standard.
    pub standard: String,
    /// SHA-256 (hex) of the method file as used.
    pub sha256: String,
    /// The lab's review of that very file; absent when not reviewed (or the file changed since).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub review: Option<MethodReview>,
}

impl MethodRef {
    /// `C1609-19 v2`.
    pub fn label(&self) -> String {
        format!("{} v{}", self.name, self.version)
    }
}

/// A lab's review of a method file (`<tests>/methods/NAME.review.json`, with the file's hash).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MethodReview {
    /// Who reviewed it.
    pub by: String,
    /// When, RFC 3339 UTC (`2026-12-06T10:00:00Z`).
    pub at: String,
    /// What the review means ("checked against the standard's text; approved for use").
    pub meaning: String,
}

/// The results each standard's report can give (`report.json` keys), in the order of today's
/// reports; a method's `results` names some of them, in its own order.
pub const STANDARD_RESULTS: [(&str, &[&str]); 3] =
    [("astm-c1609", &C1609_RESULTS), ("astm-c1856", &C1609_RESULTS), ("en-14651", &["FL", "fL", "fR1", "fR2", "fR3", "fR4"])];

const C1609_RESULTS: [&str; 12] = ["P1", "delta1", "f1", "Pp", "deltap", "fp", "P600", "P150", "f600", "f150", "T150", "RT150"];

/// The results a report of `standard` can give (empty for an unknown standard).
pub fn results_of(standard: &str) -> &'static [&'static str] {
    STANDARD_RESULTS.iter().find(|(s, _)| *s == standard).map_or(&[], |(_, r)| r)
}

/// The specimen's details a method may have its printed report show (`report_fields`): the
/// lab's table's row beyond the standard's identification (specimen, operator, dates, age,
/// machine, laboratory, which every report shows).
pub const REPORT_FIELDS: [&str; 6] = ["mix", "fibre", "dosage_kg_m3", "client", "project", "readings"];

/// The rules a method holds, each of which needs a `[[source]]` row.
pub const RULES: [&str; 5] = ["requires", "max_start_load_kn", "phase", "end", "results"];

const GAUGES: [&str; 2] = ["net_deflection", "cmod"];

impl Method {
    /// Reads a method file's text; a problem's key is the file's key (`phase[1].rate_mm_per_min`).
    pub fn parse(text: &str) -> Result<Method, Problem> {
        let m: Method = toml::from_str(text).map_err(|e| {
            let key = e.span().and_then(|s| key_at(text, s.start)).unwrap_or_default();
            Problem::new(key, e.message().to_string())
        })?;
        m.validate()?;
        Ok(m)
    }

    /// The checks of the file's values (keys relative to the file).
    pub fn validate(&self) -> Result<(), Problem> {
        valid_name(&self.name).map_err(|m| Problem::new("name", m))?;
        if !STANDARDS.contains(&self.standard.as_str()) {
            return Err(Problem::new("standard", format!("\"{}\": one of {}", self.standard, STANDARDS.join(", "))));
        }
        let dims: Vec<&str> = MEASURED_RANGES_MM.iter().map(|d| d.0).collect();
        if let Some((k, r)) = self.requires.iter().enumerate().find(|(_, r)| !dims.contains(&r.as_str())) {
            return Err(Problem::new(format!("requires[{k}]"), format!("\"{r}\": one of {}", dims.join(", "))));
        }
        for (k, v) in [("preload_kn", self.preload_kn.unwrap_or(0.0)), ("max_start_load_kn", self.max_start_load_kn)] {
            if !(v.is_finite() && (0.0..=1000.0).contains(&v)) {
                return Err(Problem::new(k, format!("{v}: a load of 0 to 1000 kN")));
            }
        }
        if self.preload_kn.is_some_and(|p| p > self.max_start_load_kn) {
            return Err(Problem::new("preload_kn", "the preload must not exceed max_start_load_kn"));
        }
        if self.phases.is_empty() {
            return Err(Problem::new("phase", "at least one [[phase]]"));
        }
        for (k, p) in self.phases.iter().enumerate() {
            p.validate().map_err(|e| e.within(&format!("phase[{k}]")))?;
        }
        self.end.validate().map_err(|e| e.within("end"))?;
        self.validate_results()?;
        self.validate_report_fields()?;
        self.validate_sources()
    }

    /// At least one result, each one its standard's report gives, none twice.
    fn validate_results(&self) -> Result<(), Problem> {
        if self.results.is_empty() {
            return Err(Problem::new("results", "at least one result"));
        }
        let known = results_of(&self.standard);
        for (k, r) in self.results.iter().enumerate() {
            if !known.contains(&r.as_str()) {
                let says = format!("\"{}\": the {} report gives {}", r.escape_debug(), self.standard, known.join(", "));
                return Err(Problem::new(format!("results[{k}]"), says));
            }
            if self.results[..k].contains(r) {
                return Err(Problem::new(format!("results[{k}]"), format!("\"{r}\" is named twice")));
            }
        }
        Ok(())
    }

    /// Each of the report's fields one of [`REPORT_FIELDS`], none twice.
    fn validate_report_fields(&self) -> Result<(), Problem> {
        let Some(fields) = &self.report_fields else { return Ok(()) };
        for (k, f) in fields.iter().enumerate() {
            if !REPORT_FIELDS.contains(&f.as_str()) {
                let says = format!("\"{}\": one of {}", f.escape_debug(), REPORT_FIELDS.join(", "));
                return Err(Problem::new(format!("report_fields[{k}]"), says));
            }
            if fields[..k].contains(f) {
                return Err(Problem::new(format!("report_fields[{k}]"), format!("\"{f}\" is named twice")));
            }
        }
        Ok(())
    }

    /// Whether the printed report shows the specimen's detail `field` (one of
    /// [`REPORT_FIELDS`]): every one when the method names none.
    pub fn shows_field(&self, field: &str) -> bool {
        self.report_fields.as_ref().is_none_or(|f| f.iter().any(|x| x == field))
    }

    /// Every rule has a source; every source names a rule, a document and a clause.
    fn validate_sources(&self) -> Result<(), Problem> {
        for (k, s) in self.sources.iter().enumerate() {
            let at = |f: &str| format!("source[{k}].{f}");
            if !RULES.contains(&s.rule.as_str()) && !["preload_kn", "validity"].contains(&s.rule.as_str()) {
                return Err(Problem::new(at("rule"), format!("\"{}\": one of {}, preload_kn, validity", s.rule, RULES.join(", "))));
            }
            if s.document.trim().is_empty() || s.clause.trim().is_empty() {
                return Err(Problem::new(at("clause"), "a source names its document and clause"));
            }
        }
        let mut rules: Vec<&str> = RULES.to_vec();
        if self.preload_kn.is_some() {
            rules.push("preload_kn");
        }
        match rules.iter().find(|r| !self.sources.iter().any(|s| s.rule == **r)) {
            Some(r) => Err(Problem::new("source", format!("no [[source]] with rule = \"{r}\": every rule names its public source"))),
            None => Ok(()),
        }
    }

    /// The phases that apply to a beam of `depth_mm` (all, when the depth is not known).
    pub fn phases_for(&self, depth_mm: Option<f64>) -> Vec<&Phase> {
        self.phases
            .iter()
            .filter(|p| match (p.for_depth_mm, depth_mm) {
                (Some([lo, hi]), Some(d)) => (lo..=hi).contains(&d),
                _ => true,
            })
            .collect()
    }
}

impl Phase {
    fn validate(&self) -> Result<(), Problem> {
        if !GAUGES.contains(&self.gauge.as_str()) {
            return Err(Problem::new("gauge", format!("\"{}\": one of {}", self.gauge, GAUGES.join(", "))));
        }
        let [lo, hi] = self.rate_mm_per_min;
        if !(lo.is_finite() && hi.is_finite() && 0.0 < lo && lo <= hi && hi <= 100.0) {
            return Err(Problem::new("rate_mm_per_min", format!("[{lo}, {hi}]: a window 0 < low ≤ high ≤ 100 mm/min")));
        }
        if let Some([lo, hi]) = self.for_depth_mm {
            if !(lo.is_finite() && hi.is_finite() && 0.0 <= lo && lo <= hi) {
                return Err(Problem::new("for_depth_mm", format!("[{lo}, {hi}]: a range of depths in mm")));
            }
        }
        one_of_two(self.until_mm, self.until_span_over, "until_mm", "until_span_over", true)
    }
}

impl End {
    fn validate(&self) -> Result<(), Problem> {
        if !GAUGES.contains(&self.gauge.as_str()) {
            return Err(Problem::new("gauge", format!("\"{}\": one of {}", self.gauge, GAUGES.join(", "))));
        }
        one_of_two(self.at_mm, self.at_span_over, "at_mm", "at_span_over", false)
    }
}

/// At most one (exactly one unless `optional`) of two positive numbers.
fn one_of_two(a: Option<f64>, b: Option<f64>, ka: &str, kb: &str, optional: bool) -> Result<(), Problem> {
    match (a, b) {
        (Some(_), Some(_)) => Err(Problem::new(kb, format!("{ka} or {kb}, not both"))),
        (None, None) if !optional => Err(Problem::new(ka, format!("{ka} or {kb} is required"))),
        (Some(v), None) if !(v.is_finite() && v > 0.0) => Err(Problem::new(ka, format!("{v}: a positive number"))),
        (None, Some(v)) if !(v.is_finite() && v > 1.0) => Err(Problem::new(kb, format!("{v}: a divisor above 1"))),
        _ => Ok(()),
    }
}

/// A method's (or specimen's) name: 1 to 64 letters, digits, `_`, `-`, `.` (not first).
pub fn valid_name(name: &str) -> Result<(), String> {
    let ok = |c: char| c.is_ascii_alphanumeric() || matches!(c, '_' | '-' | '.');
    if name.is_empty() || name.len() > 64 || name.starts_with('.') || !name.chars().all(ok) {
        return Err(format!("\"{}\": 1 to 64 letters, digits, `_`, `-` and `.` (not first)", name.escape_debug()));
    }
    Ok(())
}

/// The dotted key at byte `at` of a TOML text, as well as a parse error's span lets us say:
/// the table header above it and the key on its line (`phase[1].rate_mm_per_min`).
fn key_at(text: &str, at: usize) -> Option<String> {
    let before = text.get(..at.min(text.len()))?;
    let line_start = before.rfind('\n').map_or(0, |i| i + 1);
    let line = text[line_start..].lines().next().unwrap_or("");
    let key = line.split('=').next().map(str::trim).filter(|k| !k.is_empty() && !k.starts_with('['));
    let mut table: Option<String> = None;
    let mut counts: std::collections::BTreeMap<String, usize> = Default::default();
    for l in text[..line_start].lines().map(str::trim) {
        if let Some(name) = l.strip_prefix("[[").and_then(|r| r.strip_suffix("]]")) {
            let n = counts.entry(name.to_string()).or_insert(0);
            table = Some(format!("{name}[{n}]"));
            *n += 1;
        } else if let Some(name) = l.strip_prefix('[').and_then(|r| r.strip_suffix(']')) {
            table = Some(name.to_string());
        }
    }
    match (table, key) {
        (Some(t), Some(k)) => Some(format!("{t}.{k}")),
        (t, k) => t.or(k.map(str::to_string)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_shipped_methods_are_valid_and_name_a_source_for_every_rule() {
        for (name, text) in SHIPPED {
            let m = Method::parse(text).unwrap_or_else(|p| panic!("{name}: {p}"));
            assert_eq!(m.name, name);
            for r in RULES {
                assert!(m.sources.iter().any(|s| s.rule == r), "{name}: a source for {r}");
            }
        }
    }

    #[test]
    fn a_bad_method_names_its_key() {
        let text = SHIPPED[0].1.replacen("rate_mm_per_min = [0.035, 0.10]", "rate_mm_per_min = [0.10, 0.035]", 1);
        assert_ne!(text, SHIPPED[0].1);
        let p = Method::parse(&text).unwrap_err();
        assert!(p.key.starts_with("phase[") && p.key.ends_with("].rate_mm_per_min"), "{p}");
        let text = SHIPPED[0].1.replacen("max_start_load_kn = ", "max_start_load_kn = \"x\" #", 1);
        assert_eq!(Method::parse(&text).unwrap_err().key, "max_start_load_kn");
        let text = SHIPPED[0].1.replace("rule = \"end\"", "rule = \"results\"");
        assert!(Method::parse(&text).unwrap_err().message.contains("rule = \"end\""));
        let text = SHIPPED[2].1.replace("\"fR3\", \"fR4\"]", "\"fR3\", \"fR5\"]");
        let p = Method::parse(&text).unwrap_err();
        assert_eq!(p.key, "results[5]", "{p}");
        assert!(p.message.contains("\"fR5\": the en-14651 report gives FL, fL, fR1"), "{p}");
        let text = SHIPPED[0].1.replace("\"P1\", \"delta1\"", "\"P1\", \"P1\"");
        assert_eq!(Method::parse(&text).unwrap_err().key, "results[1]");
        let text = format!("report_fields = [\"client\", \"colour\"]\n{}", SHIPPED[0].1);
        let p = Method::parse(&text).unwrap_err();
        assert_eq!(p.key, "report_fields[1]", "{p}");
        assert!(p.message.contains("\"colour\": one of mix, fibre"), "{p}");
        let text = format!("report_fields = [\"mix\", \"mix\"]\n{}", SHIPPED[0].1);
        assert_eq!(Method::parse(&text).unwrap_err().key, "report_fields[1]");
        let text = format!("record_frames = \"yes\"\n{}", SHIPPED[0].1);
        assert_eq!(Method::parse(&text).unwrap_err().key, "record_frames");
    }

    #[test]
    fn a_method_names_the_specimen_details_its_report_shows_or_leaves_them_all() {
        for (name, text) in SHIPPED {
            let m = Method::parse(text).unwrap();
            assert!(REPORT_FIELDS.iter().all(|f| m.shows_field(f)), "{name} shows every detail");
        }
        let m = Method::parse(&format!("report_fields = [\"project\", \"client\"]\n{}", SHIPPED[0].1)).unwrap();
        assert!(m.shows_field("client") && m.shows_field("project"));
        assert!(!m.shows_field("mix") && !m.shows_field("readings"));
    }

    #[test]
    fn a_method_says_whether_its_tests_record_frames_or_leaves_it_to_the_rig() {
        for (name, text) in SHIPPED {
            assert_eq!(Method::parse(text).unwrap().record_frames, None, "{name} leaves it to the rig");
        }
        let m = Method::parse(&format!("record_frames = true\n{}", SHIPPED[0].1)).unwrap();
        assert_eq!(m.record_frames, Some(true));
    }
}
