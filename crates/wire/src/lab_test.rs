//! `<topic>/labtest/<test id>`: a lab test's record on the broker (SPEC "Tests"; issue "A day
//! of tests"), so that the archive knows the tests and not only the lines.
//!
//! The rig publishes it retained, at QoS 1, when the test starts, at every event (mark, zero,
//! resume) and when it stops (then with the SHA-256 of the folder's files); again on every
//! connection to the broker (a broker restarted without persistence forgets retained
//! messages), and the end of a run waits for the broker's acknowledgement. The record is
//! `test.json`'s ([`TestRecord`], in `tagdeflect_core::lab_test`) with the rig and the run (the MQTT test id of the topic).
//!
//! What the archive takes is checked here, for both sides: at most [`MAX_LAB_TEST_BYTES`],
//! the rig, run and test id of the topic, the control API's own limits on what an operator
//! types, no NUL (PostgreSQL's text refuses it), a stop not before the start, bounded lists.

use serde::{Deserialize, Serialize};

use tagdeflect_core::lab_test::TestRecord;
use tagdeflect_core::limits;

use crate::WireError;

/// The largest lab test message taken: the rig's control API keeps a record well within it
/// (`tagdeflect_core::limits`), so a record the API accepted is never refused here.
pub const MAX_LAB_TEST_BYTES: usize = limits::ARCHIVE_RECORD_MAX_BYTES;
/// Events of one test at most.
pub const MAX_EVENTS: usize = limits::ARCHIVE_EVENTS_MAX;
/// Hashed files of one test at most.
pub const MAX_HASHES: usize = 10_000;

/// The message.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LabTestMessage {
    /// The rig (`[output.mqtt] rig`).
    pub rig: String,
    /// The run it was published in (the topic's test id).
    pub test: String,
    /// `test.json`.
    #[serde(flatten)]
    pub record: TestRecord,
}

impl LabTestMessage {
    /// The message of `record` on the rig `rig`, run `test`.
    pub fn from_record(rig: &str, test: &str, record: &TestRecord) -> LabTestMessage {
        LabTestMessage { rig: rig.to_string(), test: test.to_string(), record: record.clone() }
    }

    /// Reads and checks a message that came on the topic of `rig`, `run` and lab test `id`.
    pub fn parse(payload: &[u8], rig: &str, run: &str, id: &str) -> Result<LabTestMessage, WireError> {
        let m = Self::read(payload)?;
        m.check(rig, run, id)?;
        Ok(m)
    }

    /// The message read from its bytes (size, NUL, JSON shape), not yet checked.
    fn read(payload: &[u8]) -> Result<LabTestMessage, WireError> {
        if payload.len() > MAX_LAB_TEST_BYTES {
            return Err(WireError::LabTest(format!(
                "{} bytes, more than the {MAX_LAB_TEST_BYTES} a lab test record may have",
                payload.len()
            )));
        }
        // PostgreSQL's text and jsonb refuse NUL; a record never has one.
        if payload.windows(6).any(|w| w == b"\\u0000") || payload.contains(&0) {
            return Err(WireError::LabTest("a NUL character in a lab test record".to_string()));
        }
        serde_json::from_slice(payload).map_err(|e| WireError::LabTest(format!("not a lab test record: {e}")))
    }

    /// The checks of [`LabTestMessage::parse`] on a message read.
    pub fn check(&self, rig: &str, run: &str, id: &str) -> Result<(), WireError> {
        self.check_topic(rig, run, id)?;
        self.check_record()
    }

    /// The rig, run and test id against the topic's.
    fn check_topic(&self, rig: &str, run: &str, id: &str) -> Result<(), WireError> {
        for (key, got, want) in [("rig", &self.rig, rig), ("test", &self.test, run), ("id", &self.record.id, id)] {
            if got != want {
                return Err(WireError::LabTest(format!(
                    "a lab test record with {key} \"{}\" on the topic of {key} \"{}\" (rejected: it would write over another's test)",
                    got.escape_debug(),
                    want.escape_debug()
                )));
            }
        }
        Ok(())
    }

