//! The specimens entered before their tests: `<tests>/specimens.json`, imported through the
//! control API (`POST /api/specimens`, CSV or JSON; `tagdeflect test specimens import`), read
//! by the page (`GET /api/specimens`) and by a start (`"specimen": "next"` or an id of the
//! table), which marks its row tested.

use std::path::PathBuf;

use serde::{Deserialize, Serialize};
use tagdeflect_core::specimen::{parse_csv, RowError, SpecimenInfo};

use super::start::NEXT;
use super::state::LabTests;
use super::TestError;

/// Rows a table may hold.
pub const MAX_SPECIMENS: usize = 2000;

/// `<tests>/specimens.json`.
#[derive(Debug, Default, Serialize, Deserialize)]
struct Table {
    specimens: Vec<Entry>,
}

/// A row and the test that took it.
#[derive(Debug, Serialize, Deserialize)]
struct Entry {
    #[serde(flatten)]
    info: SpecimenInfo,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    test: Option<String>,
}

/// A table as sent: CSV (`csv`), else JSON — an array of rows or `{"specimens": [...]}`; every
/// row checked, the first bad one named by row (1 = the first specimen) and column.
pub fn parse_specimens(body: &[u8], csv: bool) -> Result<Vec<SpecimenInfo>, TestError> {
    let bad = |e: RowError| TestError::Bad(format!("specimens: {e}"));
    let text = std::str::from_utf8(body).map_err(|_| TestError::Bad("specimens: the body is not UTF-8 text".into()))?;
    if csv {
        return parse_csv(text).map_err(bad);
    }
    let v: serde_json::Value = serde_json::from_str(text).map_err(|e| TestError::Bad(format!("specimens: the body is not JSON: {e}")))?;
    let rows = match v {
        serde_json::Value::Array(rows) => rows,
        serde_json::Value::Object(mut m) => match m.remove("specimens") {
            Some(serde_json::Value::Array(rows)) => rows,
            _ => return Err(TestError::Bad("specimens: a JSON array of rows or {\"specimens\": [...]}".into())),
        },
        _ => return Err(TestError::Bad("specimens: a JSON array of rows or {\"specimens\": [...]}".into())),
    };
    let mut out: Vec<SpecimenInfo> = Vec::new();
    for (k, row) in rows.into_iter().enumerate() {
        let column = row_column(&row);
        let s: SpecimenInfo = serde_json::from_value(row).map_err(|e| bad(RowError { row: k + 1, column, message: e.to_string() }))?;
        s.validate(k + 1).map_err(bad)?;
        if out.iter().any(|o| o.id == s.id) {
            return Err(bad(RowError { row: k + 1, column: "id".into(), message: format!("\"{}\" appears twice in the table", s.id) }));
        }
        out.push(s);
    }
    Ok(out)
}

/// The column a JSON row's type error is most likely in: an unknown key, else `-`.
fn row_column(row: &serde_json::Value) -> String {
    let known = ["id", "readings", "cast_date", "age_days", "mix", "fibre", "dosage_kg_m3", "client", "project"];
    row.as_object().and_then(|m| m.keys().find(|k| !known.contains(&k.as_str())).cloned()).unwrap_or_else(|| "-".into())
}

impl LabTests {
    fn specimens_file(&self) -> PathBuf {
        self.dir.join("specimens.json")
    }

    fn read_table(&self) -> Result<Table, TestError> {
        let path = self.specimens_file();
        match std::fs::read_to_string(&path) {
            Ok(text) => serde_json::from_str(&text).map_err(|e| TestError::Io(format!("{}: {e}", path.display()))),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(Table::default()),
            Err(e) => Err(TestError::Io(format!("{}: {e}", path.display()))),
        }
    }

    fn write_table(&self, t: &Table) -> Result<(), TestError> {
        let path = self.specimens_file();
        let tmp = path.with_extension("json.tmp");
        let text = serde_json::to_string_pretty(t).map_err(|e| TestError::Io(e.to_string()))?;
        std::fs::write(&tmp, text + "\n")
            .and_then(|()| std::fs::rename(&tmp, &path))
            .map_err(|e| TestError::Io(format!("{}: {e}", path.display())))
    }

    /// Adds `rows` to the table (a row of an id already there replaces it, keeping its test).
    pub fn import_specimens(&self, rows: Vec<SpecimenInfo>) -> Result<serde_json::Value, TestError> {
        let _g = self.lock();
        let mut t = self.read_table()?;
        let n = rows.len();
        for info in rows {
            match t.specimens.iter_mut().find(|e| e.info.id == info.id) {
                Some(e) => e.info = info,
                None => t.specimens.push(Entry { info, test: None }),
            }
        }
        if t.specimens.len() > MAX_SPECIMENS {
            return Err(TestError::Bad(format!("specimens: at most {MAX_SPECIMENS} rows in the table")));
        }
        self.write_table(&t)?;
        drop(_g);
        tracing::info!(rows = n, "specimens imported");
        let mut v = self.specimens()?;
        v["imported"] = n.into();
        Ok(v)
    }

    /// `GET /api/specimens`: every row with its test (`tested`), and the next untested one.
    pub fn specimens(&self) -> Result<serde_json::Value, TestError> {
        let t = self.read_table()?;
        let rows: Vec<serde_json::Value> = t
            .specimens
            .iter()
            .map(|e| {
                let mut v = serde_json::to_value(&e.info).unwrap_or_default();
                v["tested"] = e.test.is_some().into();
                v["test"] = e.test.clone().into();
                v["means"] = serde_json::to_value(e.info.means()).unwrap_or_default();
                v
            })
            .collect();
        let next = t.specimens.iter().find(|e| e.test.is_none()).map(|e| e.info.id.clone());
        Ok(serde_json::json!({"specimens": rows, "next": next}))
    }

    /// The row a start names: `"next"` takes the next untested one (400 when there is none);
    /// an id of the table its row; any other id none (a start outside the table).
    pub(super) fn specimen_row(&self, specimen: &str) -> Result<Option<SpecimenInfo>, TestError> {
        let t = self.read_table()?;
        if specimen.trim() == NEXT {
            return match t.specimens.into_iter().find(|e| e.test.is_none()) {
                Some(e) => Ok(Some(e.info)),
                None => Err(TestError::Bad("start: no untested specimen in the table: import some (POST /api/specimens)".into())),
            };
        }
        Ok(t.specimens.into_iter().find(|e| e.info.id == specimen.trim()).map(|e| e.info))
    }

    /// Marks the row of `specimen` tested by `test`.
    pub(super) fn mark_tested(&self, specimen: &str, test: &str) {
        let _g = self.lock();
        let result = self.read_table().and_then(|mut t| {
            if let Some(e) = t.specimens.iter_mut().find(|e| e.info.id == specimen) {
                e.test = Some(test.to_string());
            }
            self.write_table(&t)
        });
        if let Err(e) = result {
            tracing::error!(test, "cannot mark specimen {specimen} tested: {e}");
        }
    }
}
