//! A test as a lab runs it (SPEC "Tests"): one specimen from start to stop, while the daemon
//! keeps measuring between tests.
//!
//! ```text
//! control API / `tagdeflect test` ──start/stop/mark/zero──▶ LabTests (one lock, short holds)
//! solver thread ──LabTests::apply(&mut line)──▶ the line gets `test`, `events`, values from the zero
//! sinks' thread ──LabTests::on_line──▶ tests/<id>/feed.jsonl
//! UTM forwarder ──LabTests::on_utm──▶ tests/<id>/utm.jsonl (every sample, at its own rate)
//! ```
//!
//! States: idle → running → idle. `start` opens `tests/<id>/` (id: the UTC start time and the
//! specimen, `20261202T013000Z-B12`); the test's zero is the mean of its first
//! [`ZERO_SETS`] frame sets — per specimen tag (its position), the net deflection and each
//! gauge — and every later value counts from it (lines taken while the zero forms are marked
//! `zeroing` and count from the mean so far; the zero's σ, the spread of those sets over √n,
//! goes into every σ). `zero` takes it again from the next sets. `mark` puts an operator's
//! note into the feed and `test.json`. `stop` waits (at most [`STOP_WAIT`]) until the sinks
//! have written every line up to the stop, then completes the folder: `tagdeflect.toml` (the
//! config in force), `test.json` (metadata, events, the SHA-256 of every file of the folder
//! and of the calibration files) and, through the hook the binary installs, `report/`.
//!
//! A running test survives a restart of the daemon (a crash, `Restart=on-failure`): its state —
//! the record, the folder, the zero with its σ — is kept in `TESTS/.running.json` (written at
//! start, when the zero forms and at every event, atomically); a daemon that finds it at start
//! resumes the test from the same zero and puts a `resume` event (with the gap) into the feed
//! and `test.json`, so the curve never gets a second zero in its middle. The new daemon numbers
//! its frame sets from 0 again (a feed line's `seq` is the daemon's frame-set count, not the
//! test's), so the test's `feed.jsonl` has `seq` going back at the line with the `resume`
//! event: that line starts a new segment of the same test, which the report's feed reader
//! (`tagdeflect_report`, issue 24 item 3) reads as one test across it, the hole a gap in time;
//! a `seq` going back on a line without the event stays an error there.
//!
//! Tests may also start and stop by themselves, from the load and the standard's end
//! (`[output.auto_test]`, [`auto`]); an automatic stop runs on a short thread of its own, as
//! `stop` waits for the sinks.
//!
//! Nothing here blocks the solver for longer than a few field updates under the lock: files are
//! written on the sinks' thread and by the caller of `stop`.

use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Condvar, Mutex};
use std::time::Duration;

use serde::{Deserialize, Serialize};
use sha2::Digest;

use tagdeflect_core::feed::{FeedEvent, FeedLine, TestRef};
use tagdeflect_core::utm_sample::UtmSample;

pub mod auto;

pub use tagdeflect_core::lab_test::{TestMeta, TestRecord, STANDARDS};

/// Frame sets whose mean is a test's zero.
pub const ZERO_SETS: usize = 5;
/// How long `stop` waits for the sinks to write the test's last lines.
pub const STOP_WAIT: Duration = Duration::from_millis(1500);

/// Why a command was refused.
#[derive(Debug, thiserror::Error)]
pub enum TestError {
    /// The command does not fit the state (start while running, stop while idle): HTTP 409.
    #[error("{0}")]
    Conflict(String),
    /// The request is malformed: HTTP 400.
    #[error("{0}")]
    Bad(String),
    /// The folder could not be written: HTTP 500.
    #[error("{0}")]
    Io(String),
}

impl From<tagdeflect_core::lab_test::BadTestMeta> for TestError {
    fn from(e: tagdeflect_core::lab_test::BadTestMeta) -> Self {
        TestError::Bad(e.0)
    }
}

/// A stopped test's curve for the page (`GET /api/tests`): load over net deflection from its
/// zero, at most [`EARLIER_POINTS`] points.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct EarlierTest {
    /// The test's id.
    pub id: String,
    /// Its specimen.
    pub specimen: String,
    /// When it started, ns since the Unix epoch.
    pub started_t_ns: i64,
    /// Net deflection, mm.
    pub net_deflection_mm: Vec<f64>,
    /// Load, kN, at the same lines.
    pub load_kn: Vec<f64>,
}

/// Points of an earlier test's curve on the page.
pub const EARLIER_POINTS: usize = 500;
/// Earlier tests on the page at most (the day's newest).
pub const EARLIER_TESTS: usize = 12;

