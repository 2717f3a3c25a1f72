//! The whole verification: a feed and a step plan in, the certificate's figures out.

use serde::{Deserialize, Serialize};
use tagdeflect_core::feed::FeedLine;

use crate::iso9513::{classify, resolution_mm, ClassResult};
use crate::quantity::Quantity;
use crate::series::{down_displacement, tag_down_displacement, Series};
use crate::stability::{stability, Stability};
use crate::steps::{known_figures, step_result, KnownFigures, StepResult};
use crate::uncertainty::{budget, Inputs, Uncertainty};
use crate::{StepPlan, VerifyError};

/// What the figures need besides the feed and the plan.
#[derive(Debug, Clone, PartialEq)]
pub struct VerifyOptions {
    /// The verified quantity: what the plan's positions are compared with.
    pub quantity: Quantity,
    /// The world's up direction (config `world.up`): displacements count downward along it.
    pub up: [f64; 3],
    /// The reference's expanded uncertainty as typed, mm.
    pub reference_u_mm: f64,
    /// Its coverage factor.
    pub reference_k: f64,
}

/// The static hold (the first step): noise, drift and Allan deviation.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StaticFigures {
    /// The verified quantity (its SD gives the resolution).
    pub quantity: Stability,
    /// The mean downward displacement of the tags.
    pub displacement: Stability,
    /// The net deflection.
    pub net_deflection: Option<Stability>,
    /// Each tag's downward displacement, by id.
    pub tags: Vec<(u32, Stability)>,
}

/// VDI/VDE 2626's checks of an optical system with a rigid piece.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct VdiFigures {
    /// ZS applies: the verified quantity is a rigid target's displacement (a tag or the tags'
    /// mean), so its net deflection must stay zero. When the verified quantity is the net
    /// deflection or a gauge, the target deforms by design (a staged target, docs/verification.md)
    /// and ZS is not applicable: its figures are then absent.
    #[serde(default = "zs_applies_default")]
    pub zs_applies: bool,
    /// ZS (zero strain): the net deflection of the rigid piece over every hold, largest |mean of a hold|, mm.
    pub zs_net_deflection_mm: Option<f64>,
    /// ZS: SD of one net-deflection reading at rest, mm.
    pub zs_net_deflection_sd_mm: Option<f64>,
    /// ZD (zero displacement): SD of one displacement reading at rest, mm.
    pub zd_sd_mm: Option<f64>,
    /// ZD: largest |reading − mean| at rest, mm.
    pub zd_max_mm: Option<f64>,
    /// D (known displacements): largest |error| of a step, mm.
    pub d_max_error_mm: f64,
    /// D: scale error of the best-fit line, % (`(slope − 1) × 100`).
    pub d_scale_error_pct: Option<f64>,
}

/// Certificates made before `zs_applies` existed verified a rigid target.
fn zs_applies_default() -> bool {
    true
}

/// The verdict and why.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Verdict {
    /// A class of ISO 9513 was reached.
    pub passed: bool,
    /// The reasons, one sentence each.
    pub reasons: Vec<String>,
}

/// Everything a certificate states.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Verification {
    /// The verified quantity.
    pub quantity: Quantity,
    /// Feed lines read.
    pub lines: usize,
    /// The static hold.
    #[serde(rename = "static")]
    pub static_figures: StaticFigures,
    /// Each step.
    pub steps: Vec<StepResult>,
    /// Bias, linearity, repeatability, hysteresis.
    pub known: KnownFigures,
    /// ISO 9513.
    pub iso9513: ClassResult,
    /// VDI/VDE 2626.
    pub vdi2626: VdiFigures,
    /// The expanded uncertainty of a deflection.
    pub uncertainty: Uncertainty,
    /// The verdict.
    pub verdict: Verdict,
}

