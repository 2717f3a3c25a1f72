//! The certificate of a verification (`verification.json`): SPEC's keys (`class_iso9513`,
//! `bias_um`, `resolution_um`, `u_k2_mm`, `steps`, `inputs`, `date`) first, then who, with
//! what, on which rig, and the figures.

use std::collections::BTreeMap;
use std::path::Path;

use serde::Serialize;
use tagdeflect_core::camera_config::CameraConfig;
use tagdeflect_core::rig::SpecimenTag;
use tagdeflect_core::verification::CameraPlacement;

use crate::graph::in_process::ReplaySummary;
use tagdeflect_verify::{StepPlan, Verification};

use super::Source;

use crate::config::Recording;

/// The format of `verification.json`.
pub const CERTIFICATE_FORMAT: &str = "tagdeflect-verification/1";

/// The reference equipment, as typed.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Equipment {
    /// Its identification.
    pub description: Option<String>,
    /// The date of its own calibration.
    pub calibrated: Option<String>,
    /// The expanded uncertainty of its positions (k = 2), µm.
    pub reference_u_um: f64,
}

/// A file the rig was set up from, with its SHA-256.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct HashedFile {
    /// The path as found.
    pub path: String,
    /// SHA-256, lower-case hex.
    pub sha256: String,
}

/// The rig verified.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Rig {
    /// The cameras as configured (source, size, intrinsics, pose if fixed).
    pub cameras: Vec<CameraConfig>,
    /// The config in force (the recording's `tagdeflect.toml`).
    pub config: Option<HashedFile>,
    /// The calibration files the intrinsics came from.
    pub calibration_files: Vec<HashedFile>,
    /// The specimen (or verification bar) tags: id and role.
    pub tags: Vec<SpecimenTag>,
    /// The world's up direction.
    pub world_up: [f64; 3],
    /// The rig's geometry as a later run compares it (`[verification]`: a test under a
    /// changed geometry says the verification is stale; `tagdeflect_core::verification`).
    pub geometry_sha256: String,
    /// Where each posed camera was at the recording's end (a later run whose camera is not
    /// there any more says the verification is stale; `tagdeflect_core::verification`).
    pub camera_poses: Vec<CameraPlacement>,
}

/// One hold as SPEC's `steps` give it: the reference value, the measured mean on the
/// reference's scale and the error.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SpecStep {
    /// The reference's displacement held, mm.
    pub reference_mm: f64,
    /// The verified quantity's mean over the hold (after settling), on the reference's
    /// scale (counted from the first hold's reference value), mm.
    pub measured_mm: f64,
    /// `measured − reference`, µm.
    pub error_um: f64,
    /// Feed lines averaged.
    pub lines: usize,
    /// SD of one reading in the hold, µm.
    pub sd_um: Option<f64>,
}

/// Everything `verification.json` holds.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Certificate {
    /// [`CERTIFICATE_FORMAT`].
    pub format: &'static str,
    /// The ISO 9513 class reached: "0.2", "0.5", "1", "2" or "none".
    pub class_iso9513: String,
    /// The largest |error| of a hold, µm.
    pub bias_um: f64,
    /// The resolution used for the class, µm.
    pub resolution_um: f64,
    /// The expanded uncertainty (k = 2) of the verified quantity, mm.
    pub u_k2_mm: f64,
    /// Each hold: reference value, measured mean, error.
    pub steps: Vec<SpecStep>,
    /// SHA-256 of each input, by path.
    pub inputs: BTreeMap<String, String>,
    /// The date of the verification (UTC, `YYYY-MM-DD`).
    pub date: String,
    /// The verified quantity, in words.
    pub quantity: String,
    /// The file the known displacements came from.
    pub reference: String,
    /// When it was computed (UTC, RFC 3339).
    pub issued_utc: String,
    /// The tagdeflect version that computed it.
    pub version: &'static str,
    /// Who ran the verification.
    pub operator: Option<String>,
    /// The reference equipment.
    pub equipment: Equipment,
    /// The recording (as given) and its frame sets solved.
    pub recording: String,
    /// Frame sets solved.
    pub frame_sets: u64,
    /// The rig.
    pub rig: Rig,
    /// The step plan used (from the reference's holds: each window and the settling fraction).
    pub plan: StepPlan,
    /// The figures, the class, the uncertainty and the verdict.
    pub verification: Verification,
}