impl EarlierTest {
    fn new(record: &TestRecord, curve: &[(f64, f64)]) -> EarlierTest {
        let step = curve.len().div_ceil(EARLIER_POINTS).max(1);
        let kept: Vec<(f64, f64)> = curve.iter().step_by(step).copied().chain(curve.last().copied().filter(|_| step > 1)).collect();
        EarlierTest {
            id: record.id.clone(),
            specimen: record.meta.specimen.clone(),
            started_t_ns: record.started_t_ns,
            net_deflection_mm: kept.iter().map(|p| p.0).collect(),
            load_kn: kept.iter().map(|p| p.1).collect(),
        }
    }
}

/// The (net deflection, load) points of a test's `feed.jsonl`; lines that do not parse are
/// skipped (the file is this daemon's own; a line cut by a crash is the usual one).
fn read_curve(feed: &Path) -> std::io::Result<Vec<(f64, f64)>> {
    #[derive(Deserialize)]
    struct Point {
        #[serde(rename = "load_kN")]
        load_kn: Option<f64>,
        net_deflection_mm: Option<f64>,
    }
    use std::io::BufRead;
    let mut out = Vec::new();
    for line in std::io::BufReader::new(std::fs::File::open(feed)?).lines() {
        if let Ok(Point { load_kn: Some(l), net_deflection_mm: Some(n) }) = serde_json::from_str::<Point>(&line?) {
            push_point(&mut out, n, l);
        }
    }
    Ok(out)
}

/// Adds a point to a running curve, halving it when it grows past 4 × [`EARLIER_POINTS`].
fn push_point(curve: &mut Vec<(f64, f64)>, net: f64, load: f64) {
    if net.is_finite() && load.is_finite() {
        curve.push((net, load));
    }
    if curve.len() > 4 * EARLIER_POINTS {
        let mut k = 0;
        curve.retain(|_| {
            k += 1;
            k % 2 == 1
        });
    }
}

/// The local calendar day of a time, ns since the Unix epoch.
fn day_of(t_ns: i64) -> chrono::NaiveDate {
    chrono::DateTime::from_timestamp_nanos(t_ns).with_timezone(&chrono::Local).date_naive()
}

/// What `stop` answers.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Stopped {
    /// The test's id.
    pub id: String,
    /// Its folder.
    pub folder: PathBuf,
}

/// Made by the binary: writes `folder/report/` for a stopped test with a standard.
pub type ReportHook = Box<dyn Fn(&Path, &TestRecord) -> Result<(), String> + Send + Sync>;

/// Made by the binary: hands a test's record on (the MQTT publisher's `<topic>/labtest/<id>`)
/// at its start, every event and its stop. Must not block.
pub type RecordHook = Box<dyn Fn(&TestRecord) + Send + Sync>;

/// The running test.
struct Running {
    record: TestRecord,
    folder: PathBuf,
    feed: std::fs::File,
    utm: std::fs::File,
    zero: Zero,
    /// The newest line written to the folder.
    written_t_ns: i64,
    /// (net deflection, load) of the test's lines, thinned (the page's earlier tests).
    curve: Vec<(f64, f64)>,
}

#[derive(Default)]
struct Inner {
    running: Option<Running>,
    /// Events for the next line.
    pending: Vec<FeedEvent>,
    /// The newest line's time (`stop` waits for the sinks to pass it).
    last_line_t_ns: i64,
    /// The last test's id and folder (`GET /api/test` after a stop).
    last: Option<(String, PathBuf)>,
    /// Automatic start and stop (`[output.auto_test]`).
    auto: Option<auto::AutoTest>,
    /// The tests stopped today, oldest first (at most [`EARLIER_TESTS`]).
    earlier: Vec<EarlierTest>,
}

/// The tests of a daemon; see the module doc.
pub struct LabTests {
    dir: PathBuf,
    config_text: String,
    /// SHA-256 of each calibration file, by its path, taken when the daemon read its config.
    calibration_sha256: BTreeMap<String, String>,
    report: Option<ReportHook>,
    on_record: std::sync::OnceLock<RecordHook>,
    inner: Mutex<Inner>,
    written: Condvar,
}

impl LabTests {
    /// Tests kept under `dir` (created); `config_text` is the config in force, written into
    /// every test's folder; `calibration_files` (the files the intrinsics in force were read
    /// from) are hashed now — when the daemon has just read them, not when a test stops an hour
    /// later and someone may have recalibrated — and the hashes go into every `test.json`. A
    /// calibration file that cannot be read is an error: a test must not claim an unhashed
    /// calibration.
    ///
    /// A test that was running when the daemon stopped (`TESTS/.running.json`) is resumed.
    pub fn new(dir: &Path, config_text: String, calibration_files: Vec<PathBuf>, report: Option<ReportHook>) -> std::io::Result<Arc<Self>> {
        let mut calibration_sha256 = BTreeMap::new();
        for c in &calibration_files {
            let bytes = std::fs::read(c).map_err(|e| std::io::Error::new(e.kind(), format!("calibration file {}: {e}", c.display())))?;
            calibration_sha256.insert(c.display().to_string(), hex(&sha2::Sha256::digest(&bytes)));
        }
        std::fs::create_dir_all(dir)?;
        let tests = LabTests {
            dir: dir.to_path_buf(),
            config_text,
            calibration_sha256,
            report,
            on_record: std::sync::OnceLock::new(),
            inner: Mutex::default(),
            written: Condvar::new(),
        };
        tests.read_earlier();
        tests.resume()?;
        Ok(Arc::new(tests))
    }

