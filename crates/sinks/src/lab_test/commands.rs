//! The commands an operator gives (the tests' HTTP API, `tagdeflect test`): start, mark,
//! zero, stop, and the status and earlier tests the page reads.

use std::collections::BTreeMap;
use std::sync::MutexGuard;
use std::time::Duration;

use tagdeflect_core::feed::FeedEvent;

use super::folder::Phase;
use super::record::day_of;
use super::state::{Inner, LabTests, Running};
use super::zero::{Zero, ZERO_SETS};
use super::{EarlierTest, Stopped, TestError, TestMeta, TestRecord, EARLIER_TESTS};

/// How long `stop` waits for the line that carries the stop (the next frame set's) to be
/// written: a few frame intervals at the slowest rates a rig runs.
pub const STOP_WAIT: Duration = Duration::from_millis(3000);

/// How long a start waits for the previous test's stop to end — its last line written, its
/// folder and report complete — before it is refused ([`TestError::Stopping`]): a report with
/// its PDF takes 2–3 s on a lab PC, much longer only on a machine far too busy.
pub const START_WAIT: Duration = Duration::from_secs(20);

/// The `Retry-After` (s) of a start refused because the previous test is still being stopped.
pub const START_RETRY_AFTER_S: u64 = 5;

impl LabTests {
    /// `GET /api/tests`: today's stopped tests, oldest first.
    pub fn earlier(&self) -> Vec<EarlierTest> {
        let today = day_of(tagdeflect_core::clock::now_epoch_ns());
        self.lock().earlier.iter().filter(|t| day_of(t.started_t_ns) == today).cloned().collect()
    }

    /// Starts a test (its zero from the next frame sets); refused while one runs.
    pub fn start(&self, meta: TestMeta) -> Result<serde_json::Value, TestError> {
        self.start_by(meta, None)
    }

    /// [`LabTests::start`] by `user` (named on the start event).
    pub fn start_by(&self, meta: TestMeta, user: Option<String>) -> Result<serde_json::Value, TestError> {
        meta.validate()?;
        let mut g = self.after_stop(self.lock(), START_WAIT)?;
        self.open(&mut g, meta, None, user, None)?;
        drop(g);
        Ok(self.status())
    }

    /// Waits (at most `wait`) while the previous test is being stopped — its stop pressed and
    /// its last line not written yet, or its folder and report being completed — and gives the
    /// lock back; still stopping after `wait`: [`TestError::Stopping`]. A start pressed right
    /// after a stop from another client (or after an automatic stop, or by a client that gave
    /// up waiting for its stop's answer) so starts once that stop is through.
    pub(super) fn after_stop<'a>(&'a self, g: MutexGuard<'a, Inner>, wait: Duration) -> Result<MutexGuard<'a, Inner>, TestError> {
        let (g, _) = self.written.wait_timeout_while(g, wait, |g| stopping(g).is_some()).unwrap_or_else(|p| p.into_inner());
        match stopping(&g) {
            Some(id) => Err(TestError::Stopping(format!(
                "test {id} is still being stopped (its last line, folder and report): start again in a few seconds"
            ))),
            None => Ok(g),
        }
    }

    /// Opens the test's folder and makes it the running test; `note` goes with its start event,
    /// stamped `at_ns` (the line that decided an automatic start: its own time) or now — before
    /// the record is first handed on, so that every version of it has the same start.
    pub(super) fn open(
        &self,
        g: &mut Inner,
        meta: TestMeta,
        note: Option<String>,
        user: Option<String>,
        at_ns: Option<i64>,
    ) -> Result<String, TestError> {
        let meta = meta.trimmed();
        let now = tagdeflect_core::clock::now_epoch_ns();
        let started_t_ns = at_ns.unwrap_or(now);
        let stamp = chrono::DateTime::from_timestamp_nanos(now).format("%Y%m%dT%H%M%SZ");
        let id = format!("{stamp}-{}", meta.specimen);
        if let Some(r) = &g.running {
            return Err(TestError::Conflict(format!("test {} is running: stop it first", r.record.id)));
        }
        self.refuse_if_unfinished(g)?;
        let folder = self.dir.join(&id);
        if folder.exists() {
            return Err(TestError::Conflict(format!("{} exists already: wait a second and start again", folder.display())));
        }
        let io = |e: std::io::Error| TestError::Io(format!("cannot open the test's folder {}: {e}", folder.display()));
        std::fs::create_dir_all(&folder).map_err(io)?;
        let (feed, utm) = Self::open_files(&folder).map_err(io)?;
        let start = FeedEvent { kind: "start".into(), t_ns: started_t_ns, note, user };
        g.pending.push(start.clone());
        let record = TestRecord {
            id: id.clone(),
            meta,
            started_t_ns,
            stopped_t_ns: None,
            events: vec![start],
            lines: 0,
            utm_samples: 0,
            sha256: BTreeMap::new(),
            method: None,
            specimen_info: None,
            crack: None,
            preload: None,
            verification: self.verification_now(g),
            frames_stopped: None,
            record_frames: self.frames.setup.get().map(|s| s.default),
        };
        tracing::info!(test = %id, specimen = %record.meta.specimen, "test started");
        let r = Running {
            record,
            folder,
            feed,
            utm,
            zero: Zero::default(),
            written_t_ns: i64::MIN,
            curve: Vec::new(),
            ends: Default::default(),
            preload_kn: None,
        };
        self.persist(&r);
        self.publish(&r.record);
        g.running = Some(r);
        Ok(id)
    }

