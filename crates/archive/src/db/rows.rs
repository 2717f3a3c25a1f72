//! The rows a batch writes (feed lines, status messages, lab tests), the keys of lines and
//! runs, and what a committed batch did.

/// One feed line ready for the database.
#[derive(Debug, Clone)]
pub struct LineRow {
    /// Rig name (from the topic).
    pub rig: String,
    /// Test id (from the topic).
    pub test: String,
    /// Frame-set number.
    pub seq: i64,
    /// The line's `t_ns`.
    pub t_ns: i64,
    /// The line as published.
    pub line: serde_json::Value,
}

/// A status message for the database.
#[derive(Debug, Clone)]
pub struct StatusRow {
    /// Rig name (from the topic).
    pub rig: String,
    /// Test id (from the topic).
    pub test: String,
    /// The message (JSON object).
    pub status: serde_json::Value,
}

/// A lab test's record for the database (checked: [`tagdeflect_wire::LabTestMessage::parse`]).
#[derive(Debug, Clone)]
pub struct LabTestRow {
    /// Rig name (from the topic).
    pub rig: String,
    /// The run it was published in (the topic's test).
    pub run: String,
    /// The record.
    pub message: tagdeflect_wire::LabTestMessage,
}

/// What one committed batch did.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Written {
    /// Feed lines inserted (new).
    pub inserted: u64,
    /// Feed lines already stored (redelivered), left as they were.
    pub duplicates: u64,
    /// Tag samples inserted.
    pub tags: u64,
    /// Gauge samples inserted.
    pub gauges: u64,
    /// Rows refused by the database as bad data (logged, skipped).
    pub rejected: u64,
    /// Lab test records upserted.
    pub lab_tests: u64,
    /// The tests written to (also by duplicates only): (rig, test, test row id).
    pub touched: Vec<(String, String, i64)>,
}

impl Written {
    pub(super) fn add(&mut self, w: Written) {
        self.inserted += w.inserted;
        self.duplicates += w.duplicates;
        self.tags += w.tags;
        self.gauges += w.gauges;
        self.rejected += w.rejected;
        self.lab_tests += w.lab_tests;
        for t in w.touched {
            if !self.touched.contains(&t) {
                self.touched.push(t);
            }
        }
    }
}

/// A line's key (test row, run, seq) and what the archive did with it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct LineKey {
    /// The test's row id.
    pub test_id: i64,
    /// The run.
    pub run: i32,
    /// The seq.
    pub seq: i64,
}

/// A new run the archive began: a (rig, test, seq) held already with another `t_ns`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct NewRun {
    /// Rig.
    pub rig: String,
    /// Test id as published.
    pub test: String,
    /// The run's number.
    pub run: i32,
    /// The seq that began it.
    pub seq: i64,
}