    fn state_file(&self) -> PathBuf {
        self.dir.join(".running.json")
    }

    /// Keeps the running test's state on disk (see the module doc); a failure is logged.
    fn persist(&self, r: &Running) {
        let p = Persisted {
            record: r.record.clone(),
            folder: r.folder.clone(),
            zero_n: r.zero.n,
            tags: r.zero.tags.iter().map(|(k, m)| (*k, m.to_parts())).collect(),
            net: r.zero.net.to_parts(),
            gauges: r.zero.gauges.iter().map(|(k, m)| (k.clone(), m.to_parts())).collect(),
            last_line_t_ns: r.written_t_ns,
        };
        let path = self.state_file();
        let tmp = path.with_extension("json.tmp");
        let result = serde_json::to_vec(&p)
            .map_err(std::io::Error::other)
            .and_then(|bytes| {
                let mut f = std::fs::File::create(&tmp)?;
                f.write_all(&bytes)?;
                f.sync_all()
            })
            .and_then(|()| std::fs::rename(&tmp, &path));
        if let Err(e) = result {
            tracing::error!(test = %r.record.id, "cannot keep the running test's state in {}: {e}", path.display());
        }
    }

    /// The curves of today's stopped tests in the folder (once, at start).
    fn read_earlier(&self) {
        let today = day_of(tagdeflect_core::clock::now_epoch_ns());
        let Ok(entries) = std::fs::read_dir(&self.dir) else { return };
        let mut found: Vec<EarlierTest> = Vec::new();
        for e in entries.flatten() {
            let folder = e.path();
            let Ok(text) = std::fs::read_to_string(folder.join("test.json")) else { continue };
            let Ok(record) = serde_json::from_str::<TestRecord>(&text) else { continue };
            if day_of(record.started_t_ns) != today {
                continue;
            }
            match read_curve(&folder.join("feed.jsonl")) {
                Ok(curve) => found.push(EarlierTest::new(&record, &curve)),
                Err(e) => tracing::warn!(test = %record.id, "the curve of an earlier test cannot be read: {e}"),
            }
        }
        found.sort_by_key(|t| t.started_t_ns);
        let skip = found.len().saturating_sub(EARLIER_TESTS);
        self.lock().earlier = found.split_off(skip);
    }

    /// `GET /api/tests`: today's stopped tests, oldest first.
    pub fn earlier(&self) -> Vec<EarlierTest> {
        let today = day_of(tagdeflect_core::clock::now_epoch_ns());
        self.lock().earlier.iter().filter(|t| day_of(t.started_t_ns) == today).cloned().collect()
    }

