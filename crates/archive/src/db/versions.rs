//! Which version of a lab test's record the archive keeps ([`judge`]): the rig publishes a
//! test's record at its start, at every event and at its stop, and again on every connection;
//! a version that arrives may be newer, a redelivery, an older one, or a forgery on the rig's
//! topic. The rule is keyed on the stop and on time, not on how many events a version has:
//!
//! - a version of another start (`started_t_ns`) than the one held is refused;
//! - a **stop record wins** over every running version, and once held it is replaced only by a
//!   stop record that keeps its stop and its events and adds later ones (a re-analysis); a
//!   running version after it, or another stop record, is refused;
//! - between running versions, one that keeps the held events (and adds some, or fills in
//!   what the start left out: the method) replaces it; one whose events are a part of the
//!   held ones is an older version; one that tells another story is taken only when its last
//!   event is later than the held one's.
//!
//! Every refused version is logged by the caller, one line naming the test and the reason.

use tagdeflect_core::lab_test::TestRecord;

/// What to do with a version that arrived, against the one held.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) enum Verdict {
    /// It replaces the held one.
    Replace,
    /// It is the held one (a redelivery, a republish on connecting).
    Same,
    /// It is refused, and why (`older`: merely an older version).
    Refuse { why: String, older: bool },
}

/// The verdict on `new` with `held` stored (see the module doc).
pub(crate) fn judge(held: &TestRecord, new: &TestRecord) -> Verdict {
    if held == new {
        return Verdict::Same;
    }
    let refuse = |why: String, older: bool| Verdict::Refuse { why, older };
    if new.started_t_ns != held.started_t_ns {
        return refuse(format!("it was started at t_ns {}, the test held at {}", new.started_t_ns, held.started_t_ns), false);
    }
    let keeps = new.events.len() >= held.events.len() && new.events[..held.events.len()] == held.events[..];
    let part = new.events.len() < held.events.len() && held.events[..new.events.len()] == new.events[..];
    let last = |r: &TestRecord| r.events.iter().map(|e| e.t_ns).max().unwrap_or(r.started_t_ns);
    let n = |r: &TestRecord| r.events.len();
    match (held.stopped_t_ns, new.stopped_t_ns) {
        (Some(h), None) => refuse(
            format!("a running version ({} events) after the test's stop record (stopped at t_ns {h}, {} events)", n(new), n(held)),
            part,
        ),
        (Some(h), Some(s)) if s == h && keeps && n(new) > n(held) => Verdict::Replace,
        (Some(h), Some(s)) => refuse(
            format!(
                "another stop record (stopped at t_ns {s}, {} events) than the one held (stopped at t_ns {h}, {} events), which it does not extend",
                n(new),
                n(held)
            ),
            false,
        ),
        (None, Some(_)) => Verdict::Replace,
        (None, None) if keeps => Verdict::Replace,
        (None, None) if part => refuse(format!("an older version ({} events, {} held)", n(new), n(held)), true),
        (None, None) if last(new) > last(held) => Verdict::Replace,
        (None, None) => refuse(
            format!(
                "its events ({}, the last at t_ns {}) are not the held ones ({}, the last at t_ns {}) and not later",
                n(new),
                last(new),
                n(held),
                last(held)
            ),
            false,
        ),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tagdeflect_core::feed::FeedEvent;
    use tagdeflect_core::lab_test::TestMeta;

    fn ev(kind: &str, t_ns: i64) -> FeedEvent {
        FeedEvent { kind: kind.into(), t_ns, note: None, user: None }
    }

    fn record(events: &[(&str, i64)], stopped: Option<i64>) -> TestRecord {
        TestRecord {
            id: "20261202T101500Z-B12".into(),
            meta: TestMeta { specimen: "B12".into(), ..TestMeta::default() },
            started_t_ns: 100,
            stopped_t_ns: stopped,
            events: events.iter().map(|(k, t)| ev(k, *t)).collect(),
            lines: 0,
            utm_samples: 0,
            sha256: Default::default(),
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
    fn a_stop_record_is_kept_against_versions_with_more_events() {
        let start = record(&[("start", 100)], None);
        let marked = record(&[("start", 100), ("mark", 200)], None);
        let stopped = record(&[("start", 100), ("mark", 200), ("stop", 300)], Some(300));
        let forged = record(&[("start", 100), ("mark", 200), ("mark", 250), ("mark", 400), ("mark", 500)], None);
        assert_eq!(judge(&start, &marked), Verdict::Replace);
        assert_eq!(judge(&marked, &stopped), Verdict::Replace);
        assert_eq!(judge(&stopped, &stopped.clone()), Verdict::Same);
        // The forgery with more (and later) events does not replace the stop record…
        assert!(matches!(judge(&stopped, &forged), Verdict::Refuse { older: false, .. }));
        // …and the stop record replaces a forgery held before it.
        assert_eq!(judge(&forged, &stopped), Verdict::Replace);
        // An older version, redelivered.
        assert!(matches!(judge(&marked, &start), Verdict::Refuse { older: true, .. }));
        assert!(matches!(judge(&stopped, &marked), Verdict::Refuse { older: true, .. }));
        // A re-analysis adds an event after the stop: taken; another stop is not.
        let reanalysed = record(&[("start", 100), ("mark", 200), ("stop", 300), ("reanalysis", 900)], Some(300));
        assert_eq!(judge(&stopped, &reanalysed), Verdict::Replace);
        let other_stop = record(&[("start", 100), ("stop", 280)], Some(280));
        assert!(matches!(judge(&stopped, &other_stop), Verdict::Refuse { older: false, .. }));
        // The method filled in after the start: the same events, a newer version.
        let mut with_method = start.clone();
        with_method.meta.operator = Some("Ann".into());
        assert_eq!(judge(&start, &with_method), Verdict::Replace);
        // Another start with the same id.
        let mut other = start.clone();
        other.started_t_ns = 50;
        assert!(matches!(judge(&start, &other), Verdict::Refuse { .. }));
        // Running versions that tell another story: the later one.
        let a = record(&[("start", 100), ("mark", 200)], None);
        let b = record(&[("start", 100), ("zero", 150)], None);
        assert!(matches!(judge(&a, &b), Verdict::Refuse { .. }));
        assert_eq!(judge(&b, &a), Verdict::Replace);
    }
}
