//! The verification in force (`[verification]`): which certificate of `tagdeflect verify`
//! (its `verification.json`) a test is measured under, and whether it still holds.
//!
//! A certificate holds for the rig it was made on. It is **stale** — said on the live page,
//! by `check`, in `test.json` and in the report, never silently — when, since it was issued:
//! - a calibration file it names changed (its SHA-256 differs) or is gone, or the rig has a
//!   calibration file the certificate does not name;
//! - the rig's geometry changed: the world's up, the background tags (family, size, world
//!   corners), the specimen tags (family, size, ids, roles), the cameras (name, image size,
//!   intrinsics, fixed pose) — compared through [`geometry_sha256`], which the certificate
//!   records (a certificate without it, from before this rule, is stale with that reason);
//! - a camera was bumped (re-posed after its background tags jumped) after the certificate was
//!   issued — as seen by the running daemon;
//! - a camera is no longer where it was when verified: its pose from the background tags now
//!   (the daemon's held pose at a test's start and stop, `check`'s pose) differs from the pose
//!   the certificate records by more than [`MOVED_CENTRE_MM`] or [`MOVED_ANGLE_DEG`] — this
//!   catches a camera moved while no daemon ran (certificates made before poses were recorded
//!   are not compared);
//! - its validity period (`valid_days`, default [`DEFAULT_VALID_DAYS`]) is over.
//!
//! The certificate's own identity is the SHA-256 of its `verification.json`: a certificate
//! edited after it was issued is a different one.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::camera::Pose;
use crate::camera_config::CameraConfig;
use crate::rig::{BackgroundConfig, SpecimenConfig};
use crate::Problem;

/// The validity period when `valid_days` is not given: one year, the usual interval of an
/// extensometer's verification (ISO 9513 leaves it to the lab; 12 months is common practice).
pub const DEFAULT_VALID_DAYS: u32 = 365;

/// `[verification]` (extension of SPEC): the certificate in force and how long it holds.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VerificationConfig {
    /// The certificate's `verification.json` (relative to the config's folder).
    pub certificate: PathBuf,
    /// Days the certificate holds after its date.
    #[serde(default = "default_valid_days")]
    pub valid_days: u32,
}

fn default_valid_days() -> u32 {
    DEFAULT_VALID_DAYS
}

impl VerificationConfig {
    /// A validity period of 1 to 3650 days; a certificate path given.
    pub fn validate(&self) -> Result<(), Problem> {
        if self.certificate.as_os_str().is_empty() {
            return Err(Problem::new("certificate", "certificate: the path of a verification.json made by `tagdeflect verify`"));
        }
        if !(1..=3650).contains(&self.valid_days) {
            return Err(Problem::new("valid_days", format!("valid_days = {}: 1 to 3650 days", self.valid_days)));
        }
        Ok(())
    }
}

/// What the in-force check reads of a certificate (`verification.json`, written by
/// `tagdeflect verify`); the rest of the file is ignored here.
#[derive(Debug, Clone, PartialEq, Deserialize)]
pub struct CertificateHead {
    /// ISO 9513 class reached (`"0.5"`, ..., `"none"`).
    pub class_iso9513: String,
    /// The date it was made, `YYYY-MM-DD`.
    pub date: String,
    /// When it was issued, RFC 3339 (absent in hand-made files: the date's midnight UTC).
    #[serde(default)]
    pub issued_utc: Option<String>,
    /// The expanded uncertainty (k = 2) of the verified quantity, mm.
    pub u_k2_mm: f64,
    /// The verified quantity, as described by the certificate.
    #[serde(default)]
    pub quantity: Option<String>,
    /// The rig it was made on.
    pub rig: CertificateRig,
}

/// The rig part of a certificate.
#[derive(Debug, Clone, PartialEq, Deserialize)]
pub struct CertificateRig {
    /// The calibration files and their SHA-256.
    #[serde(default)]
    pub calibration_files: Vec<HashedPath>,
    /// [`geometry_sha256`] of the rig when verified (absent in certificates made before it).
    #[serde(default)]
    pub geometry_sha256: Option<String>,
    /// Where each posed camera was during the verification (absent in certificates made before
    /// poses were recorded: nothing compared).
    #[serde(default)]
    pub camera_poses: Vec<CameraPlacement>,
}

/// A camera's centre moved more than this (mm) from where it was verified: the verification is
/// stale. Poses from the background tags repeat to a few hundredths of a millimetre on the
/// simulated rigs; a millimetre is far beyond that and well under what a knock does.
pub const MOVED_CENTRE_MM: f64 = 1.0;

/// A camera turned more than this (degrees) from its verified orientation: the verification is
/// stale (0.05° is ≈ 1.2 px at f = 1400 px, the size of the daemon's own bump floor, 1 px).
pub const MOVED_ANGLE_DEG: f64 = 0.05;

