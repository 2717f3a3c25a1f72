//! The pipeline's steps: the solver's (events, the running test and values from its zero into
//! the line, the automatic rules), the sinks' (the test's lines into its folder) and the UTM
//! forwarder's (the test's samples into its folder).

use std::sync::Arc;

use tagdeflect_core::feed::{FeedEvent, FeedLine, TestRef};
use tagdeflect_core::lab_test::{Preload, TestRecord};
use tagdeflect_core::utm_sample::UtmSample;

use super::auto;
use super::folder::RESUME_NOTE;
use super::record::push_point;
use super::state::{Inner, LabTests, Running};
use super::zero::{spread_warning, ZERO_SETS};

impl LabTests {
    /// The solver's step: the line gets the pending events, the running test and values
    /// counted from the test's zero; the automatic rules see it (a start is made here, at
    /// once; a stop on a thread of its own, as it waits for the sinks).
    pub fn apply(self: &Arc<Self>, line: &mut FeedLine) {
        let mut g = self.lock();
        g.last_line_t_ns = line.t_ns;
        Self::note_bumps(&mut g, line);
        if g.running.is_none() {
            if let Some(auto::Action::Start(meta, why)) = g.auto.as_mut().and_then(|a| a.step(line, None)) {
                match self.open(&mut g, meta, Some(why.clone()), None, Some(line.t_ns)) {
                    Ok(id) => {
                        self.auto_started(&mut g, line);
                        tracing::info!(test = %id, "test started automatically ({why})");
                        self.audit_auto_start(id, why);
                    }
                    Err(e) => tracing::error!("the automatic start failed: {e}"),
                }
            }
        }
        // A line exposed before the running test's start, or after the line that carried its
        // stop, or below the preload its method waits for, is no line of the test: the test's
        // events wait for its first line (its lines and its zero start at the preload).
        let of_test =
            g.running.as_ref().map(|r| line.t_ns >= r.record.started_t_ns && r.ends.stop_line_t_ns.is_none() && !r.wait_for_preload(line));
        if of_test != Some(false) {
            line.events.append(&mut g.pending);
        }
        if let Some(r) = g.running.as_mut().filter(|_| of_test == Some(true)) {
            self.resumed_gap(r, line);
            let zeroing = r.zero.take(line);
            if zeroing && r.zero.n == ZERO_SETS {
                // The zero has formed: a restart from here resumes from it.
                self.persist(r);
            }
            // The preload: the load of the line that completed the zero, else of the first
            // line after it that carries one (a UTM sample may not have reached that line).
            if r.zero.n >= ZERO_SETS && r.record.preload.is_none() && line.load_kn.is_some() {
                let ev = preload(&mut r.record, line, r.zero.loads_kn, r.preload_kn);
                line.events.extend(ev);
                self.persist(r);
            }
            r.zero.apply(line);
            line.test = Some(TestRef { id: r.record.id.clone(), specimen: r.record.meta.specimen.clone(), zeroing });
            if let Some(stop) = r.ends.stop.take() {
                // The stop's own line: the test's last.
                line.events.push(stop);
                r.ends.stop_line_t_ns = Some(line.t_ns);
            }
        }
        let Inner { running, auto, .. } = &mut *g;
        if let (Some(r), Some(a)) = (running.as_ref(), auto.as_mut()) {
            let test = auto::RunningTest { standard: r.record.meta.standard.as_deref(), zero_formed: r.zero.n >= ZERO_SETS };
            if let Some(auto::Action::Stop(why)) = a.step(line, Some(test)) {
                let (id, at_ns) = (r.record.id.clone(), line.t_ns);
                drop(g);
                tracing::info!(test = %id, "stopping the test automatically ({why})");
                let me = self.clone();
                let spawned =
                    std::thread::Builder::new().name("auto-stop".into()).spawn(move || match me.stop_with(Some(why), None, Some(at_ns)) {
                        Ok(s) => {
                            tracing::info!(test = %s.id, "the test stopped automatically");
                            let _ = me.audit_stop(&super::audit::auto_actor(), &s);
                        }
                        Err(e) => tracing::warn!(test = %id, "the automatic stop did not go through: {e}"),
                    });
                if let Err(e) = spawned {
                    tracing::error!("cannot stop the test automatically: {e}");
                }
            }
        }
    }