    /// The record's own limits: what an operator types, times, lists.
    fn check_record(&self) -> Result<(), WireError> {
        let ok_id = |c: char| c.is_alphanumeric() || matches!(c, '_' | '-' | '.');
        let r = &self.record;
        if r.id.is_empty() || r.id.len() > limits::TEST_ID_MAX_BYTES || !r.id.chars().all(ok_id) {
            return Err(WireError::LabTest(format!(
                "test id \"{}\": 1 to {} bytes of letters, digits, `_`, `-`, `.`",
                r.id.escape_debug(),
                limits::TEST_ID_MAX_BYTES
            )));
        }
        r.meta.validate().map_err(|p| WireError::LabTest(p.message))?;
        if r.started_t_ns <= 0 {
            return Err(WireError::LabTest(format!("started_t_ns {}: a time after 1970", r.started_t_ns)));
        }
        if let Some(s) = r.stopped_t_ns {
            if s < r.started_t_ns {
                return Err(WireError::LabTest(format!("stopped_t_ns {s} is before started_t_ns {}", r.started_t_ns)));
            }
        }
        if r.events.len() > MAX_EVENTS {
            return Err(WireError::LabTest(format!("{} events, more than {MAX_EVENTS}", r.events.len())));
        }
        for e in &r.events {
            if e.kind.is_empty() || e.kind.len() > 32 || !e.kind.chars().all(|c| c.is_ascii_lowercase() || c == '_') {
                return Err(WireError::LabTest(format!("event kind \"{}\": 1 to 32 lowercase letters", e.kind.escape_debug())));
            }
            if let Some(n) = &e.note {
                limits::check_text("an event's note", n, true).map_err(|p| WireError::LabTest(p.message))?;
            }
        }
        if r.sha256.len() > MAX_HASHES {
            return Err(WireError::LabTest(format!("{} hashes, more than {MAX_HASHES}", r.sha256.len())));
        }
        for (file, h) in &r.sha256 {
            if file.is_empty() || file.len() > 4096 || file.chars().any(char::is_control) {
                return Err(WireError::LabTest(format!(
                    "hashed file name \"{}\": 1 to 4096 characters, no control characters",
                    file.escape_debug()
                )));
            }
            if h.len() != 64 || !h.chars().all(|c| c.is_ascii_hexdigit()) {
                return Err(WireError::LabTest(format!(
                    "the SHA-256 of {}: 64 hex digits, got \"{}\"",
                    file.escape_debug(),
                    h.escape_debug()
                )));
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tagdeflect_core::feed::FeedEvent;
    use tagdeflect_core::lab_test::TestMeta;

    fn record() -> TestRecord {
        TestRecord {
            id: "20261202T101500Z-B12".into(),
            meta: TestMeta {
                specimen: "B12".into(),
                operator: Some("A. Tester".into()),
                standard: Some("astm-c1609".into()),
                ..TestMeta::default()
            },
            started_t_ns: 1_700_000_000_000_000_000,
            stopped_t_ns: Some(1_700_000_600_000_000_000),
            events: vec![FeedEvent { kind: "start".into(), t_ns: 1_700_000_000_000_000_000, note: None, user: None }],
            lines: 3000,
            utm_samples: 30000,
            sha256: [("feed.jsonl".to_string(), "ab".repeat(32))].into_iter().collect(),
            method: None,
            specimen_info: None,
            crack: None,
            preload: None,
            verification: None,
            frames_stopped: None,
            record_frames: None,
        }
    }

    #[test]
    fn a_record_is_checked_against_its_topic_and_the_operators_limits() {
        let m = LabTestMessage::from_record("rig1", "run7", &record());
        let bytes = serde_json::to_vec(&m).unwrap();
        assert_eq!(LabTestMessage::parse(&bytes, "rig1", "run7", "20261202T101500Z-B12").unwrap(), m);
        let v: serde_json::Value = serde_json::from_slice(&bytes).unwrap();
        assert_eq!(v["specimen"], "B12", "test.json's fields at the top: {v}");
        assert_eq!(v["rig"], "rig1");
        let e = LabTestMessage::parse(&bytes, "rig2", "run7", "20261202T101500Z-B12").unwrap_err().to_string();
        assert!(e.contains("rig") && e.contains("rig2"), "{e}");
        assert!(LabTestMessage::parse(&bytes, "rig1", "run7", "other").unwrap_err().to_string().contains("id"));
        let bad = |f: &dyn Fn(&mut TestRecord)| {
            let mut r = record();
            f(&mut r);
            let id = r.id.clone();
            LabTestMessage::parse(&serde_json::to_vec(&LabTestMessage::from_record("rig1", "run7", &r)).unwrap(), "rig1", "run7", &id)
                .unwrap_err()
                .to_string()
        };
        assert!(bad(&|r| r.meta.specimen = "<script>".into()).contains("specimen"));
        assert!(bad(&|r| r.stopped_t_ns = Some(1)).contains("before"));
        assert!(bad(&|r| r.meta.notes = Some("a\u{0}b".into())).contains("NUL"));
        assert!(bad(&|r| r.events[0].kind = "Start!".into()).contains("event kind"));
        assert!(bad(&|r| {
            r.sha256.insert("x".into(), "zz".into());
        })
        .contains("64 hex"));
        assert!(LabTestMessage::parse(&vec![b' '; MAX_LAB_TEST_BYTES + 1], "rig1", "run7", "x").unwrap_err().to_string().contains("bytes"));
        assert!(LabTestMessage::parse(b"{\"rig\": 1}", "rig1", "run7", "x").unwrap_err().to_string().contains("not a lab test record"));
    }
}