impl Certificate {
    /// The certificate of `verification` computed from `rec`.
    pub fn new(
        rec: &Recording,
        source: &Source,
        plan: &StepPlan,
        replayed: &ReplaySummary,
        operator: Option<String>,
        equipment: Equipment,
        verification: Verification,
    ) -> anyhow::Result<Certificate> {
        let config = &rec.config;
        let toml = rec.dir.join("tagdeflect.toml");
        let mut calibration_files = Vec::new();
        for p in config.calibration_files.iter().filter(|p| p.is_file()) {
            calibration_files.push(hashed(p)?);
        }
        let now = chrono::Utc::now();
        let v = &verification;
        Ok(Certificate {
            format: CERTIFICATE_FORMAT,
            class_iso9513: v.iso9513.class.clone().unwrap_or_else(|| "none".into()),
            bias_um: v.known.max_error_mm * 1e3,
            resolution_um: v.iso9513.resolution_mm * 1e3,
            u_k2_mm: v.uncertainty.expanded_mm,
            steps: v.steps.iter().map(spec_step).collect(),
            inputs: inputs(rec, source.path())?,
            date: now.format("%Y-%m-%d").to_string(),
            quantity: v.quantity.describe(),
            reference: source.path().display().to_string(),
            issued_utc: now.to_rfc3339_opts(chrono::SecondsFormat::Secs, true),
            version: env!("CARGO_PKG_VERSION"),
            operator,
            equipment,
            recording: rec.dir.display().to_string(),
            frame_sets: replayed.sets,
            rig: Rig {
                cameras: config.cameras.clone(),
                config: toml.is_file().then(|| hashed(&toml)).transpose()?,
                calibration_files,
                tags: config.specimen.tags.clone(),
                world_up: config.world.up,
                geometry_sha256: config.geometry_sha256(),
                camera_poses: config.camera_placements(&replayed.camera_poses),
            },
            plan: plan.clone(),
            verification,
        })
    }
}

/// SPEC's view of a step: on the reference's scale, the error in µm.
fn spec_step(s: &tagdeflect_verify::steps::StepResult) -> SpecStep {
    let first_mm = s.position_mm - s.nominal_mm;
    SpecStep {
        reference_mm: s.position_mm,
        measured_mm: s.measured_mm + first_mm,
        error_um: s.error_mm * 1e3,
        lines: s.lines,
        sd_um: s.sd_mm.map(|v| v * 1e3),
    }
}

/// The SHA-256 of each input: the reference (or step plan), every file at the top of the
/// recording (its index, UTM samples, config, ...) and the calibration files.
fn inputs(rec: &Recording, reference: &Path) -> anyhow::Result<BTreeMap<String, String>> {
    let mut files = vec![reference.to_path_buf()];
    let top = std::fs::read_dir(&rec.dir).map_err(|e| anyhow::anyhow!("listing {}: {e}", rec.dir.display()))?;
    for entry in top {
        let path = entry.map_err(|e| anyhow::anyhow!("listing {}: {e}", rec.dir.display()))?.path();
        if path.is_file() {
            files.push(path);
        }
    }
    files.extend(rec.config.calibration_files.iter().filter(|p| p.is_file()).cloned());
    files.into_iter().map(|p| hashed(&p).map(|h| (h.path, h.sha256))).collect()
}

fn hashed(path: &std::path::Path) -> anyhow::Result<HashedFile> {
    use anyhow::Context;
    let sha256 = tagdeflect_report::sha256_file(path).with_context(|| format!("hashing {}", path.display()))?;
    Ok(HashedFile { path: path.display().to_string(), sha256 })
}