    /// The first line of a resumed test: its `resume` event's note gets the gap, from the last
    /// line written before the daemon stopped to this one (in the line and in the record).
    fn resumed_gap(&self, r: &mut Running, line: &mut FeedLine) {
        let Some(before) = r.ends.resumed_after_t_ns.take() else { return };
        let note = format!("{RESUME_NOTE} (no lines for {:.1} s)", (line.t_ns as i128 - before as i128) as f64 * 1e-9);
        for ev in line.events.iter_mut().filter(|e| e.kind == "resume") {
            if let Some(kept) = r.record.events.iter_mut().rev().find(|e| e.kind == "resume" && e.t_ns == ev.t_ns) {
                kept.note = Some(note.clone());
            }
            ev.note = Some(note.clone());
        }
        self.persist(r);
    }

    /// The sinks' step: a line of the running test into its folder.
    pub fn on_line(&self, line: &FeedLine) {
        let mut g = self.lock();
        let Some(r) = g.running.as_mut() else { return };
        if line.test.as_ref().is_some_and(|t| t.id == r.record.id) {
            // A full disk: the line is held back and retried (one error per outage).
            if let Err(e) = r.feed.write(line) {
                tracing::error!(test = %r.record.id, "the test's feed: {e}");
            }
            r.record.lines += 1;
            if let (Some(n), Some(l)) = (line.net_deflection_mm, line.load_kn) {
                push_point(&mut r.curve, n, l);
            }
            r.ends.stop_written |= r.ends.stop_line_t_ns == Some(line.t_ns);
        }
        r.written_t_ns = r.written_t_ns.max(line.t_ns);
        self.written.notify_all();
    }

    /// The UTM forwarder's step: a sample of the running test into its folder.
    pub fn on_utm(&self, s: &UtmSample) {
        {
            let mut g = self.lock();
            g.last_load = Some((s.load_kn, s.t_ns));
            let Some(r) = g.running.as_mut() else {
                Self::keep_recent_utm(&mut g, s);
                return;
            };
            if s.t_ns < r.record.started_t_ns {
                return;
            }
            Self::write_utm(r, s);
        }
        self.frames_utm(s);
    }

    /// A UTM sample into the running test's folder.
    pub(super) fn write_utm(r: &mut Running, s: &UtmSample) {
        match serde_json::to_string(s) {
            Ok(text) => {
                if let Err(e) = r.utm.write_text(text) {
                    tracing::error!(test = %r.record.id, "the test's UTM samples: {e}");
                }
                r.record.utm_samples += 1;
            }
            Err(e) => tracing::error!("UTM sample: {e}"),
        }
    }
}

/// The load at which the test's zero formed (`preload`), from the line that completed it (or
/// the first one after it with a load), with the range of the zero's sets' loads
/// (`zero_loads_kn`) and, when they spanned much load, a warning ([`spread_warning`]: logged,
/// kept in the record, and in the report's QC list); a test with a method gets a `preload`
/// event too (its tare and preload step).
fn preload(record: &mut TestRecord, line: &FeedLine, zero_loads_kn: Option<[f64; 2]>, preload_kn: Option<f64>) -> Option<FeedEvent> {
    let load_kn = line.load_kn?;
    let [lo, hi] = zero_loads_kn.unwrap_or([load_kn, load_kn]);
    let range = [lo.min(load_kn), hi.max(load_kn)];
    let warning = spread_warning(range, preload_kn);
    if let Some(w) = &warning {
        tracing::warn!(test = %record.id, "{w}");
    }
    record.preload = Some(Preload { load_kn, t_ns: line.t_ns, zero_loads_kn: Some(range), warning });
    record.method.as_ref()?;
    let ev = FeedEvent { kind: "preload".into(), t_ns: line.t_ns, note: Some(format!("zero taken at {load_kn:.3} kN")), user: None };
    record.events.push(ev.clone());
    Some(ev)
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
