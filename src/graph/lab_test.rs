//! The tests of a run (`[output] tests`, `--tests DIR`; SPEC "Tests"): built here from the
//! config, their control API handed to the live page, their report made by the report crate.

use std::path::Path;
use std::sync::Arc;

use anyhow::Result;
use tagdeflect_core::verification::CameraPlacement;
use tagdeflect_sinks::lab_test::{LabTests, TestRecord};
use tagdeflect_sinks::{Finished, LineSink};

use crate::config::Config;
use crate::graph::page::Page;

/// Builds the tests under `dir`, serves their control API on the page and returns them. The
/// token is `[output] http_token_file`'s first line, else `dir/.token`'s: kept from an earlier
/// start when that file is still private (mode 0600, owned by the folder's owner, 48 hex digits), so a
/// restart (`Restart=on-failure`, an upgrade) does not lock out a client holding it; else made
/// now and written there (mode 0600). Printed on stderr at every start.
/// `placed` follows where the cameras are posed (a [`PlacementWatch`] among the run's sinks):
/// the verification in force is judged with them at each test's start and stop.
pub fn start(config: &Config, dir: &Path, page: &Page, placed: PlacementWatch) -> Result<Arc<LabTests>> {
    let bad = |m: String| tagdeflect_core::BadInput::new(m);
    let report_config = config.clone();
    let hook: tagdeflect_sinks::lab_test::ReportHook =
        Box::new(move |folder: &Path, record: &TestRecord| report(&report_config, folder, record).map_err(Into::into));
    let tests = LabTests::new(dir, config.to_toml_string(), config.calibration_files.clone(), Some(hook))
        .map_err(|e| bad(format!("[output] tests {}: {e}", dir.display())))?;
    record_frames(&tests, config);
    if let Some(b) = &config.specimen.beam {
        let dims = [("width_mm", Some(b.width_mm)), ("depth_mm", Some(b.depth_mm)), ("span_mm", Some(b.span_mm)), ("notch_mm", b.notch_mm)];
        tests.set_beam(dims.into_iter().filter_map(|(k, v)| v.map(|v| (k.to_string(), v))).collect());
    }
    if config.verification.is_some() {
        let cfg = config.clone();
        match cfg.verification_in_force() {
            Ok(Some(v)) if v.stale.is_empty() => tracing::info!("{}", v.describe()),
            Ok(Some(v)) => tracing::warn!("{}", v.describe()),
            Ok(None) => {}
            Err(e) => tracing::error!("[verification] {e}: tests name no verification"),
        }
        tests.set_verification(Box::new(move |bumps| verification_for(&cfg, bumps, &placed.now())));
    }
    if let Some(rules) = config.auto_rules().map_err(|p| bad(format!("{}: {}", p.key, p.message)))? {
        tracing::info!(
            start_load_kn = rules.config.start_load_kn,
            standard = rules.standard.as_deref().unwrap_or("none"),
            "tests start and stop automatically ([output.auto_test])"
        );
        tests.set_auto(rules);
    }
    let auth = match &config.output.users_file {
        Some(f) => {
            let users = tagdeflect_core::users::Users::read(f).map_err(|e| bad(format!("[output] users_file {e}")))?;
            warn_if_shared(f);
            tracing::info!(users = users.users.len(), "control API: each user's own token and role ({})", f.display());
            tagdeflect_core::users::Credentials::Users(users)
        }
        None => tagdeflect_core::users::Credentials::Shared(shared_token(config, dir)?),
    };
    if !page.set_control(tests.clone(), auth) {
        return Err(bad(format!(
            "[output] tests = {}: the tests are driven through the control API, which needs the live page: set [output] http (or --http ADDR)",
            dir.display()
        ))
        .into());
    }
    tracing::info!(
        "tests are kept in {}; control API: POST /api/test/start|stop|mark|zero|crack|sign|reanalyse, /api/specimens",
        dir.display()
    );
    Ok(tests)
}

/// Each test's frames into its folder (`frames/`, a recording) when its method's
/// `record_frames` says so, else when `[output] record_tests` does.
fn record_frames(tests: &LabTests, config: &Config) {
    use tagdeflect_io::recording::RecordingWriter;
    let cfg = config.clone();
    let format = config.output.record_format;
    tests.set_frames(tagdeflect_sinks::lab_test::frames::FramesSetup {
        open: Box::new(move |dir: &Path| RecordingWriter::create(dir, &cfg).map(|w| w.with_format(format))),
        names: config.cameras.iter().map(|c| c.name.clone()).collect(),
        queue: 8 * config.cameras.len().max(1),
        reserve_bytes: config.output.record_tests_reserve_bytes(),
        default: config.output.record_tests,
    });
    if config.output.record_tests {
        tracing::info!("each test's frames are recorded into its folder ([output] record_tests; a method's record_frames wins)");
    }
}

