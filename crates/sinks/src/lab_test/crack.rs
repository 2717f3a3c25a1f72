//! The operator's crack entry (`POST /api/test/crack` while a test runs, or `crack` in the stop's
//! body): where the beam cracked, from mid-span, and whether inside the middle third of the
//! span — part of a C1609/C1856 test's validity. Kept in `test.json`'s `crack` and as a `crack`
//! event.

use serde::Deserialize;
use tagdeflect_core::feed::FeedEvent;
use tagdeflect_core::lab_test::CrackEntry;

use super::state::LabTests;
use super::TestError;

/// A crack entry as sent.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CrackRequest {
    /// From mid-span, signed, mm.
    pub position_mm: f64,
    /// Inside the middle third; computed from the span when not given (and checked against it
    /// when given and the span is known).
    #[serde(default)]
    pub inside_middle_third: Option<bool>,
}

impl LabTests {
    /// Records the crack entry of the running test (a later entry replaces it).
    pub fn crack(&self, c: CrackRequest) -> Result<serde_json::Value, TestError> {
        let mut g = self.lock();
        let beam_span = g.beam_mm.get("span_mm").copied();
        let Some(r) = g.running.as_mut() else { return Err(TestError::Conflict("no test is running: no crack to enter".into())) };
        let span = r.record.meta.measured.get("span_mm").copied().or(beam_span);
        let inside = inside_middle_third(&c, span)?;
        let now = tagdeflect_core::clock::now_epoch_ns();
        let note = format!("crack at {} mm from mid-span, {} the middle third", c.position_mm, if inside { "inside" } else { "outside" });
        let ev = FeedEvent { kind: "crack".into(), t_ns: now, note: Some(note), user: None };
        super::commands::room_for(&r.record, &ev)?;
        r.record.crack = Some(CrackEntry { position_mm: c.position_mm, inside_middle_third: inside, t_ns: now });
        r.record.events.push(ev.clone());
        self.persist(r);
        self.publish(&r.record);
        g.pending.push(ev);
        drop(g);
        Ok(self.status())
    }
}

/// Whether the crack is inside the middle third (|position| ≤ span/6), checked against what
/// the operator said.
fn inside_middle_third(c: &CrackRequest, span_mm: Option<f64>) -> Result<bool, TestError> {
    let x = c.position_mm;
    if !(x.is_finite() && x.abs() <= 3000.0) {
        return Err(TestError::Bad(format!("crack: position_mm = {x}: a distance from mid-span in mm")));
    }
    let Some(span) = span_mm else {
        return c.inside_middle_third.ok_or_else(|| {
            TestError::Bad("crack: the span is not known (measured.span_mm or [specimen.beam]): say inside_middle_third".into())
        });
    };
    if x.abs() > span / 2.0 {
        return Err(TestError::Bad(format!("crack: position_mm = {x}: outside the span ({span} mm, ±{} mm from mid-span)", span / 2.0)));
    }
    let inside = x.abs() <= span / 6.0;
    match c.inside_middle_third {
        Some(said) if said != inside => Err(TestError::Bad(format!(
            "crack: position_mm = {x} is {} the middle third of the {span} mm span (±{:.1} mm), but inside_middle_third = {said}",
            if inside { "inside" } else { "outside" },
            span / 6.0
        ))),
        _ => Ok(inside),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_middle_third_is_computed_and_checked() {
        let c = |x: f64, said: Option<bool>| CrackRequest { position_mm: x, inside_middle_third: said };
        assert!(inside_middle_third(&c(74.0, None), Some(450.0)).unwrap());
        assert!(!inside_middle_third(&c(-76.0, None), Some(450.0)).unwrap());
        assert!(inside_middle_third(&c(76.0, Some(true)), Some(450.0)).is_err(), "a contradiction is refused");
        assert!(inside_middle_third(&c(300.0, None), Some(450.0)).is_err(), "outside the span");
        assert!(inside_middle_third(&c(10.0, None), None).is_err(), "no span: the operator says");
        assert!(!inside_middle_third(&c(10.0, Some(false)), None).unwrap());
        assert!(inside_middle_third(&c(f64::NAN, Some(true)), None).is_err());
    }
}
