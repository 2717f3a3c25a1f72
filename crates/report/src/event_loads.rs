//! The load at each of the test's marks and crack entries (`report.json` `events`, the page's
//! *Test record*): the curve's load (the UTM's own samples when there is a UTM stream, else
//! the feed's) interpolated linearly in time at the event's time. This extends SPEC "Report"
//! (docs/report.md, "The marks' loads").

use tagdeflect_core::feed::FeedEvent;

use crate::curve::Curve;

/// True for the events the operator enters during the loading, whose load a reader wants.
fn has_load(e: &FeedEvent) -> bool {
    matches!(e.kind.as_str(), "mark" | "crack")
}

/// The load (kN, to the UTM's 1 N) at `t_ns`, linear between the curve's two points around it;
/// `None` outside the curve's time span.
pub(crate) fn load_at_time(c: &Curve, t_ns: i64) -> Option<f64> {
    let (&first, &last) = (c.t_ns.first()?, c.t_ns.last()?);
    if t_ns < first || t_ns > last {
        return None;
    }
    let b = c.t_ns.partition_point(|&t| t < t_ns);
    let p = if c.t_ns[b] == t_ns {
        c.load[b]
    } else {
        let a = b - 1;
        let w = (t_ns - c.t_ns[a]) as f64 / (c.t_ns[b] - c.t_ns[a]) as f64;
        c.load[a] + w * (c.load[b] - c.load[a])
    };
    p.is_finite().then(|| (p * 1e3).round() / 1e3)
}

/// The load of event `e`: for a mark or a crack entry within the curve's time, else `None`.
pub(crate) fn event_load(c: &Curve, e: &FeedEvent) -> Option<f64> {
    has_load(e).then(|| load_at_time(c, e.t_ns)).flatten()
}

/// `report.json` `events`: test.json's events as they are, a mark's or crack entry's with
/// `load_kN` added when its time lies within the curve.
pub(crate) fn events_json(c: &Curve, events: &[FeedEvent]) -> serde_json::Value {
    events
        .iter()
        .map(|e| {
            let mut v = serde_json::to_value(e).expect("event");
            if let Some(p) = event_load(c, e) {
                v["load_kN"] = serde_json::json!(p);
            }
            v
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn curve() -> Curve {
        let t: Vec<f64> = (0..11).map(|i| i as f64 * 0.1).collect();
        let load: Vec<f64> = t.iter().map(|s| 20.0 * s).collect();
        let x: Vec<f64> = t.iter().map(|s| 0.5 * s).collect();
        let t_ns: Vec<i64> = (0..11).map(|i| 1_000_000_000 + i * 100_000_000).collect();
        Curve::new(t_ns, load, x, vec![Some(0.001); 11], 0.0, 1, 0.001, "CMOD").unwrap()
    }

    fn ev(kind: &str, t_ns: i64) -> FeedEvent {
        FeedEvent { kind: kind.into(), t_ns, note: Some("first crack seen".into()), user: Some("ana".into()) }
    }

    #[test]
    fn a_mark_gets_the_load_at_its_time_and_other_events_none() {
        let c = curve();
        // 0.35 s in: halfway between 6 and 8 kN.
        let events = [ev("start", 1_000_000_000), ev("mark", 1_350_000_000), ev("mark", 5_000_000_000), ev("stop", 2_000_000_000)];
        let j = events_json(&c, &events);
        assert_eq!(j[1]["load_kN"], 7.0, "{j}");
        assert_eq!(
            (j[1]["note"].as_str(), j[1]["user"].as_str(), j[1]["t_ns"].as_i64()),
            (Some("first crack seen"), Some("ana"), Some(1_350_000_000))
        );
        assert!(j[0].get("load_kN").is_none() && j[3].get("load_kN").is_none(), "{j}");
        assert!(j[2].get("load_kN").is_none(), "a mark after the curve has no load: {j}");
        assert_eq!(load_at_time(&c, 1_000_000_000), Some(0.0));
        assert_eq!(load_at_time(&c, 2_000_000_000), Some(20.0));
    }
}