/// Warns when the users file is readable or writable by others than its owner (its hashes
/// let anyone who reads them try tokens offline; who can write it can make themselves admin).
pub fn warn_if_shared(path: &Path) {
    use std::os::unix::fs::MetadataExt;
    if let Ok(m) = std::fs::metadata(path) {
        if m.mode() & 0o077 != 0 {
            tracing::warn!(
                "users file {}: readable or writable by others than its owner (mode {:o}): chmod 600",
                path.display(),
                m.mode() & 0o777
            );
        }
    }
}

/// The one shared token: `[output] http_token_file`'s first line, else `dir/.token`'s (see [`start`]).
fn shared_token(config: &Config, dir: &Path) -> Result<String> {
    let bad = |m: String| tagdeflect_core::BadInput::new(m);
    if let Some(w) = config.output.token_file_warning() {
        tracing::warn!("{w}");
    }
    let token = match &config.output.http_token_file {
        Some(f) => std::fs::read_to_string(f)
            .map_err(|e| bad(format!("[output] http_token_file {}: {e}", f.display())))?
            .lines()
            .next()
            .unwrap_or_default()
            .trim()
            .to_string(),
        None => {
            let path = dir.join(".token");
            let token = match kept_token(&path) {
                Some(token) => {
                    tracing::info!("control token kept from {} (written by an earlier start)", path.display());
                    token
                }
                None => {
                    use rand::RngCore;
                    let mut bytes = [0u8; 24];
                    rand::rngs::OsRng.fill_bytes(&mut bytes);
                    let token: String = bytes.iter().map(|b| format!("{b:02x}")).collect();
                    write_private(&path, &token).map_err(|e| bad(format!("cannot write the control token to {}: {e}", path.display())))?;
                    tracing::info!("control token written to {} (mode 0600)", path.display());
                    token
                }
            };
            eprintln!("control token: {token}");
            token
        }
    };
    Ok(token)
}

/// The token an earlier start wrote to `path`, if the file is still fit to hold one: a regular
/// file of the tests folder's owner, readable by nobody else, holding 48 hex digits. Anything else (missing,
/// widened permissions, edited) makes a new token, with a warning when the file was there.
fn kept_token(path: &Path) -> Option<String> {
    use std::os::unix::fs::MetadataExt;
    let meta = std::fs::symlink_metadata(path).ok()?;
    // The tests folder is the daemon's own (made or checked writable at start): its owner is us.
    let me = std::fs::metadata(path.parent()?).ok()?.uid();
    let text = std::fs::read_to_string(path).unwrap_or_default();
    let token = text.lines().next().unwrap_or_default().trim();
    let why = if !meta.file_type().is_file() {
        "not a regular file"
    } else if meta.uid() != me {
        "owned by another user"
    } else if meta.mode() & 0o077 != 0 {
        "readable or writable by others"
    } else if token.len() != 48 || !token.bytes().all(|b| b.is_ascii_hexdigit()) {
        "not a token written by tagdeflect"
    } else {
        return Some(token.to_string());
    };
    tracing::warn!("control token file {}: {why}; a new token is made", path.display());
    if !meta.file_type().is_file() {
        // A directory or a link is not replaced behind the lab's back: writing fails and says so.
        return None;
    }
    let _ = std::fs::remove_file(path);
    None
}

fn write_private(path: &Path, text: &str) -> std::io::Result<()> {
    use std::io::Write;
    use std::os::unix::fs::OpenOptionsExt;
    let mut f = std::fs::OpenOptions::new().create(true).write(true).truncate(true).mode(0o600).open(path)?;
    f.write_all(text.as_bytes())?;
    f.write_all(b"\n")?;
    f.sync_all()
}