/// Computes the verification of `lines` (a recording's feed) held at `plan`'s steps.
pub fn verify(lines: &[FeedLine], plan: &StepPlan, opts: &VerifyOptions) -> Result<Verification, VerifyError> {
    let (first, last) = match (lines.first(), lines.last()) {
        (Some(a), Some(b)) => (a.t_ns, b.t_ns),
        _ => return Err(VerifyError::Feed("no feed lines".into())),
    };
    let windows = plan.windows(first, last)?;
    let readings = opts.quantity.readings(lines, opts.up);
    let holds: Vec<Vec<usize>> = windows.iter().map(|&(_, a, b)| settled(lines, a, b, plan.settle_fraction)).collect();
    let mut steps = Vec::new();
    for (i, (&(position, _, _), hold)) in windows.iter().zip(&holds).enumerate() {
        let values: Vec<f64> = hold.iter().filter_map(|&k| readings[k]).filter(|v| v.is_finite()).collect();
        let net: Vec<f64> = hold.iter().filter_map(|&k| lines[k].net_deflection_mm).collect();
        let previous = i.checked_sub(1).map(|j| windows[j].0);
        // The feed's displacements count from the first frame set, held at the first step.
        let r = step_result(i + 1, position, windows[0].0, previous, &values, &net).ok_or_else(|| {
            VerifyError::Feed(format!("step {} ({position} mm): no line with the {} in its hold", i + 1, opts.quantity.describe()))
        })?;
        steps.push(r);
    }
    let rest: Vec<&FeedLine> = holds[0].iter().map(|&k| &lines[k]).collect();
    let quantity_at_rest = quantity_series(lines, &readings, &holds[0], first);
    let static_figures = static_figures(&rest, stability(&quantity_at_rest), first, opts.up);
    let known = known_figures(&steps);
    let noise = static_figures.quantity.sd_mm.unwrap_or(0.0);
    let iso9513 = classify(&steps, resolution_mm(noise));
    let uncertainty = budget(&Inputs {
        max_error_mm: known.max_error_mm,
        repeatability_mm: known.repeatability_mm.unwrap_or(0.0),
        noise_mm: noise,
        reference_u_mm: opts.reference_u_mm,
        reference_k: opts.reference_k,
        range_mm: known.range_mm,
    });
    let vdi2626 = vdi(&static_figures, &steps, &known, &rest, opts);
    let verdict = verdict(&iso9513, &known, &uncertainty, &static_figures);
    let quantity = opts.quantity.clone();
    Ok(Verification { quantity, lines: lines.len(), static_figures, steps, known, iso9513, vdi2626, uncertainty, verdict })
}

/// The indices of the lines of `[a, b)` after the settling fraction.
fn settled(lines: &[FeedLine], a: i64, b: i64, settle_fraction: f64) -> Vec<usize> {
    let hold: Vec<usize> = (0..lines.len()).filter(|&k| lines[k].t_ns >= a && lines[k].t_ns < b).collect();
    let skip = (hold.len() as f64 * settle_fraction).floor() as usize;
    hold[skip.min(hold.len())..].to_vec()
}

/// The verified quantity's series over the lines `hold` (times from `t0`).
fn quantity_series(lines: &[FeedLine], readings: &[Option<f64>], hold: &[usize], t0: i64) -> Series {
    let mut s = Series::default();
    for &k in hold {
        if let Some(v) = readings[k].filter(|v| v.is_finite()) {
            s.t_s.push((lines[k].t_ns - t0) as f64 * 1e-9);
            s.value_mm.push(v);
        }
    }
    s
}

fn static_figures(hold: &[&FeedLine], quantity: Stability, t0: i64, up: [f64; 3]) -> StaticFigures {
    let mut ids: Vec<u32> = hold.iter().flat_map(|l| l.tags.iter().map(|t| t.id)).collect();
    ids.sort_unstable();
    ids.dedup();
    let net = Series::from_feed(hold, t0, |l| l.net_deflection_mm);
    StaticFigures {
        quantity,
        displacement: stability(&Series::from_feed(hold, t0, |l| down_displacement(l, up))),
        net_deflection: (!net.is_empty()).then(|| stability(&net)),
        tags: ids.into_iter().map(|id| (id, stability(&Series::from_feed(hold, t0, |l| tag_down_displacement(l, id, up))))).collect(),
    }
}

fn vdi(st: &StaticFigures, steps: &[StepResult], known: &KnownFigures, hold: &[&FeedLine], opts: &VerifyOptions) -> VdiFigures {
    let rest = Series::from_feed(hold, 0, |l| down_displacement(l, opts.up)).value_mm;
    let mean = crate::series::mean(&rest);
    let zs_applies = matches!(opts.quantity, Quantity::Tag(_) | Quantity::TagsMean);
    VdiFigures {
        zs_applies,
        zs_net_deflection_mm: steps.iter().filter_map(|s| s.net_deflection_mm.map(f64::abs)).reduce(f64::max).filter(|_| zs_applies),
        zs_net_deflection_sd_mm: st.net_deflection.as_ref().and_then(|s| s.sd_mm).filter(|_| zs_applies),
        zd_sd_mm: st.displacement.sd_mm,
        zd_max_mm: mean.map(|m| rest.iter().map(|v| (v - m).abs()).fold(0.0, f64::max)),
        d_max_error_mm: known.max_error_mm,
        d_scale_error_pct: known.slope.map(|b| (b - 1.0) * 100.0),
    }
}