    /// An operator's note, into the feed and `test.json`.
    pub fn mark(&self, note: Option<String>) -> Result<serde_json::Value, TestError> {
        self.mark_by(note, None)
    }

    /// [`LabTests::mark`] by `user`.
    pub fn mark_by(&self, note: Option<String>, user: Option<String>) -> Result<serde_json::Value, TestError> {
        if let Some(n) = &note {
            tagdeflect_core::limits::check_text("note", n, false)?;
        }
        self.event("mark", note, user)
    }

    /// Takes the zero again from the next frame sets.
    pub fn zero(&self) -> Result<serde_json::Value, TestError> {
        self.zero_by(None)
    }

    /// [`LabTests::zero`] by `user`.
    pub fn zero_by(&self, user: Option<String>) -> Result<serde_json::Value, TestError> {
        // The zero is taken again even when its state could not be kept (the event is in
        // the feed); the answer then says so.
        let v = self.event("zero", None, user);
        let mut g = self.lock();
        if let (Some(r), true) = (g.running.as_mut(), !matches!(v, Err(TestError::Conflict(_)))) {
            r.zero = Zero::default();
            self.persist(r);
        }
        v
    }

    fn event(&self, kind: &str, note: Option<String>, user: Option<String>) -> Result<serde_json::Value, TestError> {
        let mut g = self.lock();
        let Some(r) = g.running.as_mut() else { return Err(TestError::Conflict(format!("no test is running: nothing to {kind}"))) };
        if r.ends.stop.is_some() || r.ends.stop_line_t_ns.is_some() {
            return Err(TestError::Conflict(format!("the test is being stopped: no {kind}")));
        }
        let ev = FeedEvent { kind: kind.into(), t_ns: tagdeflect_core::clock::now_epoch_ns(), note, user };
        room_for(&r.record, &ev)?;
        r.record.events.push(ev.clone());
        let kept = self.persist_as(r, Phase::Running);
        self.publish(&r.record);
        g.pending.push(ev);
        drop(g);
        kept.map_err(|e| {
            TestError::Io(format!("the {kind} is in the feed and goes into test.json, but {e}: a restart now would lose it"))
        })?;
        Ok(self.status())
    }

    /// Ends the running test: waits until the sinks have written its lines (at most
    /// [`STOP_WAIT`]), then completes its folder (report included) and answers.
    pub fn stop(&self) -> Result<Stopped, TestError> {
        self.stop_with(None, None, None)
    }

    /// [`LabTests::stop`] by `user`.
    pub fn stop_by(&self, user: Option<String>) -> Result<Stopped, TestError> {
        self.stop_with(None, user, None)
    }

