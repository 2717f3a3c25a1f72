//! Preload as a step: a test whose method names a `preload_kn`, started below it, waits for
//! the load to reach it before its zero is taken (its lines start there, as a testing
//! machine's record starts at its preload); `GET /api/test` says `"preloading"` meanwhile.
//! The `preload` event ("zero taken at … kN") follows when the zero has formed. A test started
//! automatically (`[output.auto_test]`) with a method is recorded with it and waits alike.

use tagdeflect_core::feed::FeedLine;

use super::state::{Inner, LabTests, Running};

impl LabTests {
    /// An automatically started test's method (`[output.auto_test] method`): recorded in its
    /// `test.json`, and its preload waited for.
    pub(super) fn auto_method(&self, g: &mut Inner) {
        let Some((method, preload_kn)) = g.auto.as_ref().and_then(|a| a.rules().method_of_start()) else { return };
        if let Some(r) = g.running.as_mut() {
            r.record.method = Some(method);
            r.preload_kn = preload_kn;
            self.persist(r);
        }
    }
}

impl Running {
    /// True while the test waits for its preload: a preload to reach, no zero begun, and the
    /// line's load below it (or no load on the line).
    pub(super) fn wait_for_preload(&self, line: &FeedLine) -> bool {
        match self.preload_kn {
            Some(target) if self.zero.n == 0 => line.load_kn.is_none_or(|l| !(l >= target)),
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
