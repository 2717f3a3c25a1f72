//! A test's record (`test.json`), what `stop` answers, and the stopped tests' curves the page
//! draws in grey.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

pub use tagdeflect_core::lab_test::TestRecord;

/// A stopped test's curve for the page (`GET /api/tests`): load over net deflection from its
/// zero, at most [`EARLIER_POINTS`] points.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct EarlierTest {
    /// The test's id.
    pub id: String,
    /// Its specimen.
    pub specimen: String,
    /// When it started, ns since the Unix epoch.
    pub started_t_ns: i64,
    /// Net deflection, mm.
    pub net_deflection_mm: Vec<f64>,
    /// Load, kN, at the same lines.
    pub load_kn: Vec<f64>,
}

/// Points of an earlier test's curve on the page.
pub const EARLIER_POINTS: usize = 500;
/// Earlier tests on the page at most (the day's newest).
pub const EARLIER_TESTS: usize = 12;

impl EarlierTest {
    pub(super) fn new(record: &TestRecord, curve: &[(f64, f64)]) -> EarlierTest {
        let step = curve.len().div_ceil(EARLIER_POINTS).max(1);
        let kept: Vec<(f64, f64)> = curve.iter().step_by(step).copied().chain(curve.last().copied().filter(|_| step > 1)).collect();
        EarlierTest {
            id: record.id.clone(),
            specimen: record.meta.specimen.clone(),
            started_t_ns: record.started_t_ns,
            net_deflection_mm: kept.iter().map(|p| p.0).collect(),
            load_kn: kept.iter().map(|p| p.1).collect(),
        }
    }
}

/// The (net deflection, load) points of a test's `feed.jsonl`; lines that do not parse are
/// skipped (the file is this daemon's own; a line cut by a crash is the usual one).
pub(super) fn read_curve(feed: &Path) -> std::io::Result<Vec<(f64, f64)>> {
    #[derive(Deserialize)]
    struct Point {
        #[serde(rename = "load_kN")]
        load_kn: Option<f64>,
        net_deflection_mm: Option<f64>,
    }
    use std::io::BufRead;
    let mut out = Vec::new();
    for line in std::io::BufReader::new(std::fs::File::open(feed)?).lines() {
        if let Ok(Point { load_kn: Some(l), net_deflection_mm: Some(n) }) = serde_json::from_str::<Point>(&line?) {
            push_point(&mut out, n, l);
        }
    }
    Ok(out)
}

/// Adds a point to a running curve, halving it when it grows past 4 × [`EARLIER_POINTS`].
pub(super) fn push_point(curve: &mut Vec<(f64, f64)>, net: f64, load: f64) {
    if net.is_finite() && load.is_finite() {
        curve.push((net, load));
    }
    if curve.len() > 4 * EARLIER_POINTS {
        let mut k = 0;
        curve.retain(|_| {
            k += 1;
            k % 2 == 1
        });
    }
}

/// The local calendar day of a time, ns since the Unix epoch.
pub(super) fn day_of(t_ns: i64) -> chrono::NaiveDate {
    chrono::DateTime::from_timestamp_nanos(t_ns).with_timezone(&chrono::Local).date_naive()
}

/// What `stop` answers.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Stopped {
    /// The test's id.
    pub id: String,
    /// Its folder.
    pub folder: PathBuf,
    /// Why its report could not be made (a standard was set, the report failed).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub report_error: Option<String>,
}
