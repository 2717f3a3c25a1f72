//! A start as the control API takes it (`POST /api/test/start`): the request's `method` and
//! `specimen` resolved — the method from `<tests>/methods/` or the shipped ones, the specimen
//! from the table entered beforehand (`"next"`: the next untested one) — and the start refused
//! when its report could not be made (geometry missing, 400) or the specimen is under load
//! (above the method's `max_start_load_kn`, 409).

use std::collections::BTreeMap;

use tagdeflect_core::method::library::{self, MethodError};
use tagdeflect_core::specimen::SpecimenInfo;

use super::state::LabTests;
use super::{TestError, TestMeta};

/// The dimensions a report of `standard` needs when no method says.
pub fn standard_requires(standard: &str) -> Vec<String> {
    let mut dims = vec!["width_mm", "depth_mm", "span_mm"];
    if standard == "en-14651" {
        dims.push("notch_mm");
    }
    dims.into_iter().map(str::to_string).collect()
}

/// The specimen id that takes the table's next untested specimen.
pub const NEXT: &str = "next";

impl LabTests {
    /// The config's `[specimen.beam]` dimensions (`width_mm`, ...): a start finds there what
    /// its body and specimen row do not give.
    pub fn set_beam(&self, dims_mm: BTreeMap<String, f64>) {
        self.lock().beam_mm = dims_mm;
    }

    /// `POST /api/test/start`: [`TestMeta`]'s fields plus an optional `method` (a method's
    /// name); `specimen` may be `"next"` or an id of the table; `user` is named on the start
    /// event. See the module doc.
    pub fn start_request(&self, body: serde_json::Value, user: Option<String>) -> Result<serde_json::Value, TestError> {
        let serde_json::Value::Object(mut fields) = body else { return Err(TestError::Bad("start: the body is a JSON object".into())) };
        let method = match fields.remove("method") {
            None | Some(serde_json::Value::Null) => None,
            Some(serde_json::Value::String(m)) => Some(self.method(&m)?),
            Some(other) => return Err(TestError::Bad(format!("start: \"method\" is a method's name, not {other}"))),
        };
        let mut meta: TestMeta = serde_json::from_value::<TestMeta>(serde_json::Value::Object(fields))
            .map_err(|e| TestError::Bad(format!("start: {e}")))?
            .trimmed();
        if let Some(m) = &method {
            match &meta.standard {
                Some(s) if *s != m.method.standard => {
                    return Err(TestError::Bad(format!("start: standard \"{s}\" but method {} is {}", m.method.name, m.method.standard)))
                }
                _ => meta.standard = Some(m.method.standard.clone()),
            }
        }
        let row = self.specimen_row(&meta.specimen)?;
        if let Some(row) = &row {
            meta.specimen = row.id.clone();
            for (k, v) in row.means() {
                meta.measured.entry(k).or_insert(v);
            }
        }
        meta.validate()?;
        self.check_start(&meta, method.as_ref())?;
        let in_table = row.as_ref().map(|r| r.id.clone());
        let mut g = self.after_stop(self.lock(), super::START_WAIT)?;
        let id = self.open(&mut g, meta, None, user, None)?;
        if let Some(r) = g.running.as_mut() {
            r.record.method = method.as_ref().map(library::Loaded::reference);
            r.preload_kn = method.as_ref().and_then(|m| m.method.preload_kn);
            if let Some(on) = method.as_ref().and_then(|m| m.method.record_frames) {
                r.record.record_frames = Some(on);
            }
            r.record.specimen_info = row.map(|s| with_age(s, r.record.started_t_ns));
            self.persist(r);
            self.publish(&r.record);
        }
        drop(g);
        if let Some(specimen) = in_table {
            self.mark_tested(&specimen, &id);
        }
        Ok(self.status())
    }

    /// `GET /api/methods`: every method (a file that does not pass with its error) and the
    /// config's beam, for the page's start form and its rate window.
    pub fn methods(&self) -> serde_json::Value {
        let methods: Vec<serde_json::Value> = library::list(&self.dir)
            .into_iter()
            .map(|m| match m {
                Ok(m) => {
                    let mut v = serde_json::to_value(&m.method).unwrap_or_default();
                    v["origin"] = m.origin().into();
                    v["sha256"] = m.sha256.clone().into();
                    v["review"] = serde_json::to_value(&m.review).unwrap_or_default();
                    v
                }
                Err(e) => serde_json::json!({"error": e.to_string()}),
            })
            .collect();
        serde_json::json!({"methods": methods, "beam_mm": self.lock().beam_mm})
    }

    /// The method `name`, or why it cannot be used (400).
    fn method(&self, name: &str) -> Result<library::Loaded, TestError> {
        library::find(&self.dir, name).map_err(|e| match e {
            MethodError::Bad { origin, problem, .. } => TestError::Bad(format!("start: method {name} ({origin}) is not valid: {problem}")),
            other => TestError::Bad(format!("start: {other}")),
        })
    }

    /// A start whose report cannot be made is refused (400, naming what is missing and where
    /// it was looked for); so is a start under load above the method's limit (409).
    fn check_start(&self, meta: &TestMeta, method: Option<&library::Loaded>) -> Result<(), TestError> {
        let g = self.lock();
        let requires = match (method, &meta.standard) {
            (Some(m), _) => m.method.requires.clone(),
            (None, Some(s)) => standard_requires(s),
            (None, None) => Vec::new(),
        };
        let missing: Vec<&str> =
            requires.iter().map(String::as_str).filter(|k| !meta.measured.contains_key(*k) && !g.beam_mm.contains_key(*k)).collect();
        if !missing.is_empty() {
            let what = method
                .map_or_else(|| format!("standard {}", meta.standard.as_deref().unwrap_or("")), |m| format!("method {}", m.method.name));
            return Err(TestError::Bad(format!(
                "start refused: {what} needs {} for its report, given neither in the start's measured, nor by the specimen's row, nor in [specimen.beam]",
                missing.join(", ")
            )));
        }
        if let (Some(m), Some((load_kn, _))) = (method, g.last_load) {
            if load_kn > m.method.max_start_load_kn {
                return Err(TestError::Conflict(format!(
                    "start refused: the load is {load_kn:.3} kN, above method {}'s max_start_load_kn = {} kN: unload the specimen first",
                    m.method.name, m.method.max_start_load_kn
                )));
            }
        }
        Ok(())
    }
}

/// The row with its age at the start (from its cast date when not given).
fn with_age(mut s: SpecimenInfo, started_t_ns: i64) -> SpecimenInfo {
    if s.age_days.is_none() {
        let cast = s.cast_date.as_deref().and_then(|d| chrono::NaiveDate::parse_from_str(d, "%Y-%m-%d").ok());
        let day = chrono::DateTime::from_timestamp_nanos(started_t_ns).date_naive();
        s.age_days = cast.and_then(|c| u32::try_from((day - c).num_days()).ok());
    }
    s
}
