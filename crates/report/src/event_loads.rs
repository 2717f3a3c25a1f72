//! The load at each of the test's marks and crack entries (`report.json` `events`, the page's
//! *Test record*, the marks drawn on the curve): the curve's load (the UTM's own samples when
//! there is a UTM stream, else the feed's) interpolated linearly in time at the event's point
//! of the curve. An event is stamped by the daemon's clock, as the UTM's samples are; with a
//! UTM stream the curve's times are those samples' put on the cameras' clock, so the event is
//! put there by the same shift ([`OnCurve::time_ns`]). This extends SPEC "Report" (docs/report.md,
//! "The marks' loads").

use tagdeflect_core::feed::FeedEvent;

use crate::curve::Curve;
use crate::report::Report;

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

/// An event's point on a curve: the curve, and the shift (ns) from the daemon's clock, which
/// stamps the events, to the curve's ([`Report::utm_shift_ns`]).
#[derive(Clone, Copy)]
pub(crate) struct OnCurve<'a> {
    pub curve: &'a Curve,
    pub shift_ns: i64,
}

impl<'a> OnCurve<'a> {
    /// The report's curve and its shift.
    pub(crate) fn of(report: &'a Report) -> Self {
        OnCurve { curve: &report.curve, shift_ns: report.utm_shift_ns }
    }

    /// Where an event stamped `t_ns` by the daemon's clock lies on the curve's clock.
    pub(crate) fn time_ns(self, t_ns: i64) -> i64 {
        t_ns.saturating_sub(self.shift_ns)
    }

    /// The load of event `e`: for a mark or a crack entry within the curve's time, else `None`.
    pub(crate) fn event_load(self, e: &FeedEvent) -> Option<f64> {
        has_load(e).then(|| load_at_time(self.curve, self.time_ns(e.t_ns))).flatten()
    }

    /// `report.json` `events`: test.json's events as they are, a mark's or crack entry's with
    /// `load_kN` added when its point lies within the curve.
    pub(crate) fn events_json(self, events: &[FeedEvent]) -> serde_json::Value {
        events
            .iter()
            .map(|e| {
                let mut v = serde_json::to_value(e).expect("event");
                if let Some(p) = self.event_load(e) {
                    v["load_kN"] = serde_json::json!(p);
                }
                v
            })
            .collect()
    }
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
        let j = OnCurve { curve: &c, shift_ns: 0 }.events_json(&events);
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

    /// A mark stamped by the daemon's clock, as the UTM's samples are, on a curve whose times
    /// are those samples' put on the cameras' clock (`t − offset`): the mark moves with them,
    /// so it reads the load the UTM had at the mark's time, whatever the offset.
    #[test]
    fn a_mark_is_put_on_the_curves_clock_by_the_utms_shift() {
        let c = curve();
        // The UTM's clock 0.3 s ahead: the sample stamped 1.65 s is the curve's point at 1.35 s.
        let on = OnCurve { curve: &c, shift_ns: 300_000_000 };
        let j = on.events_json(&[ev("mark", 1_650_000_000), ev("crack", 1_200_000_000)]);
        assert_eq!((j[0]["load_kN"].as_f64(), j[0]["t_ns"].as_i64()), (Some(7.0), Some(1_650_000_000)), "{j}");
        assert!(j[1].get("load_kN").is_none(), "before the curve once shifted: {j}");
        assert_eq!(on.time_ns(1_650_000_000), 1_350_000_000);
    }
}
