//! Specimens entered before their tests (issue "the test a lab signs", item 2): a row per
//! specimen — id, the readings of each measured dimension (several readings → their mean goes
//! into the test's `measured`), cast date and age, mix, fibre and dosage, client, project
//! ([`SpecimenInfo`], `test.json`'s `specimen_info`). A table is imported as CSV
//! ([`parse_csv`]) or JSON; every row is checked and the first bad one is named by row and
//! column ([`RowError`]).

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use crate::lab_test::{TestMeta, MEASURED_RANGES_MM};

/// A specimen's row.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SpecimenInfo {
    /// The specimen's id (a test's `specimen`).
    pub id: String,
    /// Readings of each dimension, mm (`{"width_mm": [150.1, 150.3]}`).
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub readings: BTreeMap<String, Vec<f64>>,
    /// When it was cast, `YYYY-MM-DD`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cast_date: Option<String>,
    /// Its age at the test, days (from `cast_date` at the start when not given).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub age_days: Option<u32>,
    /// The mix.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mix: Option<String>,
    /// The fibre type.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fibre: Option<String>,
    /// The fibre dosage, kg/m³.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dosage_kg_m3: Option<f64>,
    /// The client.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub client: Option<String>,
    /// The project.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub project: Option<String>,
}

/// The first bad row of a table: its row (1 = the first data row; the CSV header is row 0) and
/// column (the column's header).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("row {row}, column {column}: {message}")]
pub struct RowError {
    /// The row, 1 for the first specimen.
    pub row: usize,
    /// The column's name.
    pub column: String,
    /// What is wrong.
    pub message: String,
}

impl RowError {
    fn new(row: usize, column: &str, message: impl Into<String>) -> Self {
        RowError { row, column: column.to_string(), message: message.into() }
    }
}

/// The columns a CSV may have (the dimensions of [`MEASURED_RANGES_MM`] may repeat, one reading
/// each; a cell may also hold several readings separated by `;`).
pub const TEXT_COLUMNS: [&str; 5] = ["cast_date", "mix", "fibre", "client", "project"];

impl SpecimenInfo {
    /// The mean of each dimension's readings (what goes into the test's `measured`).
    pub fn means(&self) -> BTreeMap<String, f64> {
        self.readings.iter().filter(|(_, v)| !v.is_empty()).map(|(k, v)| (k.clone(), v.iter().sum::<f64>() / v.len() as f64)).collect()
    }

    /// Checks the row (`row` for the error): the id as a test's specimen, each reading in its
    /// dimension's range, the date, the texts.
    pub fn validate(&self, row: usize) -> Result<(), RowError> {
        let meta = TestMeta { specimen: self.id.clone(), ..TestMeta::default() };
        meta.validate().map_err(|p| RowError::new(row, "id", p.message))?;
        for (k, vs) in &self.readings {
            let Some((_, lo, hi)) = MEASURED_RANGES_MM.iter().find(|d| d.0 == k) else {
                return Err(RowError::new(row, k, format!("not a dimension: {}", dims())));
            };
            if let Some(v) = vs.iter().find(|v| !(v.is_finite() && (*lo..=*hi).contains(*v))) {
                return Err(RowError::new(row, k, format!("{v}: a beam's {k} is {lo} to {hi} mm")));
            }
        }
        if let Some(d) = &self.cast_date {
            if !is_date(d) {
                return Err(RowError::new(row, "cast_date", format!("\"{}\": a date YYYY-MM-DD", d.escape_debug())));
            }
        }
        if self.dosage_kg_m3.is_some_and(|v| !(v.is_finite() && (0.0..=2000.0).contains(&v))) {
            return Err(RowError::new(row, "dosage_kg_m3", "a dosage of 0 to 2000 kg/m³"));
        }
        let texts = [("mix", &self.mix), ("fibre", &self.fibre), ("client", &self.client), ("project", &self.project)];
        if let Some((k, _)) = texts.iter().find(|(_, t)| t.as_ref().is_some_and(|t| t.len() > 200 || t.chars().any(char::is_control))) {
            return Err(RowError::new(row, k, "at most 200 characters, no control characters"));
        }
        Ok(())
    }
}

fn dims() -> String {
    MEASURED_RANGES_MM.iter().map(|d| d.0).collect::<Vec<_>>().join(", ")
}

/// `YYYY-MM-DD` with a month 1–12 and a day 1–31.
fn is_date(d: &str) -> bool {
    let p: Vec<&str> = d.split('-').collect();
    let num = |s: &str, n: usize, lo: u32, hi: u32| s.len() == n && s.parse::<u32>().is_ok_and(|v| (lo..=hi).contains(&v));
    p.len() == 3 && num(p[0], 4, 1900, 2999) && num(p[1], 2, 1, 12) && num(p[2], 2, 1, 31)
}

