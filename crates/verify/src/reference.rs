//! The known displacements of a verification as SPEC gives them (`--reference FILE`): JSON
//! Lines `{"t_ns": ..., "displacement_mm": ...}`, grouped into holds.
//!
//! Consecutive lines with the same displacement (within [`SAME_MM`]) form one hold: the
//! reference value held from the hold's first time to its last. Each hold's window reaches
//! half the feed's median frame-set spacing beyond its first and last time (so a single
//! line is a hold of the frame sets within ± half that spacing), but never past the midpoint
//! to the next or previous hold: a frame set belongs to one hold at most.

use serde::Deserialize;

use crate::{StepPlan, StepWindow};

/// Name of the reference file in a recording folder (written by `simulate --verify-steps`,
/// or by the lab next to its recording).
pub const REFERENCE_FILE: &str = "reference.jsonl";

/// Two reference values closer than this are the same position, mm.
pub const SAME_MM: f64 = 1e-9;

/// One line of the reference file.
/// Other fields are ignored (a stage may log more).
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
pub struct ReferencePoint {
    /// The time, ns since the Unix epoch (the feed's `t_ns`).
    pub t_ns: i64,
    /// The known displacement of the verified quantity at that time, mm.
    pub displacement_mm: f64,
}

/// A consecutive run of reference lines with the same displacement.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hold {
    /// The displacement held, mm.
    pub displacement_mm: f64,
    /// The first line's time, ns.
    pub first_ns: i64,
    /// The last line's time, ns.
    pub last_ns: i64,
    /// Lines in the hold.
    pub lines: usize,
}

/// A reference line that cannot be read.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("line {line}: {message}")]
pub struct ReferenceError {
    /// The line number, from 1.
    pub line: usize,
    /// What is wrong with it.
    pub message: String,
}

/// Parses the reference file's text (blank lines skipped; times must not go backwards).
pub fn parse_reference(text: &str) -> Result<Vec<ReferencePoint>, ReferenceError> {
    let mut points: Vec<ReferencePoint> = Vec::new();
    for (i, raw) in text.lines().enumerate() {
        let bad = |message: String| ReferenceError { line: i + 1, message };
        if raw.trim().is_empty() {
            continue;
        }
        let p: ReferencePoint =
            serde_json::from_str(raw).map_err(|e| bad(format!("{e}: expected {{\"t_ns\": <integer>, \"displacement_mm\": <number>}}")))?;
        if !p.displacement_mm.is_finite() {
            return Err(bad("displacement_mm is not a finite number".into()));
        }
        if let Some(prev) = points.last().filter(|prev| p.t_ns < prev.t_ns) {
            return Err(bad(format!("t_ns {} is earlier than the line before ({})", p.t_ns, prev.t_ns)));
        }
        points.push(p);
    }
    if points.is_empty() {
        return Err(ReferenceError { line: 0, message: "no reference line".into() });
    }
    Ok(points)
}

/// Groups consecutive points with the same displacement into holds.
pub fn holds(points: &[ReferencePoint]) -> Vec<Hold> {
    let mut out: Vec<Hold> = Vec::new();
    for p in points {
        match out.last_mut() {
            Some(h) if (h.displacement_mm - p.displacement_mm).abs() < SAME_MM => {
                h.last_ns = p.t_ns;
                h.lines += 1;
            }
            _ => out.push(Hold { displacement_mm: p.displacement_mm, first_ns: p.t_ns, last_ns: p.t_ns, lines: 1 }),
        }
    }
    out
}

/// The step plan of `holds`: each hold's window `[first − pad, last + pad]` with `pad` half
/// the feed's median frame-set spacing `spacing_ns`, clipped at the midpoints between holds;
/// `settle_fraction` of each window's lines left out at its start.
pub fn plan_from_holds(holds: &[Hold], spacing_ns: i64, settle_fraction: f64) -> StepPlan {
    let pad = (spacing_ns.max(0) + 1) / 2;
    let steps = holds
        .iter()
        .enumerate()
        .map(|(i, h)| {
            let mut start = h.first_ns - pad;
            let mut end = h.last_ns + pad + 1;
            if let Some(prev) = i.checked_sub(1).map(|j| holds[j]) {
                start = start.max(midpoint(prev.last_ns, h.first_ns));
            }
            if let Some(next) = holds.get(i + 1) {
                end = end.min(midpoint(h.last_ns, next.first_ns));
            }
            StepWindow { position_mm: h.displacement_mm, start_ns: Some(start), end_ns: Some(end.max(start + 1)) }
        })
        .collect();
    StepPlan { steps, settle_fraction }
}

fn midpoint(a: i64, b: i64) -> i64 {
    a + (b - a) / 2
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pts(v: &[(i64, f64)]) -> Vec<ReferencePoint> {
        v.iter().map(|&(t_ns, displacement_mm)| ReferencePoint { t_ns, displacement_mm }).collect()
    }

    #[test]
    fn consecutive_equal_values_form_one_hold_and_a_return_is_a_new_one() {
        let h = holds(&pts(&[(0, 0.0), (10, 0.0), (20, 0.5), (30, 0.5), (40, 0.5), (50, 0.0)]));
        assert_eq!(
            h,
            vec![
                Hold { displacement_mm: 0.0, first_ns: 0, last_ns: 10, lines: 2 },
                Hold { displacement_mm: 0.5, first_ns: 20, last_ns: 40, lines: 3 },
                Hold { displacement_mm: 0.0, first_ns: 50, last_ns: 50, lines: 1 },
            ]
        );
    }

    #[test]
    fn windows_pad_by_half_the_spacing_and_never_overlap() {
        // Typed steps, one line each, 1000 ns apart; frame sets every 100 ns: ± 50 ns.
        let h = holds(&pts(&[(0, 0.0), (1000, 0.5), (2000, 1.0)]));
        let plan = plan_from_holds(&h, 100, 0.3);
        let w = plan.windows(0, 0).unwrap();
        assert_eq!(w, vec![(0.0, -50, 51), (0.5, 950, 1051), (1.0, 1950, 2051)]);
        // A stage logged every 100 ns with frame sets every 400 ns: clipped at the midpoints.
        let h = holds(&pts(&[(0, 0.0), (100, 0.0), (200, 0.5), (300, 0.5)]));
        let w = plan_from_holds(&h, 400, 0.3).windows(0, 0).unwrap();
        assert_eq!(w, vec![(0.0, -200, 150), (0.5, 150, 501)]);
        assert_eq!(plan.settle_fraction, 0.3);
    }

    #[test]
    fn a_bad_line_is_named_by_its_number() {
        let text = "{\"t_ns\": 1, \"displacement_mm\": 0}\n\n{\"t_ns\": 2, \"displacement\": 0.5}\n";
        assert_eq!(parse_reference(text).unwrap_err().line, 3);
        let back = "{\"t_ns\": 5, \"displacement_mm\": 0}\n{\"t_ns\": 4, \"displacement_mm\": 0}\n";
        assert_eq!(parse_reference(back).unwrap_err().line, 2);
        assert_eq!(parse_reference("{\"t_ns\": 1.5, \"displacement_mm\": 0}").unwrap_err().line, 1);
        assert_eq!(parse_reference(" \n").unwrap_err().line, 0);
        assert_eq!(parse_reference("{\"t_ns\": 1, \"displacement_mm\": 2}\n").unwrap().len(), 1);
    }
}
