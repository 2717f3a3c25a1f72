//! The tests of a daemon ([`LabTests`]): the running test, what waits for the next line, the
//! hooks the binary installs, and the lock they share.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Condvar, Mutex};

use sha2::Digest;
use tagdeflect_core::feed::FeedEvent;
use tagdeflect_core::feed_file::FeedWriter;
use tagdeflect_core::utm_sample::UtmSample;

use super::folder::hex;
use super::zero::Zero;
use super::{auto, EarlierTest, TestRecord};

/// Why the report of a stopped test could not be made (the hook's own error).
pub type ReportError = Box<dyn std::error::Error + Send + Sync>;

/// Made by the binary: writes `folder/report/` for a stopped test with a standard.
pub type ReportHook = Box<dyn Fn(&Path, &TestRecord) -> Result<(), ReportError> + Send + Sync>;

/// Made by the binary: writes its own files into a stopped test's folder before the report
/// and the hashes (the control outputs' `control.json`). An error is logged, never fatal.
pub type FolderHook = Box<dyn Fn(&Path, &TestRecord) -> Result<(), ReportError> + Send + Sync>;

/// Made by the binary: hands a test's record on (the MQTT publisher's `<topic>/labtest/<id>`)
/// at its start, every event and its stop. Must not block.
pub type RecordHook = Box<dyn Fn(&TestRecord) + Send + Sync>;

/// The running test.
pub(super) struct Running {
    pub(super) record: TestRecord,
    pub(super) folder: PathBuf,
    /// `feed.jsonl` and `utm.jsonl`: whole lines only, held back and retried while the disk
    /// is full (the main feed's writer, [`tagdeflect_core::feed_file`]).
    pub(super) feed: FeedWriter,
    pub(super) utm: FeedWriter,
    pub(super) zero: Zero,
    /// The newest line written to the folder.
    pub(super) written_t_ns: i64,
    /// (net deflection, load) of the test's lines, thinned (the page's earlier tests).
    pub(super) curve: Vec<(f64, f64)>,
    /// The test's first and last lines: a resume's gap, the stop's own line.
    pub(super) ends: Ends,
    /// The preload its method asks for, kN, until the load reaches it: no zero is taken
    /// below it ([`super::preload`]).
    pub(super) preload_kn: Option<f64>,
}

/// What the running test's first line after a resume and its last line carry.
#[derive(Debug, Default)]
pub(super) struct Ends {
    /// The stop pressed: the next line is the test's last and carries it.
    pub(super) stop: Option<FeedEvent>,
    /// The time of the line that carries the stop (later lines are no test's).
    pub(super) stop_line_t_ns: Option<i64>,
    /// The sinks wrote that line into the folder.
    pub(super) stop_written: bool,
    /// Resumed: the time of the last line written before the daemon stopped (the resume
    /// event's gap runs from it to the first line after).
    pub(super) resumed_after_t_ns: Option<i64>,
}

#[derive(Default)]
pub(super) struct Inner {
    pub(super) running: Option<Running>,
    /// Events for the next line.
    pub(super) pending: Vec<FeedEvent>,
    /// The newest line's time (`stop` waits for the sinks to pass it).
    pub(super) last_line_t_ns: i64,
    /// The last test's id and folder (`GET /api/test` after a stop).
    pub(super) last: Option<(String, PathBuf)>,
    /// Automatic start and stop (`[output.auto_test]`).
    pub(super) auto: Option<auto::AutoTest>,
    /// The tests stopped today, oldest first (at most [`EARLIER_TESTS`](super::EARLIER_TESTS)).
    pub(super) earlier: Vec<EarlierTest>,
    /// The config's `[specimen.beam]` dimensions, mm (`width_mm`, ...).
    pub(super) beam_mm: BTreeMap<String, f64>,
    /// The newest UTM load and its time (kN, ns): a start under load is refused by its method.
    pub(super) last_load: Option<(f64, i64)>,
    /// Why the last test's report could not be made, if it could not.
    pub(super) last_report_error: Option<String>,
    /// A stopped test whose folder is not complete yet.
    pub(super) unfinished: Option<super::stopping::Unfinished>,
    /// Cameras bumped while this daemon ran (camera, when): a verification made before is stale.
    pub(super) bumps: Vec<(String, i64)>,
    /// The UTM samples of the last [`RECENT_UTM_NS`](super::preload::RECENT_UTM_NS) while no
    /// test runs: an automatic start keeps those from its line on ([`super::preload`]).
    pub(super) recent_utm: std::collections::VecDeque<UtmSample>,
}