/// A CSV table (a header row, then a row per specimen; `id` required), every row checked.
pub fn parse_csv(text: &str) -> Result<Vec<SpecimenInfo>, RowError> {
    let mut r = csv::ReaderBuilder::new().trim(csv::Trim::All).flexible(false).from_reader(text.as_bytes());
    let header: Vec<String> = r.headers().map_err(|e| RowError::new(0, "-", e.to_string()))?.iter().map(str::to_string).collect();
    let known = |h: &str| {
        h == "id" || h == "age_days" || h == "dosage_kg_m3" || TEXT_COLUMNS.contains(&h) || MEASURED_RANGES_MM.iter().any(|d| d.0 == h)
    };
    if let Some(h) = header.iter().find(|h| !known(h)) {
        return Err(RowError::new(0, h, format!("an unknown column: id, {}, age_days, dosage_kg_m3, {}", dims(), TEXT_COLUMNS.join(", "))));
    }
    if !header.iter().any(|h| h == "id") {
        return Err(RowError::new(0, "id", "the table needs an id column"));
    }
    let mut out: Vec<SpecimenInfo> = Vec::new();
    for (k, rec) in r.records().enumerate() {
        let row = k + 1;
        let rec = rec.map_err(|e| RowError::new(row, "-", e.to_string()))?;
        let s = parse_row(&header, &rec, row)?;
        if out.iter().any(|o| o.id == s.id) {
            return Err(RowError::new(row, "id", format!("\"{}\" appears twice in the table", s.id)));
        }
        out.push(s);
    }
    Ok(out)
}

fn parse_row(header: &[String], rec: &csv::StringRecord, row: usize) -> Result<SpecimenInfo, RowError> {
    let mut s = SpecimenInfo::default();
    let number =
        |col: &str, v: &str| v.parse::<f64>().map_err(|_| RowError::new(row, col, format!("\"{}\" is not a number", v.escape_debug())));
    for (col, cell) in header.iter().zip(rec.iter()) {
        if cell.is_empty() {
            continue;
        }
        let text = || Some(cell.to_string());
        match col.as_str() {
            "id" => s.id = cell.to_string(),
            "cast_date" => s.cast_date = text(),
            "mix" => s.mix = text(),
            "fibre" => s.fibre = text(),
            "client" => s.client = text(),
            "project" => s.project = text(),
            "age_days" => s.age_days = Some(cell.parse().map_err(|_| RowError::new(row, col, "a whole number of days"))?),
            "dosage_kg_m3" => s.dosage_kg_m3 = Some(number(col, cell)?),
            dim => {
                for v in cell.split(';').map(str::trim).filter(|v| !v.is_empty()) {
                    let v = number(dim, v)?;
                    s.readings.entry(dim.to_string()).or_default().push(v);
                }
            }
        }
    }
    s.validate(row)?;
    Ok(s)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_table_is_read_with_several_readings_and_a_bad_row_is_named() {
        let csv = "id,width_mm,width_mm,depth_mm,span_mm,cast_date,fibre,dosage_kg_m3\n\
                   B1,150.1,150.3,150.0;149.8,450,2026-11-01,hooked steel,40\n\
                   B2,100,,100,300,,,\n";
        let t = parse_csv(csv).unwrap();
        assert_eq!(t.len(), 2);
        assert_eq!(t[0].readings["width_mm"], vec![150.1, 150.3]);
        let m = t[0].means();
        assert!((m["width_mm"] - 150.2).abs() < 1e-9 && (m["depth_mm"] - 149.9).abs() < 1e-9, "{m:?}");
        assert_eq!(t[1].means()["width_mm"], 100.0);
        let bad = "id,width_mm,depth_mm\nB1,150,150\nB2,150,1.5e3\n";
        let e = parse_csv(bad).unwrap_err();
        assert_eq!((e.row, e.column.as_str()), (2, "depth_mm"), "{e}");
        let e = parse_csv("id,width_mm\nB1,15O\n").unwrap_err();
        assert_eq!((e.row, e.column.as_str()), (1, "width_mm"), "{e}");
        let e = parse_csv("id,colour\nB1,red\n").unwrap_err();
        assert_eq!(e.column, "colour");
        let e = parse_csv("id,cast_date\nB1,2026-13-01\n").unwrap_err();
        assert_eq!((e.row, e.column.as_str()), (1, "cast_date"));
    }
}