    /// Resumes the test of `TESTS/.running.json`, if there is one.
    fn resume(&self) -> std::io::Result<()> {
        let path = self.state_file();
        let text = match std::fs::read_to_string(&path) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(()),
            Err(e) => return Err(e),
        };
        let p: Persisted = serde_json::from_str(&text)
            .map_err(|e| std::io::Error::new(std::io::ErrorKind::InvalidData, format!("{}: {e}", path.display())))?;
        // A crash may have cut the last line of the test's files: cut back to whole lines.
        for name in ["feed.jsonl", "utm.jsonl"] {
            tagdeflect_core::linefile::LineFile::open_append(&p.folder.join(name))?;
        }
        let open = |name: &str| std::fs::OpenOptions::new().append(true).open(p.folder.join(name));
        let (feed, utm) = (open("feed.jsonl")?, open("utm.jsonl")?);
        let now = tagdeflect_core::clock::now_epoch_ns();
        let gap_s = if p.last_line_t_ns > i64::MIN { (now as i128 - p.last_line_t_ns as i128) as f64 * 1e-9 } else { f64::NAN };
        let ev = FeedEvent {
            kind: "resume".into(),
            t_ns: now,
            note: Some(format!("the daemon restarted; the test goes on from its zero (no lines for {gap_s:.1} s)")),
        };
        let mut record = p.record;
        record.events.push(ev.clone());
        let zero = Zero {
            n: p.zero_n,
            tags: p.tags.into_iter().map(|(k, v)| (k, Mean::from_parts(&v))).collect(),
            net: Mean::from_parts(&p.net),
            gauges: p.gauges.into_iter().map(|(k, v)| (k, Mean::from_parts(&v))).collect(),
        };
        tracing::warn!(test = %record.id, gap_s = format!("{gap_s:.1}"), "a test was running when the daemon stopped: resumed from its zero");
        let curve = read_curve(&p.folder.join("feed.jsonl")).unwrap_or_default();
        let r = Running { record, folder: p.folder, feed, utm, zero, written_t_ns: p.last_line_t_ns, curve };
        self.persist(&r);
        let mut g = self.lock();
        g.pending.push(ev);
        g.running = Some(r);
        Ok(())
    }

    /// The folder tests are kept in.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Inner> {
        self.inner.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Hands every record on from now on (the running test's at once); set once.
    pub fn set_on_record(&self, hook: RecordHook) {
        let g = self.lock();
        if let Some(r) = &g.running {
            hook(&r.record);
        }
        let _ = self.on_record.set(hook);
    }

    fn publish(&self, record: &TestRecord) {
        if let Some(h) = self.on_record.get() {
            h(record);
        }
    }

    /// Starts and stops tests by `rules` from now on (see [`auto`]).
    pub fn set_auto(&self, rules: auto::AutoRules) {
        self.lock().auto = Some(auto::AutoTest::new(rules));
    }

    /// Starts a test (its zero from the next frame sets); refused while one runs.
    pub fn start(&self, meta: TestMeta) -> Result<serde_json::Value, TestError> {
        meta.validate()?;
        let mut g = self.lock();
        self.open(&mut g, meta, None)?;
        drop(g);
        Ok(self.status())
    }

    /// Opens the test's folder and makes it the running test; `note` goes with its start event.
    fn open(&self, g: &mut Inner, meta: TestMeta, note: Option<String>) -> Result<String, TestError> {
        let now = tagdeflect_core::clock::now_epoch_ns();
        let stamp = chrono::DateTime::from_timestamp_nanos(now).format("%Y%m%dT%H%M%SZ");
        let id = format!("{stamp}-{}", meta.specimen.trim());
        if let Some(r) = &g.running {
            return Err(TestError::Conflict(format!("test {} is running: stop it first", r.record.id)));
        }
        let folder = self.dir.join(&id);
        if folder.exists() {
            return Err(TestError::Conflict(format!("{} exists already: wait a second and start again", folder.display())));
        }
        let io = |e: std::io::Error| TestError::Io(format!("cannot open the test's folder {}: {e}", folder.display()));
        std::fs::create_dir_all(&folder).map_err(io)?;
        let open = |name: &str| std::fs::OpenOptions::new().create_new(true).append(true).open(folder.join(name));
        let feed = open("feed.jsonl").map_err(io)?;
        let utm = open("utm.jsonl").map_err(io)?;
        let start = FeedEvent { kind: "start".into(), t_ns: now, note };
        g.pending.push(start.clone());
        let record = TestRecord {
            id: id.clone(),
            meta,
            started_t_ns: now,
            stopped_t_ns: None,
            events: vec![start],
            lines: 0,
            utm_samples: 0,
            sha256: BTreeMap::new(),
        };
        tracing::info!(test = %id, specimen = %record.meta.specimen, "test started");
        let r = Running { record, folder, feed, utm, zero: Zero::default(), written_t_ns: i64::MIN, curve: Vec::new() };
        self.persist(&r);
        self.publish(&r.record);
        g.running = Some(r);
        Ok(id)
    }

    /// An operator's note, into the feed and `test.json`.
    pub fn mark(&self, note: Option<String>) -> Result<serde_json::Value, TestError> {
        if let Some(n) = &note {
            if n.len() > 4096 || n.chars().any(|c| c.is_control()) {
                return Err(TestError::Bad("note: at most 4096 characters, no control characters".into()));
            }
        }
        self.event("mark", note)
    }

    /// Takes the zero again from the next frame sets.
    pub fn zero(&self) -> Result<serde_json::Value, TestError> {
        let v = self.event("zero", None)?;
        let mut g = self.lock();
        if let Some(r) = g.running.as_mut() {
            r.zero = Zero::default();
            self.persist(r);
        }
        Ok(v)
    }

    fn event(&self, kind: &str, note: Option<String>) -> Result<serde_json::Value, TestError> {
        let mut g = self.lock();
        let Some(r) = g.running.as_mut() else { return Err(TestError::Conflict(format!("no test is running: nothing to {kind}"))) };
        let ev = FeedEvent { kind: kind.into(), t_ns: tagdeflect_core::clock::now_epoch_ns(), note };
        r.record.events.push(ev.clone());
        self.persist(r);
        self.publish(&r.record);
        g.pending.push(ev);
        drop(g);
        Ok(self.status())
    }

    /// Ends the running test: waits until the sinks have written its lines (at most
    /// [`STOP_WAIT`]), then completes its folder (report included) and answers.
    pub fn stop(&self) -> Result<Stopped, TestError> {
        self.stop_with(None)
    }

    /// [`LabTests::stop`] with a note on the stop event (why it stopped).
    fn stop_with(&self, note: Option<String>) -> Result<Stopped, TestError> {
        let now = tagdeflect_core::clock::now_epoch_ns();
        let mut g = self.lock();
        if g.running.is_none() {
            return Err(TestError::Conflict("no test is running: nothing to stop".into()));
        }
        // Every line solved before the stop reaches the folder first (the sinks run behind
        // the solver by a line or two).
        let target = g.last_line_t_ns;
        let (g2, _) = self
            .written
            .wait_timeout_while(g, STOP_WAIT, |g| g.running.as_ref().is_some_and(|r| r.written_t_ns < target))
            .unwrap_or_else(|p| p.into_inner());
        g = g2;
        let Some(mut r) = g.running.take() else { return Err(TestError::Conflict("the test was stopped meanwhile".into())) };
        let stop = FeedEvent { kind: "stop".into(), t_ns: now, note };
        r.record.events.push(stop.clone());
        r.record.stopped_t_ns = Some(now);
        g.pending.push(stop);
        g.last = Some((r.record.id.clone(), r.folder.clone()));
        g.earlier.push(EarlierTest::new(&r.record, &r.curve));
        if g.earlier.len() > EARLIER_TESTS {
            g.earlier.remove(0);
        }
        drop(g);
        if let Err(e) = std::fs::remove_file(self.state_file()) {
            tracing::error!("cannot remove {}: {e}", self.state_file().display());
        }
        let id = r.record.id.clone();
        let folder = r.folder.clone();
        self.complete(r)?;
        tracing::info!(test = %id, folder = %folder.display(), "test stopped; its folder is complete");
        Ok(Stopped { id, folder })
    }

    /// Writes the config, the report and `test.json` of a stopped test.
    fn complete(&self, r: Running) -> Result<(), TestError> {
        let Running { mut record, folder, feed, utm, .. } = r;
        let io = |what: &str, e: std::io::Error| TestError::Io(format!("{}: {what}: {e}", folder.display()));
        feed.sync_all().map_err(|e| io("feed.jsonl", e))?;
        utm.sync_all().map_err(|e| io("utm.jsonl", e))?;
        std::fs::write(folder.join("tagdeflect.toml"), &self.config_text).map_err(|e| io("tagdeflect.toml", e))?;
        if record.meta.standard.is_some() {
            if let Some(hook) = &self.report {
                if let Err(e) = hook(&folder, &record) {
                    tracing::error!(test = %record.id, "the test's report could not be made: {e}");
                }
            }
        }
        record.sha256 = hash_folder(&folder).map_err(|e| io("hashing", e))?;
        record.sha256.extend(self.calibration_sha256.clone());
        let text = serde_json::to_string_pretty(&record).map_err(|e| TestError::Io(e.to_string()))?;
        let tmp = folder.join("test.json.tmp");
        std::fs::write(&tmp, text + "\n").map_err(|e| io("test.json", e))?;
        std::fs::rename(&tmp, folder.join("test.json")).map_err(|e| io("test.json", e))?;
        self.publish(&record);
        Ok(())
    }

    /// `GET /api/test`.
    pub fn status(&self) -> serde_json::Value {
        let g = self.lock();
        let mut st = match &g.running {
            Some(r) => serde_json::json!({
                "state": "running",
                "id": r.record.id,
                "specimen": r.record.meta.specimen,
                "operator": r.record.meta.operator,
                "standard": r.record.meta.standard,
                "started_t_ns": r.record.started_t_ns,
                "events": r.record.events,
                "lines": r.record.lines,
                "zeroing": r.zero.n < ZERO_SETS,
                "folder": r.folder,
            }),
            None => serde_json::json!({
                "state": "idle",
                "last": g.last.as_ref().map(|(id, f)| serde_json::json!({"id": id, "folder": f})),
            }),
        };
        if let Some(a) = &g.auto {
            st["auto"] = a.status();
        }
        st
    }

    /// The solver's step: the line gets the pending events, the running test and values
    /// counted from the test's zero; the automatic rules see it (a start is made here, at
    /// once; a stop on a thread of its own, as it waits for the sinks).
    pub fn apply(self: &Arc<Self>, line: &mut FeedLine) {
        let mut g = self.lock();
        g.last_line_t_ns = line.t_ns;
        if g.running.is_none() {
            if let Some(auto::Action::Start(meta, why)) = g.auto.as_mut().and_then(|a| a.step(line, None)) {
                match self.open(&mut g, meta, Some(why.clone())) {
                    Ok(id) => tracing::info!(test = %id, "test started automatically ({why})"),
                    Err(e) => tracing::error!("the automatic start failed: {e}"),
                }
            }
        }
        line.events.append(&mut g.pending);
        if let Some(r) = g.running.as_mut() {
            let zeroing = r.zero.take(line);
            if zeroing && r.zero.n == ZERO_SETS {
                // The zero has formed: a restart from here resumes from it.
                self.persist(r);
            }
            r.zero.apply(line);
            line.test = Some(TestRef { id: r.record.id.clone(), specimen: r.record.meta.specimen.clone(), zeroing });
        }
        let Inner { running, auto, .. } = &mut *g;
        if let (Some(r), Some(a)) = (running.as_ref(), auto.as_mut()) {
            let test = auto::RunningTest { standard: r.record.meta.standard.as_deref(), zero_formed: r.zero.n >= ZERO_SETS };
            if let Some(auto::Action::Stop(why)) = a.step(line, Some(test)) {
                let id = r.record.id.clone();
                drop(g);
                tracing::info!(test = %id, "stopping the test automatically ({why})");
                let me = self.clone();
                let spawned = std::thread::Builder::new().name("auto-stop".into()).spawn(move || match me.stop_with(Some(why)) {
                    Ok(s) => tracing::info!(test = %s.id, "the test stopped automatically"),
                    Err(e) => tracing::warn!(test = %id, "the automatic stop did not go through: {e}"),
                });
                if let Err(e) = spawned {
                    tracing::error!("cannot stop the test automatically: {e}");
                }
            }
        }
    }

    /// The sinks' step: a line of the running test into its folder.
    pub fn on_line(&self, line: &FeedLine) {
        let mut g = self.lock();
        let Some(r) = g.running.as_mut() else { return };
        if line.test.as_ref().is_some_and(|t| t.id == r.record.id) {
            let text = line.to_json() + "\n";
            if let Err(e) = r.feed.write_all(text.as_bytes()) {
                tracing::error!(test = %r.record.id, "cannot write the test's feed: {e}");
            } else {
                r.record.lines += 1;
            }
            if let (Some(n), Some(l)) = (line.net_deflection_mm, line.load_kn) {
                push_point(&mut r.curve, n, l);
            }
        }
        r.written_t_ns = r.written_t_ns.max(line.t_ns);
        self.written.notify_all();
    }

    /// The UTM forwarder's step: a sample of the running test into its folder.
    pub fn on_utm(&self, s: &UtmSample) {
        let mut g = self.lock();
        let Some(r) = g.running.as_mut() else { return };
        if s.t_ns < r.record.started_t_ns {
            return;
        }
        match serde_json::to_string(s) {
            Ok(text) => match r.utm.write_all((text + "\n").as_bytes()) {
                Ok(()) => r.record.utm_samples += 1,
                Err(e) => tracing::error!(test = %r.record.id, "cannot write the test's UTM samples: {e}"),
            },
            Err(e) => tracing::error!("UTM sample: {e}"),
        }
    }
}

