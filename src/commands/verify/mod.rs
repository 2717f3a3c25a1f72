//! `tagdeflect verify DIR --reference FILE --out OUT`: the verification of the rig from a
//! recording of a target at rest and at known displacements (docs/verification.md). The recording is replayed
//! in-process, the figures computed by `tagdeflect-verify`, and the certificate written into
//! `verify/<date>/`: `verification.json`, `verification.html` (and `verification.pdf` when
//! Chromium prints it) and the raw recording (hard links, else copies). With `--live` the rig
//! itself is recorded first, into the certificate's folder (`live`).

mod certificate;
mod html;
pub mod live;
mod source;

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use tagdeflect_core::feed::FeedLine;
use tagdeflect_core::BadInput;
use tagdeflect_verify::VerifyOptions;

use crate::graph::in_process::{self, ReplayOptions};

pub use certificate::{Certificate, Equipment};
pub use source::Source;

/// The options of `tagdeflect verify`.
#[derive(Debug, Clone, clap::Args)]
pub struct VerifyArgs {
    /// The recording of the verification (a rigid target at rest, then at known positions);
    /// not with `--live`.
    #[arg(required_unless_present = "live", conflicts_with = "live")]
    pub dir: Option<PathBuf>,
    /// (extension) Record the rig of `--config` for `--duration-s` first (into the
    /// certificate's `recording/`), then verify that recording.
    #[arg(long, requires_all = ["config", "duration_s"])]
    pub live: bool,
    /// With `--live`: the rig's config.
    #[arg(long, value_name = "FILE", requires = "live")]
    pub config: Option<PathBuf>,
    /// With `--live`: how long to record, s.
    #[arg(long, value_name = "S", requires = "live")]
    pub duration_s: Option<f64>,
    /// With `--live`: the positions typed on standard input while it records (each held from
    /// its Enter for `--hold-s`), instead of a reference file or the stroke.
    #[arg(long, requires = "live", conflicts_with_all = ["reference", "steps", "reference_from_stroke"])]
    pub type_positions: bool,
    /// With `--type-positions`: how long each typed position is held, s.
    #[arg(long, value_name = "S", default_value_t = 10.0)]
    pub hold_s: f64,
    /// The known displacements (SPEC): JSON Lines `{"t_ns": ..., "displacement_mm": ...}`,
    /// consecutive equal values one hold; default: the recording's own `reference.jsonl`.
    #[arg(long, value_name = "FILE", conflicts_with = "steps")]
    pub reference: Option<PathBuf>,
    /// (extension) A step plan instead: `verify_steps.json` (`{"steps": [{"position_mm",
    /// "start_ns", "end_ns"}]}`, or a bare array of positions in mm held for equal times).
    #[arg(long, value_name = "FILE")]
    pub steps: Option<PathBuf>,
    /// (extension) The known displacements from the UTM's stroke in the recording: each
    /// position the crosshead holds is a hold of the reference (the crosshead carries the target).
    #[arg(long, conflicts_with_all = ["reference", "steps"])]
    pub reference_from_stroke: bool,
    /// With `--reference-from-stroke`: the largest range of the stroke within a hold, µm.
    #[arg(long, value_name = "UM", default_value_t = 2.0)]
    pub stroke_tolerance_um: f64,
    /// With `--reference-from-stroke`: the shortest hold, s.
    #[arg(long, value_name = "S", default_value_t = 1.0)]
    pub stroke_min_hold_s: f64,
    /// With `--reference-from-stroke`: 1 when the stroke grows as the target moves down, −1
    /// when it grows as it rises.
    #[arg(long, value_name = "SIGN", default_value_t = 1.0, allow_negative_numbers = true)]
    pub stroke_sign: f64,
    /// Verify this `[[gauge]]`'s value instead of the net deflection.
    #[arg(long, value_name = "NAME", conflicts_with_all = ["tag", "all_tags"])]
    pub gauge: Option<String>,
    /// Verify this specimen tag's vertical displacement (downward positive) instead of the
    /// net deflection.
    #[arg(long, value_name = "ID", conflicts_with = "all_tags")]
    pub tag: Option<u32>,
    /// (extension) Verify the mean downward displacement of the specimen tags.
    #[arg(long)]
    pub all_tags: bool,
    /// Who ran the verification (printed on the certificate).
    #[arg(long, value_name = "NAME")]
    pub operator: Option<String>,
    /// The reference equipment's identification (micrometer stage, height gauge, ...), as typed.
    #[arg(long, value_name = "TEXT")]
    pub equipment: Option<String>,
    /// The date of the reference equipment's own calibration, as typed.
    #[arg(long, value_name = "DATE")]
    pub equipment_calibrated: Option<String>,
    /// The expanded uncertainty of the reference's positions (k = 2), µm, from its certificate.
    #[arg(long, value_name = "UM", default_value_t = 0.0)]
    pub reference_u_um: f64,
    /// The certificate's folder (new or empty); default `verify/<date>/` (a time is added
    /// when that folder is taken).
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
    /// Do not print verification.pdf.
    #[arg(long)]
    pub no_pdf: bool,
}

