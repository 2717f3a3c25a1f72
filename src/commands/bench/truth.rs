//! The bench's figures against a synthetic recording's truth: the net deflection's error line
//! by line, its noise (whole and settled) and its response to a step.

use serde::Serialize;

/// How the net deflection followed a step of its truth (`BenchFigures::step`).
#[derive(Debug, Clone, Serialize)]
pub struct StepResponse {
    /// The step of the true net deflection, mm.
    pub step_mm: f64,
    /// Errors of the first four lines after the step, µm, less the mean error of the lines
    /// before it (the zero's own offset): `[0]` is the first set after the step, half a frame
    /// period after it.
    pub errors_after_um: Vec<f64>,
    /// Lines after the step before the error stays within 10 % of the step for five lines in
    /// a row (0: from the first set after it on, i.e. within half a frame period of the step);
    /// `None` if it never does.
    pub sets_to_10_percent: Option<usize>,
}

/// The true net deflection and the feed's error against it, line by line (the first line
/// with a net deflection is the reference, as the feed's displacements), mm.
pub(super) fn net_errors(rec: &crate::config::Recording, lines: &[tagdeflect_core::feed::FeedLine]) -> Vec<(f64, f64)> {
    use crate::config::TagRole;
    let up = nalgebra::Vector3::from(rec.config.world.up).normalize();
    let mut first = std::collections::HashMap::new();
    let mut out = Vec::new();
    for l in lines {
        let tr = crate::accuracy::truth_at(&rec.truth, l.t_ns);
        let mut down = std::collections::HashMap::new();
        for t in &l.tags {
            if let Some(p) = tr.get(&t.id) {
                let p0 = *first.entry(t.id).or_insert(*p);
                down.insert(t.id, -(p - p0).dot(&up));
            }
        }
        let Some(net) = l.net_deflection_mm else { continue };
        let mean = |role: TagRole| {
            let v: Vec<f64> =
                l.tags.iter().filter(|t| rec.config.role_of(t.id) == Some(role)).filter_map(|t| down.get(&t.id)).copied().collect();
            (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
        };
        if let (Some(m), Some(s)) = (mean(TagRole::Midspan), mean(TagRole::Support)) {
            out.push((m - s, net - (m - s)));
        }
    }
    out
}

/// Time after the first line with a net deflection from which the output noise counts as
/// settled (`net_noise_settled_mm`), ns.
pub(super) const SETTLE_NS: i64 = 1_000_000_000;

/// The lines from `after_ns` past the first line with a net deflection on (none when there
/// is no such line).
pub(super) fn settled(lines: &[tagdeflect_core::feed::FeedLine], after_ns: i64) -> &[tagdeflect_core::feed::FeedLine] {
    let Some(t0) = lines.iter().find(|l| l.net_deflection_mm.is_some()).map(|l| l.t_ns) else { return &[] };
    let from = lines.iter().position(|l| l.t_ns >= t0 + after_ns).unwrap_or(lines.len());
    &lines[from..]
}

/// Standard deviation of the net deflection's error against truth (`net_errors`), mm.
pub(super) fn net_noise(errors: &[(f64, f64)]) -> Option<f64> {
    if errors.len() < 2 {
        return None;
    }
    let n = errors.len() as f64;
    let mean = errors.iter().map(|e| e.1).sum::<f64>() / n;
    Some((errors.iter().map(|e| (e.1 - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt())
}

/// The response to a step of the true net deflection (`net_errors`): one change between
/// consecutive lines at least 20× every other, with at least three lines before it and five
/// after; `None` for any other course (a ramp, a recording at rest).
pub(super) fn step_response(errors: &[(f64, f64)]) -> Option<StepResponse> {
    let changes: Vec<f64> = errors.windows(2).map(|w| w[1].0 - w[0].0).collect();
    let (k, step) = changes.iter().copied().enumerate().max_by(|a, b| a.1.abs().total_cmp(&b.1.abs()))?;
    let at = k + 1;
    let alone = changes.iter().enumerate().all(|(j, c)| j == k || c.abs() * 20.0 <= step.abs());
    if step == 0.0 || !alone || at < 3 || errors.len() < at + 5 {
        return None;
    }
    let offset = errors[..at].iter().map(|e| e.1).sum::<f64>() / at as f64;
    let after: Vec<f64> = errors[at..].iter().map(|e| e.1 - offset).collect();
    let within = |e: &f64| e.abs() <= 0.1 * step.abs();
    Some(StepResponse {
        step_mm: step,
        errors_after_um: after.iter().take(4).map(|e| e * 1e3).collect(),
        sets_to_10_percent: (0..=after.len() - 5).find(|&j| after[j..j + 5].iter().all(within)),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_step_is_found_and_its_settling_counted() {
        // Truth 0 for 6 lines, then 0.05 mm; the error has an offset of 2 µm, the estimate
        // lags by 30 % and 12 % of the step in the first two lines after it.
        let truth = |k: usize| if k < 6 { 0.0 } else { 0.05 };
        let err = |k: usize| 0.002 + [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -0.015, -0.006, 0.001, -0.001, 0.0, 0.0, 0.0][k];
        let errors: Vec<(f64, f64)> = (0..13).map(|k| (truth(k), err(k))).collect();
        let s = step_response(&errors).unwrap();
        assert!((s.step_mm - 0.05).abs() < 1e-12);
        assert_eq!(s.errors_after_um.iter().map(|e| e.round() as i64).collect::<Vec<_>>(), [-15, -6, 1, -1]);
        assert_eq!(s.sets_to_10_percent, Some(2));
        // A ramp is no step; nor is a recording at rest.
        let ramp: Vec<(f64, f64)> = (0..13).map(|k| (k as f64 * 0.01, 0.0)).collect();
        assert!(step_response(&ramp).is_none());
        let rest: Vec<(f64, f64)> = (0..13).map(|k| (0.0, k as f64 * 1e-4)).collect();
        assert!(step_response(&rest).is_none());
        assert!(net_noise(&rest).unwrap() > 0.0);
        // Never within 10 %: said.
        let slow: Vec<(f64, f64)> = (0..13).map(|k| (truth(k), if k < 6 { 0.0 } else { -0.01 })).collect();
        assert_eq!(step_response(&slow).unwrap().sets_to_10_percent, None);
    }

    #[test]
    fn the_settled_noise_counts_from_a_second_after_the_first_net_deflection() {
        let line = |t_ns: i64, net: Option<f64>| tagdeflect_core::feed::FeedLine { t_ns, net_deflection_mm: net, ..Default::default() };
        // No net deflection on the first two lines; the first one at 0.5 s.
        let lines: Vec<_> = (0..10).map(|k| line(k * 250_000_000, (k >= 2).then_some(0.0))).collect();
        let s = settled(&lines, SETTLE_NS);
        assert_eq!(s.first().map(|l| l.t_ns), Some(1_500_000_000));
        assert_eq!(s.len(), 4);
        assert!(settled(&lines, 10 * SETTLE_NS).is_empty());
        assert!(settled(&lines[..2], 0).is_empty());
    }
}