/// A line sink that hands every line to [`LabTests::on_line`].
pub struct LabTestSink(pub Arc<LabTests>);

impl crate::LineSink for LabTestSink {
    fn name(&self) -> String {
        format!("tests {}", self.0.dir.display())
    }
    fn accept(&mut self, finished: &crate::Finished) {
        self.0.on_line(&finished.line);
    }
}

/// A test's zero: the mean of its first [`ZERO_SETS`] sets, per quantity.
#[derive(Default)]
struct Zero {
    n: usize,
    tags: BTreeMap<u32, Mean<3>>,
    net: Mean<1>,
    gauges: BTreeMap<String, Mean<1>>,
}

impl Zero {
    /// Takes `line` into the zero while it forms; true while it does.
    fn take(&mut self, line: &FeedLine) -> bool {
        if self.n >= ZERO_SETS {
            return false;
        }
        self.n += 1;
        for t in &line.tags {
            self.tags.entry(t.id).or_default().add(t.pos_mm);
        }
        if let Some(v) = line.net_deflection_mm {
            self.net.add([v]);
        }
        for (k, g) in &line.gauges {
            self.gauges.entry(k.clone()).or_default().add([g.value]);
        }
        true
    }

    /// Counts the line's values from the zero; a tag first seen after the zero formed counts
    /// from where it was first seen.
    fn apply(&mut self, line: &mut FeedLine) {
        for t in &mut line.tags {
            let m = self.tags.entry(t.id).or_insert_with(|| {
                let mut m = Mean::default();
                m.add(t.pos_mm);
                m
            });
            let (mean, sd_of_mean) = m.get();
            for ((d, p), m) in t.disp_mm.iter_mut().zip(t.pos_mm).zip(mean) {
                *d = round_um(p - m);
            }
            if let Some(s) = t.sigma_mm.as_mut() {
                for k in 0..3 {
                    s[k] = (s[k].powi(2) + sd_of_mean[k].powi(2)).sqrt();
                }
            }
        }
        if let Some(v) = line.net_deflection_mm.as_mut() {
            if self.net.n > 0 {
                let (mean, sd) = self.net.get();
                *v = round_um(*v - mean[0]);
                if let Some(s) = line.net_deflection_sigma_mm.as_mut() {
                    *s = (s.powi(2) + sd[0].powi(2)).sqrt();
                }
            }
        }
        for (k, g) in line.gauges.iter_mut() {
            if let Some(m) = self.gauges.get(k) {
                let (mean, sd) = m.get();
                g.value -= mean[0];
                if g.sigma.is_finite() {
                    g.sigma = (g.sigma.powi(2) + sd[0].powi(2)).sqrt();
                }
            }
        }
    }
}