/// The report of a stopped test with a standard, into `folder/report/`: its inputs built
/// from the folder and the record by [`tagdeflect_report::test_folder::prepare`], the one
/// function `report DIR` and `report --series` use, so every route gives the same values.
fn report(config: &Config, folder: &Path, record: &TestRecord) -> Result<(), TestReportError> {
    use tagdeflect_report::test_folder::{build_test, checked, prepare, read_streams};
    let Some(standard) = record.meta.standard.as_deref() else { return Ok(()) };
    let out = folder.join("report");
    let std: tagdeflect_report::Standard = serde_json::from_value(serde_json::json!(standard))
        .map_err(|source| TestReportError::Standard { standard: standard.to_string(), source })?;
    let base = config.report.clone().unwrap_or_else(|| tagdeflect_report::ReportConfig::new(std, out.clone()));
    let (cfg_path, record_path) = (folder.join("tagdeflect.toml"), folder.join("test.json"));
    checked(record, &record_path)?;
    let prepared = prepare(record, &config.test_rig(), &base, None, &record_path, &cfg_path)?;
    prepared
        .opts
        .validate_with(prepared.rig.specimen.beam.as_ref())
        .map_err(|p| TestReportError::Section(format!("{}: {}", p.key, p.message)))?;
    let (mut feeds, utm) = read_streams(folder, &prepared, false)?;
    let feed = feeds.remove(0);
    let mut rep = build_test(&feed, utm.as_ref(), &prepared, record, &cfg_path)?;
    rep.inputs = vec![("config".into(), cfg_path)];
    std::fs::create_dir_all(&out)?;
    tagdeflect_report::write(&rep, &feed, &out)?;
    Ok(())
}

/// Why the report of a stopped test could not be made (logged by the tests' sink).
#[derive(Debug, thiserror::Error)]
enum TestReportError {
    /// The test's standard is not one the report knows.
    #[error("standard {standard}: {source}")]
    Standard {
        /// The standard as the test named it.
        standard: String,
        /// Why it is not known.
        source: serde_json::Error,
    },
    /// The report's options or geometry cannot make a report (no `[specimen.beam]` nor
    /// measured dimensions, no notch for EN 14651).
    #[error("[report]: {0}")]
    Section(String),
    /// The report's own error (the feed, the UTM samples, the build, the files).
    #[error("{0}")]
    Report(#[from] tagdeflect_report::ReportError),
    /// The report's folder could not be made.
    #[error("{0}")]
    Folder(#[from] std::io::Error),
}

/// Where the cameras are posed now, as the last finished frame set left them: a line sink
/// (clones share the placements).
#[derive(Clone, Default)]
pub struct PlacementWatch {
    names: Arc<Vec<String>>,
    placed: Arc<std::sync::Mutex<Vec<CameraPlacement>>>,
}

impl PlacementWatch {
    /// A watch of `config`'s cameras.
    pub fn new(config: &Config) -> Self {
        PlacementWatch { names: Arc::new(config.cameras.iter().map(|c| c.name.clone()).collect()), ..Default::default() }
    }

    /// The placements of the last frame set (cameras never posed left out).
    pub fn now(&self) -> Vec<CameraPlacement> {
        self.placed.lock().map(|p| p.clone()).unwrap_or_default()
    }
}

impl LineSink for PlacementWatch {
    fn name(&self) -> String {
        "camera placements".into()
    }
    fn accept(&mut self, finished: &Finished) {
        let placed = self
            .names
            .iter()
            .zip(&finished.observed.camera_poses)
            .filter_map(|(n, p)| p.as_ref().map(|p| CameraPlacement::from_pose(n, p)))
            .collect();
        if let Ok(mut g) = self.placed.lock() {
            *g = placed;
        }
    }
}

/// The verification in force for a test (`[verification]`) with the bumps the daemon saw and
/// the cameras where they are posed now; `None` (logged) when its certificate or a
/// calibration file cannot be read.
fn verification_for(
    config: &Config,
    bumps: &[(String, i64)],
    placed: &[CameraPlacement],
) -> Option<tagdeflect_core::verification::InForce> {
    let v = config.verification.as_ref()?;
    let mut now = match config.rig_now() {
        Ok(now) => now,
        Err(e) => {
            tracing::error!("[verification]: {e}");
            return None;
        }
    };
    now.bumps = bumps.to_vec();
    now.camera_poses = placed.to_vec();
    match tagdeflect_core::verification::assess(&v.certificate, v.valid_days, &now, tagdeflect_core::clock::now_epoch_ns()) {
        Ok(f) => Some(f),
        Err(e) => {
            tracing::error!("[verification] {e}");
            None
        }
    }
}
