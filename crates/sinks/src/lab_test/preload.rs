//! Preload as a step: a test whose method names a `preload_kn`, started below it, waits for
//! the load to reach it before its zero is taken (its lines start there, as a testing
//! machine's record starts at its preload); `GET /api/test` says `"preloading"` meanwhile.
//! The `preload` event ("zero taken at … kN") follows when the zero has formed. A test started
//! automatically (`[output.auto_test]`) starts at the line that started it, keeps the UTM
//! samples from that line's time on, and with a method is recorded with it and waits alike.

use tagdeflect_core::feed::FeedLine;
use tagdeflect_core::utm_sample::UtmSample;

use super::state::{Inner, LabTests, Running};

/// How long before the newest UTM sample the samples are kept while no test runs, ns: longer
/// than a line takes from its exposure through the solver (a played recording's seconds count
/// as its own, several times the wall clock's).
pub(super) const RECENT_UTM_NS: i64 = 120_000_000_000;

impl LabTests {
    /// An automatically started test (opened at the time of the line that started it — not the
    /// clock's when the line was solved — so its UTM samples and lines are its own from there,
    /// in a played recording too): the UTM samples already seen from that time on go into its
    /// folder; its method (`[output.auto_test] method`) is recorded in its `test.json` (the
    /// record handed on again), and its preload waited for.
    pub(super) fn auto_started(&self, g: &mut Inner, line: &FeedLine) {
        let method = g.auto.as_ref().and_then(|a| a.rules().method_of_start());
        let recent = std::mem::take(&mut g.recent_utm);
        let Some(r) = g.running.as_mut() else { return };
        for s in recent.iter().filter(|s| s.t_ns >= line.t_ns) {
            Self::write_utm(r, s);
        }
        if let Some((method, preload_kn, record_frames)) = method {
            r.record.method = Some(method);
            r.preload_kn = preload_kn;
            r.record.record_frames = record_frames.or(r.record.record_frames);
            self.publish(&r.record);
        }
        self.persist(r);
    }

    /// A UTM sample while no test runs, kept for [`RECENT_UTM_NS`].
    pub(super) fn keep_recent_utm(g: &mut Inner, s: &UtmSample) {
        if g.auto.is_none() {
            return;
        }
        g.recent_utm.push_back(*s);
        while g.recent_utm.front().is_some_and(|f| f.t_ns < s.t_ns - RECENT_UTM_NS) {
            g.recent_utm.pop_front();
        }
    }
}

impl Running {
    /// True while the test waits for its preload: a preload to reach, no zero begun, no stop
    /// pressed (a stop's line ends the wait), and the line's load below it (or no load on it).
    pub(super) fn wait_for_preload(&self, line: &FeedLine) -> bool {
        match self.preload_kn {
            Some(target) if self.zero.n == 0 && self.ends.stop.is_none() => line.load_kn.is_none_or(|l| !(l >= target)),
            _ => false,
        }
    }

    /// `GET /api/test`'s `preloading`: the preload waited for, kN, or null.
    pub(super) fn preloading_status(&self) -> serde_json::Value {
        match self.preload_kn {
            Some(target) if self.zero.n == 0 => serde_json::json!({"preload_kn": target}),
            _ => serde_json::Value::Null,
        }
    }
}