/// The tests of a daemon; see the module doc.
pub struct LabTests {
    pub(super) dir: PathBuf,
    pub(super) config_text: String,
    /// SHA-256 of each calibration file, by its path, taken when the daemon read its config.
    pub(super) calibration_sha256: BTreeMap<String, String>,
    pub(super) report: Option<ReportHook>,
    pub(super) on_record: std::sync::OnceLock<RecordHook>,
    /// Records made before the hook was set (a stop completed at start, a resumed test), the
    /// newest of each test: handed on when it is set.
    pub(super) unsent: Mutex<Vec<TestRecord>>,
    pub(super) inner: Mutex<Inner>,
    pub(super) written: Condvar,
    /// `<dir>/audit.jsonl`, its tail kept (see [`super::audit`]).
    pub(super) audit: Mutex<tagdeflect_core::audit::AuditLog>,
    /// The check of the verification in force (`[verification]`), if one is configured.
    pub(super) verification: std::sync::OnceLock<super::verification::VerificationCheck>,
    /// The binary's own files of a stopped test ([`FolderHook`]).
    pub(super) folder_files: std::sync::OnceLock<FolderHook>,
    /// The verification `GET /api/test` names while no test runs.
    pub(super) idle_verification: super::verification::IdleVerification,
    /// Each test's own frames (`[output] record_tests`, [`super::frames`]).
    pub(super) frames: super::frames::TestFrames,
}

impl LabTests {
    /// Tests kept under `dir` (created); `config_text` is the config in force, written into
    /// every test's folder; `calibration_files` (the files the intrinsics in force were read
    /// from) are hashed now — when the daemon has just read them, not when a test stops an hour
    /// later and someone may have recalibrated — and the hashes go into every `test.json`. A
    /// calibration file that cannot be read is an error: a test must not claim an unhashed
    /// calibration.
    ///
    /// A test that was running when the daemon stopped (`TESTS/.running.json`) is resumed; one
    /// that was being stopped has its folder completed.
    pub fn new(dir: &Path, config_text: String, calibration_files: Vec<PathBuf>, report: Option<ReportHook>) -> std::io::Result<Arc<Self>> {
        let mut calibration_sha256 = BTreeMap::new();
        for c in &calibration_files {
            let bytes = std::fs::read(c).map_err(|e| std::io::Error::new(e.kind(), format!("calibration file {}: {e}", c.display())))?;
            calibration_sha256.insert(c.display().to_string(), hex(&sha2::Sha256::digest(&bytes)));
        }
        std::fs::create_dir_all(dir)?;
        let audit = tagdeflect_core::audit::AuditLog::open(&dir.join(super::audit::AUDIT_FILE)).map_err(std::io::Error::other)?;
        let tests = LabTests {
            dir: dir.to_path_buf(),
            config_text,
            calibration_sha256,
            report,
            on_record: std::sync::OnceLock::new(),
            unsent: Mutex::default(),
            inner: Mutex::default(),
            written: Condvar::new(),
            audit: Mutex::new(audit),
            verification: std::sync::OnceLock::new(),
            folder_files: std::sync::OnceLock::new(),
            idle_verification: Default::default(),
            frames: Default::default(),
        };
        tests.read_earlier();
        let stopping = tests.resume()?;
        let tests = Arc::new(tests);
        if let Some(r) = stopping {
            tests.complete_at_start(r);
        }
        Ok(tests)
    }

    /// Installs the hook that writes the binary's own files into each stopped test's folder
    /// (the first one set stays).
    pub fn set_folder_files(&self, hook: FolderHook) {
        let _ = self.folder_files.set(hook);
    }

    /// The folder tests are kept in.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    pub(super) fn lock(&self) -> std::sync::MutexGuard<'_, Inner> {
        self.inner.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Hands every record on from now on: first those made before (a stop the last daemon
    /// left unfinished and this one completed, a resumed test's), then the running test's;
    /// set once.
    pub fn set_on_record(&self, hook: RecordHook) {
        let g = self.lock();
        let mut unsent = self.unsent.lock().unwrap_or_else(|p| p.into_inner());
        for r in unsent.drain(..) {
            hook(&r);
        }
        if let Some(r) = &g.running {
            hook(&r.record);
        }
        let _ = self.on_record.set(hook);
    }

    /// Hands `record` on, or keeps it (the newest of each test, at most
    /// [`EARLIER_TESTS`](super::EARLIER_TESTS) tests) until the hook is set.
    pub(super) fn publish(&self, record: &TestRecord) {
        // Under the lock `set_on_record` takes: a record is handed on or kept, never lost
        // between the two.
        let mut unsent = self.unsent.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(h) = self.on_record.get() {
            h(record);
            return;
        }
        unsent.retain(|r| r.id != record.id);
        unsent.push(record.clone());
        if unsent.len() > super::EARLIER_TESTS {
            unsent.remove(0);
        }
    }

    /// Starts and stops tests by `rules` from now on (see [`auto`]).
    pub fn set_auto(&self, rules: auto::AutoRules) {
        self.lock().auto = Some(auto::AutoTest::new(rules));
    }
}
