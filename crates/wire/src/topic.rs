//! The topic template of a rig's messages and the layout below it (SPEC "Configuration"):
//!
//! ```text
//! <topic>/feed            feed lines
//! <topic>/status          the rig's retained status
//! <topic>/archive         the archive's retained acknowledgement (ack)
//! <topic>/labtest/<id>    a lab test's retained record (lab_test)
//! ```
//!
//! `<topic>` is the template (`tagdeflect/{rig}/{test}`) with the rig and the test id filled
//! in; both are whole topic levels, so the archive reads them back off a topic.

use crate::WireError;

/// The last level of a feed line's topic: `<topic>/feed`.
pub const FEED_SUFFIX: &str = "feed";
/// The last level of the rig's status topic: `<topic>/status`.
pub const STATUS_SUFFIX: &str = "status";
/// The last level of the acknowledgement topic: `<topic>/archive`.
pub const ACK_SUFFIX: &str = "archive";
/// The last level of a lab test's topic, before its id: `<topic>/labtest/<id>`.
pub const LAB_TEST_SUFFIX: &str = "labtest";

/// Replaces `{rig}` and `{test}` in a topic template.
pub fn topic_for(template: &str, rig: &str, test: &str) -> String {
    template.replace("{rig}", rig).replace("{test}", test)
}

/// Checks a topic template: no wildcards, `{rig}` and `{test}` each one whole level.
pub fn check_topic_template(t: &str) -> Result<(), WireError> {
    if t.is_empty() || t.contains(['+', '#', '\0']) {
        return Err(WireError::Topic(format!("\"{t}\" must be a non-empty topic without the wildcards + and #")));
    }
    let levels: Vec<&str> = t.split('/').collect();
    for ph in ["{rig}", "{test}"] {
        let whole = levels.iter().filter(|l| **l == ph).count();
        if whole != 1 || t.matches(ph).count() != 1 {
            return Err(WireError::Topic(format!("\"{t}\" must contain {ph} exactly once, as a whole topic level (e.g. \"tagdeflect/{{rig}}/{{test}}\"), so an archive can tell rigs and tests apart")));
        }
    }
    Ok(())
}

/// Checks a rig or test name used in a topic level.
pub fn check_level_name(what: &str, v: &str) -> Result<(), WireError> {
    if v.is_empty() || v.contains(['/', '+', '#', '\0']) || v.starts_with('$') {
        return Err(WireError::Topic(format!(
            "{what} \"{v}\" must be non-empty, without '/', '+', '#' and not start with '$' (it is a topic level)"
        )));
    }
    Ok(())
}

/// Which message a topic carries.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    /// `<topic>/feed`: a feed line.
    Feed,
    /// `<topic>/status`: the rig's status.
    Status,
    /// `<topic>/labtest/<id>`: a lab test's record (its id is the last level).
    LabTest,
}

/// The topic template of the rigs, to subscribe and to read rig and test from a topic.
#[derive(Debug, Clone)]
pub struct TopicLayout {
    levels: Vec<String>,
    rig: usize,
    test: usize,
}

impl TopicLayout {
    /// Parses a template such as `tagdeflect/{rig}/{test}`.
    pub fn new(template: &str) -> Result<TopicLayout, WireError> {
        check_topic_template(template)?;
        let levels: Vec<String> = template.split('/').map(str::to_string).collect();
        let rig = levels.iter().position(|l| l == "{rig}").expect("checked");
        let test = levels.iter().position(|l| l == "{test}").expect("checked");
        Ok(TopicLayout { levels, rig, test })
    }

    /// The subscription filter of one kind of message (placeholders become `+`).
    pub fn filter(&self, kind: Kind) -> String {
        let mut f: Vec<&str> = self.levels.iter().map(|l| if l == "{rig}" || l == "{test}" { "+" } else { l.as_str() }).collect();
        match kind {
            Kind::Feed => f.push(FEED_SUFFIX),
            Kind::Status => f.push(STATUS_SUFFIX),
            Kind::LabTest => f.extend([LAB_TEST_SUFFIX, "+"]),
        }
        f.join("/")
    }

    /// The base topic of a rig and test (the template filled in).
    pub fn topic_of(&self, rig: &str, test: &str) -> String {
        let v: Vec<&str> = self
            .levels
            .iter()
            .enumerate()
            .map(|(i, l)| {
                if i == self.rig {
                    rig
                } else if i == self.test {
                    test
                } else {
                    l.as_str()
                }
            })
            .collect();
        v.join("/")
    }

    /// Rig and test of the template's levels of `parts`, or `None` when they do not fit.
    fn base(&self, parts: &[&str]) -> Option<(String, String)> {
        for (i, l) in self.levels.iter().enumerate() {
            if i != self.rig && i != self.test && parts.get(i) != Some(&l.as_str()) {
                return None;
            }
        }
        let (rig, test) = (*parts.get(self.rig)?, *parts.get(self.test)?);
        if rig.is_empty() || test.is_empty() {
            return None;
        }
        Some((rig.to_string(), test.to_string()))
    }

    /// Rig, test and kind of a topic, or `None` when it does not fit the template (a lab
    /// test's topic: [`TopicLayout::parse_lab`]).
    pub fn parse(&self, topic: &str) -> Option<(String, String, Kind)> {
        let parts: Vec<&str> = topic.split('/').collect();
        if parts.len() != self.levels.len() + 1 {
            return None;
        }
        let kind = match parts[self.levels.len()] {
            FEED_SUFFIX => Kind::Feed,
            STATUS_SUFFIX => Kind::Status,
            _ => return None,
        };
        let (rig, test) = self.base(&parts)?;
        Some((rig, test, kind))
    }

    /// Rig, run (the topic's test) and lab test id of a `<topic>/labtest/<id>` topic.
    pub fn parse_lab(&self, topic: &str) -> Option<(String, String, String)> {
        let parts: Vec<&str> = topic.split('/').collect();
        let n = self.levels.len();
        if parts.len() != n + 2 || parts[n] != LAB_TEST_SUFFIX || parts[n + 1].is_empty() {
            return None;
        }
        let (rig, run) = self.base(&parts)?;
        Some((rig, run, parts[n + 1].to_string()))
    }
}
