//! The certificate of a verification (`verification.json`): who, with what, on which rig,
//! and the figures.

use serde::Serialize;
use tagdeflect_core::camera_config::CameraConfig;
use tagdeflect_core::rig::SpecimenTag;
use tagdeflect_verify::{StepPlan, Verification};

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
}

/// Everything `verification.json` holds.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Certificate {
    /// [`CERTIFICATE_FORMAT`].
    pub format: &'static str,
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
    /// The step plan used.
    pub plan: StepPlan,
    /// The figures, the class, the uncertainty and the verdict.
    pub verification: Verification,
}

impl Certificate {
    /// The certificate of `verification` computed from `rec`.
    pub fn new(
        rec: &Recording,
        plan: &StepPlan,
        frame_sets: u64,
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
        Ok(Certificate {
            format: CERTIFICATE_FORMAT,
            issued_utc: chrono::Utc::now().to_rfc3339_opts(chrono::SecondsFormat::Secs, true),
            version: env!("CARGO_PKG_VERSION"),
            operator,
            equipment,
            recording: rec.dir.display().to_string(),
            frame_sets,
            rig: Rig {
                cameras: config.cameras.clone(),
                config: toml.is_file().then(|| hashed(&toml)).transpose()?,
                calibration_files,
                tags: config.specimen.tags.clone(),
                world_up: config.world.up,
            },
            plan: plan.clone(),
            verification,
        })
    }
}

fn hashed(path: &std::path::Path) -> anyhow::Result<HashedFile> {
    use anyhow::Context;
    let sha256 = tagdeflect_report::sha256_file(path).with_context(|| format!("hashing {}", path.display()))?;
    Ok(HashedFile { path: path.display().to_string(), sha256 })
}
