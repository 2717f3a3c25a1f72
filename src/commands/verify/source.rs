//! Where the known displacements come from: SPEC's `--reference FILE` (JSON Lines grouped
//! into holds), the extensions `--steps FILE` (a step plan) and `--reference-from-stroke`
//! (the holds of the UTM's stroke in the recording's `utm.jsonl`: the crosshead carries the
//! target), or the recording's own `reference.jsonl` (else `verify_steps.json`) when none is
//! given; and which quantity they are compared with.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use tagdeflect_core::feed::FeedLine;
use tagdeflect_core::BadInput;
use tagdeflect_verify::reference::{holds, parse_reference, plan_from_holds};
use tagdeflect_verify::{holds_from_stroke, Hold, Quantity, StepPlan, StrokeHolds, REFERENCE_FILE, VERIFY_STEPS_FILE};

use crate::config::Recording;

use super::VerifyArgs;

/// Fraction of each hold's lines left out at its start while the target settles.
const SETTLE_FRACTION: f64 = 0.3;

/// The known displacements as read, before the feed is known.
#[derive(Debug, Clone)]
pub enum Source {
    /// SPEC's reference file and its holds.
    Reference {
        /// The file.
        path: PathBuf,
        /// Its holds.
        holds: Vec<Hold>,
    },
    /// The holds of the UTM's stroke (extension); `path` is the recording's `utm.jsonl`.
    Stroke {
        /// The recording's UTM file.
        path: PathBuf,
        /// Its holds.
        holds: Vec<Hold>,
    },
    /// A step plan (extension).
    Steps {
        /// The file.
        path: PathBuf,
        /// The plan.
        plan: StepPlan,
    },
}

impl Source {
    /// Reads `--reference`, `--steps`, `--reference-from-stroke`, or the recording's own file.
    pub fn read(args: &VerifyArgs, rec: &Recording) -> Result<Source> {
        if args.reference_from_stroke {
            return from_stroke(args, rec);
        }
        if let Some(path) = &args.reference {
            return read_reference(path);
        }
        if let Some(path) = &args.steps {
            return read_steps(path);
        }
        let (reference, steps) = (rec.dir.join(REFERENCE_FILE), rec.dir.join(VERIFY_STEPS_FILE));
        if reference.is_file() {
            return read_reference(&reference);
        }
        if steps.is_file() {
            return read_steps(&steps);
        }
        Err(BadInput::new(format!(
            "{}: no known displacements (give --reference FILE, or put {REFERENCE_FILE} in the recording)",
            rec.dir.display()
        ))
        .into())
    }

    /// The file the known displacements came from.
    pub fn path(&self) -> &Path {
        match self {
            Source::Reference { path, .. } | Source::Stroke { path, .. } | Source::Steps { path, .. } => path,
        }
    }

    /// The step plan over `lines` (the reference's holds padded by half the feed's median
    /// frame-set spacing).
    pub fn plan(&self, lines: &[FeedLine]) -> StepPlan {
        match self {
            Source::Steps { plan, .. } => plan.clone(),
            Source::Reference { holds, .. } | Source::Stroke { holds, .. } => {
                let gaps: Vec<f64> = lines.windows(2).map(|w| (w[1].t_ns - w[0].t_ns) as f64).collect();
                let spacing_ns = tagdeflect_core::stats::median(&gaps).unwrap_or(0.0).round() as i64;
                plan_from_holds(holds, spacing_ns, SETTLE_FRACTION)
            }
        }
    }
}

/// The verified quantity of `args`: `--gauge`, `--tag`, `--all-tags`, else the net deflection.
pub fn quantity(args: &VerifyArgs) -> Quantity {
    match (&args.gauge, args.tag) {
        (Some(name), _) => Quantity::Gauge(name.clone()),
        (None, Some(id)) => Quantity::Tag(id),
        (None, None) if args.all_tags => Quantity::TagsMean,
        (None, None) => Quantity::NetDeflection,
    }
}

fn read_text(path: &Path) -> Result<String> {
    if !path.is_file() {
        return Err(BadInput::new(format!("{}: no such file", path.display())).into());
    }
    std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))
}

fn read_reference(path: &Path) -> Result<Source> {
    let text = read_text(path)?;
    let points = parse_reference(&text).map_err(|e| BadInput::new(format!("{}:{}: {}", path.display(), e.line, e.message)))?;
    Ok(Source::Reference { path: path.to_path_buf(), holds: holds(&points) })
}

/// The holds of the recording's UTM stroke (`--stroke-tolerance-um`, `--stroke-min-hold-s`,
/// `--stroke-sign`); at least two are needed (the zero and one displacement).
fn from_stroke(args: &VerifyArgs, rec: &Recording) -> Result<Source> {
    let path = rec.dir.join(tagdeflect_io::recording::UTM_FILE);
    let bad = |what: String| -> anyhow::Error { BadInput::new(format!("{}: {what}", path.display())).into() };
    let samples: Vec<(i64, f64)> = rec.utm.iter().filter_map(|s| s.stroke_mm.map(|v| (s.t_ns, v))).collect();
    if samples.is_empty() {
        return Err(bad("no UTM sample with a stroke (--reference-from-stroke needs the stroke recorded)".into()));
    }
    let ok = |v: f64| v.is_finite() && v > 0.0;
    if !ok(args.stroke_tolerance_um) || !ok(args.stroke_min_hold_s) || args.stroke_sign.abs() != 1.0 {
        return Err(BadInput::new("--stroke-tolerance-um and --stroke-min-hold-s must be positive, --stroke-sign 1 or -1").into());
    }
    let rule = StrokeHolds {
        tolerance_mm: args.stroke_tolerance_um * 1e-3,
        min_hold_ns: (args.stroke_min_hold_s * 1e9).round() as i64,
        scale: args.stroke_sign,
    };
    let holds = holds_from_stroke(&samples, &rule);
    if holds.len() < 2 {
        return Err(bad(format!(
            "{} hold(s) of the stroke found ({} samples; a hold stays within {} µm for {} s): expected the zero and at least one displacement",
            holds.len(),
            samples.len(),
            args.stroke_tolerance_um,
            args.stroke_min_hold_s
        )));
    }
    Ok(Source::Stroke { path, holds })
}

fn read_steps(path: &Path) -> Result<Source> {
    let text = read_text(path)?;
    let plan = StepPlan::from_json(&text).map_err(|e| BadInput::new(format!("{}: {e}", path.display())))?;
    plan.windows(0, 1).map_err(|e| BadInput::new(format!("{}: {e}", path.display())))?;
    Ok(Source::Steps { path: path.to_path_buf(), plan })
}
