//! One message off the broker as the archive takes it: a feed line, a status or a lab
//! test's record, checked against its topic; anything else is malformed.

use tagdeflect_core::feed::FeedLine;
use tagdeflect_wire::{Kind, TopicLayout};

use crate::db::{LabTestRow, LineRow, StatusRow};

/// Why a message is malformed (logged, acknowledged, skipped).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct Malformed(pub String);

/// The largest message the archive takes (a feed line of a big rig is a few kB); a bigger
/// one is malformed: acknowledged, logged, counted, skipped.
pub const MAX_MESSAGE_BYTES: usize = 1 << 20;

/// What one message turned out to be.
pub(crate) enum Parsed {
    Line(LineRow),
    Status(StatusRow),
    LabTest(Box<LabTestRow>),
    Skip,
}

/// Checks one message as the archive would take it: `Ok` when it would be stored, else
/// why it is malformed (what the fuzz target drives).
pub fn check_message(layout: &TopicLayout, topic: &str, payload: &[u8]) -> Result<(), Malformed> {
    parse_message(layout, topic, payload).map(|_| ())
}

pub(crate) fn parse_message(layout: &TopicLayout, topic: &str, payload: &[u8]) -> Result<Parsed, Malformed> {
    if let Some((rig, run, id)) = layout.parse_lab(topic) {
        let m = tagdeflect_wire::LabTestMessage::parse(payload, &rig, &run, &id).map_err(|e| Malformed(e.to_string()))?;
        return Ok(Parsed::LabTest(Box::new(LabTestRow { rig, run, message: m })));
    }
    let Some((rig, test, kind)) = layout.parse(topic) else {
        return Err(Malformed(format!("topic {topic} does not fit the template")));
    };
    if payload.len() > MAX_MESSAGE_BYTES {
        return Err(Malformed(format!("{} bytes, more than the {} a feed line or status may have", payload.len(), MAX_MESSAGE_BYTES)));
    }
    let value: serde_json::Value = serde_json::from_slice(payload).map_err(|e| Malformed(format!("not JSON: {e}")))?;
    match kind {
        Kind::Feed => parse_line(rig, test, value),
        Kind::Status => parse_status(rig, test, value),
        // `parse` never says LabTest: a lab test's topic has its id (`parse_lab`, above).
        Kind::LabTest => Err(Malformed(format!("topic {topic}: a lab test record needs its id as the last level"))),
    }
}

/// A feed line: a feed line's shape, a seq in range, each tag once, gauges as
/// `{value, sigma, unit}`.
fn parse_line(rig: String, test: String, value: serde_json::Value) -> Result<Parsed, Malformed> {
    let line: FeedLine = serde_json::from_value(value.clone()).map_err(|e| Malformed(format!("not a feed line: {e}")))?;
    let seq = i64::try_from(line.seq).map_err(|_| Malformed("seq out of range".to_string()))?;
    let mut ids = std::collections::HashSet::new();
    if line.tags.iter().any(|t| !ids.insert(t.id)) {
        return Err(Malformed("a tag id appears twice".to_string()));
    }
    if let Some(g) = value.get("gauges") {
        let ok = g.as_object().is_some_and(|m| {
            m.values().all(|v| {
                v.is_object()
                    && v.get("value").is_none_or(|x| x.is_number() || x.is_null())
                    && v.get("sigma").is_none_or(|x| x.is_number() || x.is_null())
            })
        });
        if !ok {
            return Err(Malformed("`gauges` is not an object of {value, sigma, unit}".to_string()));
        }
    }
    Ok(Parsed::Line(LineRow { rig, test, seq, t_ns: line.t_ns, line: value }))
}

/// A status: an object, naming (if at all) its topic's rig and test; else skipped.
fn parse_status(rig: String, test: String, value: serde_json::Value) -> Result<Parsed, Malformed> {
    if !value.is_object() {
        return Ok(Parsed::Skip);
    }
    // A status names its rig and test: one that claims another than its topic's is
    // someone else's writing over this rig's (set the broker's ACLs).
    for (key, want) in [("rig", &rig), ("test", &test)] {
        if let Some(v) = value.get(key) {
            if v.as_str() != Some(want.as_str()) {
                return Err(Malformed(format!(
                    "a status for {key} {v} on the topic of {key} \"{want}\" (rejected: it would overwrite that rig's status)"
                )));
            }
        }
    }
    Ok(Parsed::Status(StatusRow { rig, test, status: value }))
}
