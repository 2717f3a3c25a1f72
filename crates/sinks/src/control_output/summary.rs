//! The control registers' part in a test's `control.json` (docs/control.md "A test under
//! control"): each frame set's verdict — valid by the signal's rule, or why not — and the
//! exposure → register latency of the test's values, into the
//! [`SignalLog`](crate::signal_log::SignalLog).

use std::sync::Arc;
use std::time::Instant;

use tagdeflect_core::control_summary::OutputSummary;
use tagdeflect_core::feed::FeedLine;

use super::{ControlOutput, Shared};
use crate::signal::SignalState;
use crate::signal_log::{stall_s, verdict, TestSummaries};

impl Shared {
    /// Takes the line just taken into the signal (`taken`: it carried a value, served
    /// `latency_ms` after its exposure) into the test log.
    pub(super) fn log_line(&self, st: &SignalState, line: &FeedLine, taken: bool, latency_ms: f64) {
        let v = verdict(st, &self.rule, taken, Instant::now());
        let mut log = self.log.lock().expect("control test log");
        log.take(line.test.as_ref().map(|t| t.id.as_str()), line.seq, line.t_ns, &v, stall_s(st, &self.rule));
        if taken {
            log.written(line.seq, latency_ms);
        }
    }
}

impl ControlOutput {
    /// The figures of test `id` per test, as a handle that outlives the sink (the tests'
    /// folder hook writes them into `control.json`).
    pub fn test_summaries(&self) -> TestSummaries {
        let shared = self.shared.clone();
        Arc::new(move |id: &str| summary_of(&shared, id))
    }
}

fn summary_of(shared: &Shared, id: &str) -> Option<OutputSummary> {
    let mut s = shared.log.lock().expect("control test log").summary(id)?;
    s.kind = "registers".into();
    s.target = shared.target.clone();
    s.gauge = shared.rule.gauge.clone();
    s.max_sigma_mm = shared.rule.max_sigma_mm;
    s.stale_sets = shared.rule.stale_sets;
    Some(s)
}