fn verdict(class: &ClassResult, known: &KnownFigures, u: &Uncertainty, st: &StaticFigures) -> Verdict {
    let um = |mm: f64| format!("{:.2} µm", mm * 1e3);
    let mut reasons = Vec::new();
    match &class.class {
        Some(c) => reasons.push(format!(
            "ISO 9513 class {c}: the bias at every step and the resolution ({}) are within its limits",
            um(class.resolution_mm)
        )),
        None => reasons.push("no ISO 9513 class: the limits of class 2 are exceeded".into()),
    }
    for c in class.checks.iter().take_while(|c| Some(&c.class) != class.class.as_ref()) {
        if !c.bias_ok {
            reasons.push(format!(
                "not class {}: step {} uses {:.0} % of its bias limit",
                c.class,
                c.worst_bias_step,
                c.worst_bias_ratio * 100.0
            ));
        }
        if !c.resolution_ok {
            reasons.push(format!("not class {}: the resolution {} exceeds its limit", c.class, um(class.resolution_mm)));
        }
    }
    reasons.push(format!(
        "expanded uncertainty U (k = 2) of a deflection over {:.3}–{:.3} mm: {}",
        u.range_mm[0],
        u.range_mm[1],
        um(u.expanded_mm)
    ));
    reasons.push(format!("largest step error {}, bias {}", um(known.max_error_mm), um(known.bias_mm)));
    match st.quantity.drift_mm_per_h {
        Some(d) => reasons.push(format!("drift at rest {} per hour over {:.0} s", um(d), st.quantity.duration_s)),
        None => reasons.push(format!("drift at rest: not enough data ({:.1} s at rest, 60 s needed)", st.quantity.duration_s)),
    }
    Verdict { passed: class.class.is_some(), reasons }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tagdeflect_core::feed::FeedTag;

    /// A feed of two tags moved rigidly through `positions` (10 lines each, 0.1 s apart), the
    /// tag 2 reading `error_mm` more at step `bad`.
    fn feed(positions: &[f64], bad: usize, error_mm: f64) -> Vec<FeedLine> {
        let mut lines = Vec::new();
        for (i, p) in positions.iter().enumerate() {
            for k in 0..10 {
                let seq = (i * 10 + k) as u64;
                let wobble = if k % 2 == 0 { 3e-4 } else { -3e-4 };
                let extra = if i == bad { 2.0 * error_mm } else { 0.0 };
                let tag = |id, e: f64| FeedTag {
                    id,
                    pos_mm: [0.0; 3],
                    disp_mm: [0.0, 0.0, -(p + wobble + e)],
                    views: 2,
                    sigma_mm: None,
                    disp_sigma_mm: None,
                    reproj_px: None,
                };
                lines.push(FeedLine {
                    seq,
                    t_ns: seq as i64 * 100_000_000,
                    tags: vec![tag(1, 0.0), tag(2, extra)],
                    net_deflection_mm: Some(wobble),
                    ..FeedLine::default()
                });
            }
        }
        lines
    }

    #[test]
    fn a_rigid_target_through_its_steps_gives_the_class_its_errors_allow() {
        let positions = [0.0, 0.5, 1.0, 2.0, 1.0, 0.5, 0.0];
        let opts = VerifyOptions { quantity: Quantity::TagsMean, up: [0.0, 0.0, 1.0], reference_u_mm: 0.0, reference_k: 2.0 };
        let plan = StepPlan::from_positions(&positions);
        let good = verify(&feed(&positions, usize::MAX, 0.0), &plan, &opts).unwrap();
        assert_eq!(good.steps.len(), 7);
        assert!(good.known.max_error_mm < 1e-4, "{:?}", good.known);
        assert_eq!(
            good.iso9513.class.as_deref(),
            Some("0.5"),
            "a resolution of 2 × 0.3 µm rules out class 0.2 (0.5 µm at 0.5 mm) ({:?})",
            good.iso9513
        );
        assert!(good.verdict.passed);
        // 7 µm (mean of the two tags) at the first 1 mm step: class 0.5 allows 5 µm, class 1 10 µm.
        let bad = verify(&feed(&positions, 2, 0.007), &plan, &opts).unwrap();
        assert_eq!(bad.iso9513.class.as_deref(), Some("1"));
        assert!((bad.known.hysteresis_mm.unwrap() - 0.007).abs() < 1e-6);
        assert!(bad.verdict.reasons.iter().any(|r| r.starts_with("not class 0.5: step 3")), "{:?}", bad.verdict.reasons);
        assert!(bad.uncertainty.expanded_mm > good.uncertainty.expanded_mm);
    }
}