    /// [`LabTests::stop`] with a note on the stop event (why it stopped), stamped `at_ns` (the
    /// line that decided an automatic stop: its own time, as an automatic start's) or now.
    pub(super) fn stop_with(&self, note: Option<String>, user: Option<String>, at_ns: Option<i64>) -> Result<Stopped, TestError> {
        let now = at_ns.unwrap_or_else(tagdeflect_core::clock::now_epoch_ns);
        let mut g = self.lock();
        if g.running.is_none() {
            drop(g);
            return self.retry_unfinished().unwrap_or_else(|| Err(TestError::Conflict("no test is running: nothing to stop".into())));
        }
        if g.running.as_ref().is_some_and(|r| r.ends.stop.is_some() || r.ends.stop_line_t_ns.is_some()) {
            return Err(TestError::Conflict("the test is being stopped".into()));
        }
        // The stop goes onto the next line, the test's last; the stop answers once the sinks
        // have written it (every line solved before it is then in the folder too).
        let stop = FeedEvent { kind: "stop".into(), t_ns: now, note, user };
        if let Some(r) = g.running.as_mut() {
            r.ends.stop = Some(stop.clone());
        }
        let (g2, _) = self
            .written
            .wait_timeout_while(g, STOP_WAIT, |g| g.running.as_ref().is_some_and(|r| !r.ends.stop_written))
            .unwrap_or_else(|p| p.into_inner());
        g = g2;
        let Some(mut r) = g.running.take() else { return Err(TestError::Conflict("the test was stopped meanwhile".into())) };
        if !r.ends.stop_written {
            tracing::warn!(test = %r.record.id, "no line came within {STOP_WAIT:?} of the stop: its stop event is in test.json, not in the feed");
        }
        r.record.events.push(stop);
        r.record.stopped_t_ns = Some(now);
        // Assessed again: a bump (or the validity's end) during the test makes it stale.
        if let Some(v) = self.verification_now(&g) {
            r.record.verification = Some(v);
        }
        g.last = Some((r.record.id.clone(), r.folder.clone()));
        g.earlier.push(EarlierTest::new(&r.record, &r.curve));
        if g.earlier.len() > EARLIER_TESTS {
            g.earlier.remove(0);
        }
        Self::being_completed(&mut g, &r.record.id);
        drop(g);
        let id = r.record.id.clone();
        let folder = r.folder.clone();
        let report_error = self.finish_stop(r)?;
        tracing::info!(test = %id, folder = %folder.display(), "test stopped; its folder is complete");
        Ok(Stopped { id, folder, report_error })
    }

    /// `GET /api/test`: the running test, or idle with the last one (and `stopping`, its id,
    /// while its folder is being completed); the verification in force either way.
    pub fn status(&self) -> serde_json::Value {
        let idle_verification = if self.lock().running.is_none() { self.verification_idle() } else { None };
        let g = self.lock();
        let mut st = match &g.running {
            Some(r) => serde_json::json!({
                "state": "running",
                "id": r.record.id,
                "specimen": r.record.meta.specimen,
                "operator": r.record.meta.operator,
                "standard": r.record.meta.standard,
                "method": r.record.method,
                "verification": r.record.verification,
                "measured": r.record.meta.measured,
                "started_t_ns": r.record.started_t_ns,
                "events": r.record.events,
                "lines": r.record.lines,
                "zeroing": r.zero.n < ZERO_SETS,
                "preloading": r.preloading_status(),
                "folder": r.folder,
            }),
            None => serde_json::json!({
                "state": "idle",
                "last": g.last.as_ref().map(|(id, f)| serde_json::json!({"id": id, "folder": f, "report_error": g.last_report_error})),
                "verification": idle_verification,
            }),
        };
        // Taken off and its folder (report, test.json) being completed: `last` is not complete
        // yet (the page reads its verdict once `stopping` is gone).
        if let (None, Some(u)) = (&g.running, g.unfinished.as_ref().filter(|u| u.test.is_none())) {
            st["stopping"] = u.id.clone().into();
        }
        if let Some(a) = &g.auto {
            st["auto"] = a.status();
        }
        st
    }
}

/// The test being stopped, if one is: its stop pressed (its last line not written yet), or
/// taken off and its folder being completed (not one whose completion failed: that waits for
/// the next `stop`).
fn stopping(g: &Inner) -> Option<String> {
    if let Some(r) = g.running.as_ref().filter(|r| r.ends.stop.is_some() || r.ends.stop_line_t_ns.is_some()) {
        return Some(r.record.id.clone());
    }
    g.unfinished.as_ref().filter(|u| u.test.is_none()).map(|u| u.id.clone())
}

/// An operator's event `ev` fits the running test's record within the limits the archive
/// takes ([`tagdeflect_core::limits`]): at most [`OPERATOR_EVENTS_MAX`] of them, the record at
/// most [`RECORD_MAX_BYTES`] with it; else 400 naming the note.
pub(super) fn room_for(record: &TestRecord, ev: &FeedEvent) -> Result<(), TestError> {
    use tagdeflect_core::limits::{OPERATOR_EVENTS_MAX, RECORD_MAX_BYTES};
    let daemons = ["start", "stop", "resume", "preload"];
    let operators = record.events.iter().filter(|e| !daemons.contains(&e.kind.as_str())).count();
    if operators >= OPERATOR_EVENTS_MAX {
        return Err(TestError::Bad(format!("{}: a test takes at most {OPERATOR_EVENTS_MAX} marks, zeros and cracks", ev.kind)));
    }
    let bytes = serde_json::to_vec(record).map_or(0, |v| v.len()) + serde_json::to_vec(ev).map_or(0, |v| v.len()) + 1;
    if bytes > RECORD_MAX_BYTES {
        return Err(TestError::Bad(format!(
            "note: the test's record would be {bytes} bytes with this {}, over the {RECORD_MAX_BYTES} a test's record may have: a shorter note",
            ev.kind
        )));
    }
    Ok(())
}
