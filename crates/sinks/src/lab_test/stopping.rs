//! A stop that survives a crash: the stopped test's state stays in `TESTS/.running.json`,
//! saying "stopping", until its folder is complete (`test.json` in place, synced), and only
//! then goes. A daemon started on a "stopping" state completes the folder (the report,
//! `test.json`) on a thread of its own and logs it; a stop whose folder could not be completed
//! (a full disk) stays unfinished: the next `stop` completes it again, and no test starts
//! before it is complete.

use std::sync::Arc;

use super::folder::{sync_dir, Phase};
use super::state::{LabTests, Running};
use super::TestError;

/// A stopped test whose folder is not complete yet.
pub(super) struct Unfinished {
    /// The test's id.
    pub(super) id: String,
    /// The test, when its completion failed (taken by the next `stop`); `None` while it is being
    /// completed.
    pub(super) test: Option<Running>,
    /// What is going on, for the operator.
    pub(super) why: String,
}

impl LabTests {
    /// Completes a stopped test's folder: its state says "stopping" first, the folder is
    /// completed, then the state goes. On an error the test stays unfinished (see the module doc).
    pub(super) fn finish_stop(&self, mut r: Running) -> Result<Option<String>, TestError> {
        if let Err(e) = self.persist_as(&r, Phase::Stopping) {
            tracing::error!(test = %r.record.id, "{e}");
        }
        match self.complete(&mut r) {
            Ok(report_error) => {
                // The state goes before a start may write its own (a start waits while the
                // test is unfinished).
                self.drop_state();
                let mut g = self.lock();
                g.unfinished = None;
                g.last_report_error = report_error.clone();
                drop(g);
                // A start waiting for this stop goes on.
                self.written.notify_all();
                Ok(report_error)
            }
            Err(e) => {
                tracing::error!(test = %r.record.id, "the stopped test's folder could not be completed: {e}; stop again once it can be written");
                let why =
                    format!("test {} stopped, but its folder could not be completed ({e}): stop again once it can be written", r.record.id);
                self.lock().unfinished = Some(Unfinished { id: r.record.id.clone(), test: Some(r), why });
                self.written.notify_all();
                Err(e)
            }
        }
    }

    /// Removes `TESTS/.running.json` (the folder synced): no test runs or stops.
    fn drop_state(&self) {
        let path = self.state_file();
        if let Err(e) = std::fs::remove_file(&path).and_then(|()| sync_dir(&self.dir)) {
            tracing::error!("cannot remove {}: {e}", path.display());
        }
    }

    /// `stop` with no test running: completes an unfinished stop, if there is one to retry.
    pub(super) fn retry_unfinished(&self) -> Option<Result<super::Stopped, TestError>> {
        let mut g = self.lock();
        let u = g.unfinished.as_mut()?;
        let Some(r) = u.test.take() else { return Some(Err(TestError::Conflict(u.why.clone()))) };
        let id = u.id.clone();
        Self::being_completed(&mut g, &id);
        drop(g);
        let (id, folder) = (r.record.id.clone(), r.folder.clone());
        Some(self.finish_stop(r).map(|report_error| {
            tracing::info!(test = %id, "the stopped test's folder is complete");
            super::Stopped { id, folder, report_error }
        }))
    }

    /// Marks the test just taken off as running as being completed: no test starts (and
    /// writes its state over this one's) until its folder is complete.
    pub(super) fn being_completed(g: &mut super::state::Inner, id: &str) {
        let why = format!("test {id} stopped and its folder is being completed");
        g.unfinished = Some(Unfinished { id: id.to_string(), test: None, why });
    }

    /// Refused while a stopped test's folder is not complete (`start`).
    pub(super) fn refuse_if_unfinished(&self, g: &super::state::Inner) -> Result<(), TestError> {
        match &g.unfinished {
            Some(u) => Err(TestError::Conflict(u.why.clone())),
            None => Ok(()),
        }
    }

    /// Completes, on a thread of its own, the folder of a test the last daemon stopped but
    /// did not complete (its state said "stopping").
    pub(super) fn complete_at_start(self: &Arc<Self>, r: Running) {
        let id = r.record.id.clone();
        tracing::warn!(test = %id, folder = %r.folder.display(), "the daemon stopped while this test was being stopped: its folder (report, test.json) is completed now");
        {
            let mut g = self.lock();
            g.last = Some((id.clone(), r.folder.clone()));
            g.earlier.push(super::EarlierTest::new(&r.record, &r.curve));
            if g.earlier.len() > super::EARLIER_TESTS {
                g.earlier.remove(0);
            }
            Self::being_completed(&mut g, &id);
        }
        let me = self.clone();
        let spawned = std::thread::Builder::new().name("complete-stop".into()).spawn(move || {
            if me.finish_stop(r).is_ok() {
                tracing::info!(test = %id, "the stopped test's folder is complete");
            }
        });
        if let Err(e) = spawned {
            tracing::error!("cannot complete the stopped test's folder: {e}");
        }
    }
}