/// The running test's state on disk (`TESTS/.running.json`).
#[derive(Serialize, Deserialize)]
struct Persisted {
    record: TestRecord,
    folder: PathBuf,
    zero_n: usize,
    tags: BTreeMap<u32, MeanParts>,
    net: MeanParts,
    gauges: BTreeMap<String, MeanParts>,
    last_line_t_ns: i64,
}

/// A [`Mean`] as stored: count, sums, sums of squares.
type MeanParts = (usize, Vec<f64>, Vec<f64>);

/// A running mean of `N` values with the standard deviation of the mean.
#[derive(Clone, Copy)]
struct Mean<const N: usize> {
    n: usize,
    sum: [f64; N],
    sum_sq: [f64; N],
}

impl<const N: usize> Default for Mean<N> {
    fn default() -> Self {
        Mean { n: 0, sum: [0.0; N], sum_sq: [0.0; N] }
    }
}

impl<const N: usize> Mean<N> {
    fn to_parts(self) -> MeanParts {
        (self.n, self.sum.to_vec(), self.sum_sq.to_vec())
    }
    fn from_parts(p: &MeanParts) -> Self {
        let mut m = Mean { n: p.0, ..Mean::default() };
        for (k, (sum, sq)) in m.sum.iter_mut().zip(m.sum_sq.iter_mut()).enumerate() {
            *sum = p.1.get(k).copied().unwrap_or(0.0);
            *sq = p.2.get(k).copied().unwrap_or(0.0);
        }
        m
    }
    fn add(&mut self, v: [f64; N]) {
        self.n += 1;
        for ((sum, sq), x) in self.sum.iter_mut().zip(self.sum_sq.iter_mut()).zip(v) {
            *sum += x;
            *sq += x * x;
        }
    }
    /// Mean, and the standard deviation of the mean (0 from one value).
    fn get(&self) -> ([f64; N], [f64; N]) {
        let n = self.n.max(1) as f64;
        let mut mean = [0.0; N];
        let mut sd = [0.0; N];
        for k in 0..N {
            mean[k] = self.sum[k] / n;
            if self.n > 1 {
                let var = ((self.sum_sq[k] - n * mean[k] * mean[k]) / (n - 1.0)).max(0.0);
                sd[k] = (var / n).sqrt();
            }
        }
        (mean, sd)
    }
}