/// Runs `tagdeflect verify`; returns the certificate's folder.
pub fn run(args: &VerifyArgs) -> Result<PathBuf> {
    if !args.reference_u_um.is_finite() || args.reference_u_um < 0.0 {
        return Err(BadInput::new(format!("--reference-u-um {}: expected a non-negative number of µm", args.reference_u_um)).into());
    }
    if !args.hold_s.is_finite() || args.hold_s <= 0.0 {
        return Err(BadInput::new(format!("--hold-s {}: expected a positive number of seconds", args.hold_s)).into());
    }
    let out = out_dir(args.out.as_deref())?;
    let (dir, recorded_here) = match (&args.dir, args.live) {
        (_, true) => {
            std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
            (live::record(args, &out)?, true)
        }
        (Some(dir), false) => (dir.clone(), false),
        (None, false) => return Err(BadInput::new("verify needs a recording DIR, or --live --config FILE --duration-s S").into()),
    };
    let rec = in_process::open(&dir, None)?;
    let source = Source::read(args, &rec)?;
    let quantity = source::quantity(args);
    let mut lines: Vec<FeedLine> = Vec::new();
    let summary = in_process::replay(&rec, ReplayOptions { progress: true, ..Default::default() }, |l, _, _| lines.push(l.clone()))?;
    let plan = source.plan(&lines);
    let opts = VerifyOptions { quantity, up: rec.config.world.up, reference_u_mm: args.reference_u_um * 1e-3, reference_k: 2.0 };
    let verification = tagdeflect_verify::verify(&lines, &plan, &opts).map_err(|e| BadInput::new(format!("{}: {e}", dir.display())))?;
    let equipment = Equipment {
        description: args.equipment.clone(),
        calibrated: args.equipment_calibrated.clone(),
        reference_u_um: args.reference_u_um,
    };
    let cert = Certificate::new(&rec, &source, &plan, summary.sets, args.operator.clone(), equipment, verification)?;
    write(&cert, &lines, (!recorded_here).then_some(dir.as_path()), &out, !args.no_pdf)?;
    tracing::info!(
        "{}: {} class {}, U (k = 2) {:.2} µm — {}",
        out.display(),
        cert.quantity,
        cert.class_iso9513,
        cert.u_k2_mm * 1e3,
        if cert.verification.verdict.passed { "passed" } else { "NOT passed" }
    );
    Ok(out)
}

/// The certificate's folder: `out` (new or empty), else `verify/<date>` (or `<date>T<time>`
/// when taken).
fn out_dir(out: Option<&Path>) -> Result<PathBuf> {
    let now = chrono::Utc::now();
    let dir = match out {
        Some(d) => d.to_path_buf(),
        None => {
            let day = PathBuf::from("verify").join(now.format("%Y-%m-%d").to_string());
            if day.exists() {
                PathBuf::from("verify").join(now.format("%Y-%m-%dT%H%M%S").to_string())
            } else {
                day
            }
        }
    };
    if dir.exists() && std::fs::read_dir(&dir).map(|mut d| d.next().is_some()).unwrap_or(true) {
        return Err(
            BadInput::new(format!("{}: the certificate's folder exists and is not empty (nothing is overwritten)", dir.display())).into()
        );
    }
    Ok(dir)
}

/// Writes the certificate, its page (and PDF), the feed it was computed from and the raw
/// recording (`None`: it was recorded into `out` already).
fn write(cert: &Certificate, lines: &[FeedLine], recording: Option<&Path>, out: &Path, pdf: bool) -> Result<()> {
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let json = serde_json::to_string_pretty(cert).context("the certificate as JSON")? + "\n";
    tagdeflect_report::write_atomic(&out.join("verification.json"), json.as_bytes())?;
    let feed: String = lines.iter().map(|l| l.to_json() + "\n").collect();
    tagdeflect_report::write_atomic(&out.join("feed.jsonl"), feed.as_bytes())?;
    let page = out.join("verification.html");
    tagdeflect_report::write_atomic(&page, html::page(cert).as_bytes())?;
    if pdf {
        match tagdeflect_report::print_pdf(&page, &out.join("verification.pdf")) {
            Ok(true) => {}
            Ok(false) => tracing::info!("no Chromium found: verification.pdf not printed (print verification.html from a browser)"),
            Err(e) => tracing::warn!("verification.pdf could not be printed: {e}"),
        }
    }
    let Some(recording) = recording else { return Ok(()) };
    link_or_copy_tree(recording, &out.join("recording"))
        .with_context(|| format!("keeping the recording {} in {}", recording.display(), out.display()))
}

/// Hard-links (else copies) every file of `from` into `to`, keeping the tree.
fn link_or_copy_tree(from: &Path, to: &Path) -> std::io::Result<()> {
    std::fs::create_dir_all(to)?;
    for entry in std::fs::read_dir(from)? {
        let entry = entry?;
        let (src, dst) = (entry.path(), to.join(entry.file_name()));
        if entry.file_type()?.is_dir() {
            link_or_copy_tree(&src, &dst)?;
        } else if std::fs::hard_link(&src, &dst).is_err() {
            std::fs::copy(&src, &dst)?;
        }
    }
    Ok(())
}