/// Where a camera was, as a certificate records it and a later run compares (world → camera).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CameraPlacement {
    /// The camera's name in the config.
    pub camera: String,
    /// Rotation world → camera as a rotation vector (axis × angle), rad.
    pub rvec: [f64; 3],
    /// The camera's centre in the world, mm.
    pub centre_mm: [f64; 3],
}

impl CameraPlacement {
    /// The placement of camera `camera` posed at `pose`.
    pub fn from_pose(camera: &str, pose: &Pose) -> Self {
        let c = pose.centre();
        CameraPlacement { camera: camera.to_string(), rvec: pose.rvec(), centre_mm: [c.x, c.y, c.z] }
    }

    /// How far `other` is from this: the centres' distance (mm) and the rotation between (degrees).
    pub fn moved_from(&self, other: &CameraPlacement) -> (f64, f64) {
        let d = (0..3).map(|k| (self.centre_mm[k] - other.centre_mm[k]).powi(2)).sum::<f64>().sqrt();
        let pose = |p: &CameraPlacement| Pose::from_rvec_tvec(p.rvec, [0.0; 3]);
        (d, pose(self).angle_to(&pose(other)).to_degrees())
    }
}

/// Cameras placed now farther from where the certificate recorded them than the limits.
fn moved_cameras(then: &[CameraPlacement], now: &[CameraPlacement]) -> Vec<String> {
    let mut out = Vec::new();
    for t in then {
        let Some(n) = now.iter().find(|n| n.camera == t.camera) else { continue };
        let (mm, deg) = n.moved_from(t);
        if mm > MOVED_CENTRE_MM || deg > MOVED_ANGLE_DEG {
            out.push(format!(
                "camera {} is {mm:.2} mm and {deg:.3}° from where it was when verified (limits {MOVED_CENTRE_MM} mm, {MOVED_ANGLE_DEG}°)",
                t.camera
            ));
        }
    }
    out
}

/// A file named with its SHA-256.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct HashedPath {
    /// The path as found.
    pub path: String,
    /// SHA-256, lower-case hex.
    pub sha256: String,
}

/// What the rig is now, to compare with a certificate.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct RigNow {
    /// The calibration files in use and their SHA-256 (compared by file name).
    pub calibration_files: Vec<HashedPath>,
    /// [`geometry_sha256`] of the config in force.
    pub geometry_sha256: String,
    /// Cameras bumped since the daemon started: (camera, when, ns since the Unix epoch).
    pub bumps: Vec<(String, i64)>,
    /// Where the cameras posed now are (empty: not known, nothing compared).
    pub camera_poses: Vec<CameraPlacement>,
}

/// The verification in force, as `test.json`, `check`, the page and the report give it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct InForce {
    /// The certificate's identity: the SHA-256 of its `verification.json`.
    pub id: String,
    /// Where it was read.
    pub file: String,
    /// ISO 9513 class.
    pub class_iso9513: String,
    /// Its date, `YYYY-MM-DD`.
    pub date: String,
    /// The last day it holds, `YYYY-MM-DD`.
    pub valid_until: String,
    /// Expanded uncertainty (k = 2), mm.
    pub u_k2_mm: f64,
    /// Why it no longer holds (empty: it holds).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub stale: Vec<String>,
}

impl InForce {
    /// One line for a log, `check` or the page: class, date, id and staleness.
    pub fn describe(&self) -> String {
        let head = format!(
            "verification {} of {} (class {}, U(k=2) {:.1} µm, valid until {})",
            &self.id[..self.id.len().min(12)],
            self.date,
            self.class_iso9513,
            self.u_k2_mm * 1e3,
            self.valid_until
        );
        if self.stale.is_empty() {
            format!("{head}: in force")
        } else {
            format!("{head}: STALE — {}", self.stale.join("; "))
        }
    }
}

/// Why a certificate could not be read.
#[derive(Debug, thiserror::Error)]
#[error("{path}: {message}")]
pub struct CertificateError {
    /// The file.
    pub path: PathBuf,
    /// What is wrong.
    pub message: String,
}