fn round_um(v: f64) -> f64 {
    (v * 1e6).round() / 1e6
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// SHA-256 of every file under `folder` (but `test.json`), by path relative to it.
fn hash_folder(folder: &Path) -> std::io::Result<BTreeMap<String, String>> {
    let mut out = BTreeMap::new();
    let mut stack = vec![folder.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d)? {
            let e = e?;
            let p = e.path();
            if e.file_type()?.is_dir() {
                stack.push(p);
                continue;
            }
            let rel = p.strip_prefix(folder).unwrap_or(&p).to_string_lossy().into_owned();
            if rel == "test.json" || rel.ends_with(".tmp") {
                continue;
            }
            out.insert(rel, hex(&sha2::Sha256::digest(std::fs::read(&p)?)));
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use tagdeflect_core::feed::FeedTag;

    fn line(t_ns: i64, z: f64, net: f64) -> FeedLine {
        let tag = FeedTag { id: 1, pos_mm: [10.0, 0.0, z], disp_mm: [0.0, 0.0, z], views: 2, sigma_mm: Some([0.01; 3]), reproj_px: None };
        FeedLine { seq: t_ns as u64, t_ns, tags: vec![tag], net_deflection_mm: Some(net), ..FeedLine::default() }
    }

    #[test]
    fn a_test_counts_from_the_mean_of_its_first_sets_and_keeps_its_folder() {
        let dir = tempfile::tempdir().unwrap();
        let tests = LabTests::new(dir.path(), "[world]\n".into(), Vec::new(), None).unwrap();
        assert!(matches!(tests.stop(), Err(TestError::Conflict(_))));
        tests.start(TestMeta { specimen: "B12".into(), ..TestMeta::default() }).unwrap();
        assert!(matches!(tests.start(TestMeta { specimen: "B13".into(), ..TestMeta::default() }), Err(TestError::Conflict(_))));
        // Five sets at rest around z = 5 ± 0.01, then the beam deflects by 1 mm.
        let rest = [5.01, 4.99, 5.0, 5.02, 4.98];
        let mut out = Vec::new();
        for (k, z) in rest.iter().enumerate() {
            let mut l = line(k as i64, *z, *z * 0.1);
            tests.apply(&mut l);
            tests.on_line(&l);
            out.push(l);
        }
        let mut l = line(10, 4.0, 0.4);
        tests.apply(&mut l);
        tests.on_line(&l);
        assert!(out.iter().all(|l| l.test.as_ref().unwrap().zeroing));
        assert_eq!(out[0].events.iter().map(|e| e.kind.as_str()).collect::<Vec<_>>(), vec!["start"]);
        let t = l.test.as_ref().unwrap();
        assert!(!t.zeroing && t.specimen == "B12");
        assert!((l.tags[0].disp_mm[2] + 1.0).abs() < 1e-9, "{:?}", l.tags[0].disp_mm);
        assert!((l.net_deflection_mm.unwrap() + 0.1).abs() < 1e-9);
        tests.mark(Some("first crack seen".into())).unwrap();
        let stopped = tests.stop().unwrap();
        let mut after = line(11, 4.0, 0.4);
        tests.apply(&mut after);
        assert!(after.test.is_none());
        assert_eq!(after.events.iter().map(|e| e.kind.as_str()).collect::<Vec<_>>(), vec!["mark", "stop"]);
        let record: TestRecord = serde_json::from_str(&std::fs::read_to_string(stopped.folder.join("test.json")).unwrap()).unwrap();
        assert_eq!(record.lines, 6);
        assert_eq!(record.events.iter().map(|e| e.kind.as_str()).collect::<Vec<_>>(), vec!["start", "mark", "stop"]);
        for f in ["feed.jsonl", "utm.jsonl", "tagdeflect.toml"] {
            let want = hex(&sha2::Sha256::digest(std::fs::read(stopped.folder.join(f)).unwrap()));
            assert_eq!(record.sha256.get(f), Some(&want), "{f}");
        }
        assert!(!dir.path().join(".running.json").exists(), "a stopped test leaves no state behind");
        assert!(TestMeta { specimen: "<b>".into(), ..TestMeta::default() }.validate().is_err());
        assert!(TestMeta { specimen: "B1".into(), standard: Some("iso".into()), ..TestMeta::default() }.validate().is_err());
    }

    #[test]
    fn a_test_running_when_the_daemon_stops_resumes_from_its_zero() {
        let dir = tempfile::tempdir().unwrap();
        let id = {
            let tests = LabTests::new(dir.path(), String::new(), Vec::new(), None).unwrap();
            tests.start(TestMeta { specimen: "B7".into(), ..TestMeta::default() }).unwrap();
            for k in 0..ZERO_SETS {
                let mut l = line(k as i64, 5.0 + 0.01 * k as f64, 0.5);
                tests.apply(&mut l);
                tests.on_line(&l);
            }
            tests.status()["id"].as_str().unwrap().to_string()
            // Dropped without a stop: the daemon died.
        };
        let tests = LabTests::new(dir.path(), String::new(), Vec::new(), None).unwrap();
        let st = tests.status();
        assert_eq!(st["state"], "running");
        assert_eq!(st["id"], id.as_str());
        let mut l = line(100, 4.02, 0.4);
        tests.apply(&mut l);
        assert_eq!(l.events.iter().map(|e| e.kind.as_str()).collect::<Vec<_>>(), vec!["resume"]);
        assert!(!l.test.as_ref().unwrap().zeroing, "the zero is kept, not taken again");
        // The zero was the mean of 5.00 .. 5.04 = 5.02.
        assert!((l.tags[0].disp_mm[2] + 1.0).abs() < 1e-9, "{:?}", l.tags[0].disp_mm);
        tests.on_line(&l);
        let stopped = tests.stop().unwrap();
        let record: TestRecord = serde_json::from_str(&std::fs::read_to_string(stopped.folder.join("test.json")).unwrap()).unwrap();
        assert_eq!(record.events.iter().map(|e| e.kind.as_str()).collect::<Vec<_>>(), vec!["start", "resume", "stop"]);
        assert_eq!(std::fs::read_to_string(stopped.folder.join("feed.jsonl")).unwrap().lines().count(), ZERO_SETS + 1);
    }
}