/// Reads the certificate at `path` and says whether it holds for `now` at `now_ns`.
pub fn assess(path: &Path, valid_days: u32, now: &RigNow, now_ns: i64) -> Result<InForce, CertificateError> {
    let fail = |message: String| CertificateError { path: path.to_path_buf(), message };
    let bytes = std::fs::read(path).map_err(|e| fail(format!("cannot read the verification certificate: {e}")))?;
    let head: CertificateHead =
        serde_json::from_slice(&bytes).map_err(|e| fail(format!("not a verification.json of `tagdeflect verify`: {e}")))?;
    let issued_ns = issued_ns(&head).ok_or_else(|| fail(format!("date \"{}\": expected YYYY-MM-DD", head.date)))?;
    let until_ns = issued_ns.saturating_add(i64::from(valid_days) * DAY_NS);
    let mut stale = calibration_changes(&head.rig.calibration_files, &now.calibration_files);
    match &head.rig.geometry_sha256 {
        None => stale.push("the certificate does not record the rig's geometry (made before that was recorded)".into()),
        Some(g) if *g != now.geometry_sha256 => stale.push("the rig's geometry changed (tags, cameras or intrinsics in the config)".into()),
        Some(_) => {}
    }
    stale.extend(moved_cameras(&head.rig.camera_poses, &now.camera_poses));
    for (camera, t_ns) in now.bumps.iter().filter(|(_, t)| *t > issued_ns) {
        stale.push(format!("camera {camera} was bumped at {} after the verification", utc_date_time(*t_ns)));
    }
    if now_ns > until_ns {
        stale.push(format!("its validity of {valid_days} days ended on {}", utc_date(until_ns - DAY_NS)));
    }
    Ok(InForce {
        id: hex(&Sha256::digest(&bytes)),
        file: path.display().to_string(),
        class_iso9513: head.class_iso9513,
        date: head.date,
        valid_until: utc_date(until_ns - DAY_NS),
        u_k2_mm: head.u_k2_mm,
        stale,
    })
}

const DAY_NS: i64 = 86_400_000_000_000;

/// The certificate's issue time: `issued_utc`, else its date's midnight (UTC).
fn issued_ns(head: &CertificateHead) -> Option<i64> {
    if let Some(t) = head.issued_utc.as_deref().and_then(parse_rfc3339_ns) {
        return Some(t);
    }
    days_from_date(&head.date).map(|d| d * DAY_NS)
}

/// Calibration files changed, gone or new, by file name.
fn calibration_changes(then: &[HashedPath], now: &[HashedPath]) -> Vec<String> {
    let name = |p: &str| Path::new(p).file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| p.to_string());
    let mut out = Vec::new();
    for t in then {
        match now.iter().find(|n| name(&n.path) == name(&t.path)) {
            None => out.push(format!("calibration file {} is no longer in use", name(&t.path))),
            Some(n) if n.sha256 != t.sha256 => out.push(format!("calibration file {} changed since the verification", name(&t.path))),
            Some(_) => {}
        }
    }
    for n in now.iter().filter(|n| !then.iter().any(|t| name(&t.path) == name(&n.path))) {
        out.push(format!("calibration file {} was not in use when verified", name(&n.path)));
    }
    out
}

/// SHA-256 of the rig's geometry as the config gives it: the world's up, the background tags,
/// the specimen tags (not the beam's dimensions, which change with each specimen) and each
/// camera's name, image size, intrinsics and fixed pose (not its source).
pub fn geometry_sha256(up: [f64; 3], background: &BackgroundConfig, specimen: &SpecimenConfig, cameras: &[CameraConfig]) -> String {
    let specimen = SpecimenConfig { beam: None, ..specimen.clone() };
    let cameras: Vec<serde_json::Value> = cameras
        .iter()
        .map(|c| {
            serde_json::json!({
                "name": c.name, "width": c.width, "height": c.height, "fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy,
                "dist": c.dist, "rvec": c.rvec, "tvec_mm": c.tvec_mm,
            })
        })
        .collect();
    let doc = serde_json::json!({ "up": up, "background": background, "specimen": specimen, "cameras": cameras });
    hex(&Sha256::digest(doc.to_string().as_bytes()))
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// Days since 1970-01-01 of `YYYY-MM-DD`.
fn days_from_date(s: &str) -> Option<i64> {
    let d = chrono::NaiveDate::parse_from_str(s, "%Y-%m-%d").ok()?;
    Some(d.signed_duration_since(chrono::NaiveDate::default()).num_days())
}

/// An RFC 3339 time as ns since the epoch.
fn parse_rfc3339_ns(s: &str) -> Option<i64> {
    chrono::DateTime::parse_from_rfc3339(s).ok()?.timestamp_nanos_opt()
}

/// `YYYY-MM-DD` of ns since the epoch (UTC).
fn utc_date(t_ns: i64) -> String {
    chrono::DateTime::from_timestamp_nanos(t_ns).format("%Y-%m-%d").to_string()
}

/// `YYYY-MM-DD HH:MM:SS UTC` of ns since the epoch.
fn utc_date_time(t_ns: i64) -> String {
    chrono::DateTime::from_timestamp_nanos(t_ns).format("%Y-%m-%d %H:%M:%S UTC").to_string()
}

#[cfg(test)]
mod tests;
