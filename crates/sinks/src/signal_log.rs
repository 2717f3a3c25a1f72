//! A control output's record of each lab test it served (docs/control.md "A test under
//! control"): per frame set of the test, whether the valid line was high after it and, when
//! not, why; the stretches of invalid sets (a pause between frame sets longer than the
//! signal's staleness is one too) and the longest; the exposure → write latency of the test's
//! values. The figures go into the test's `control.json` at its stop
//! ([`tagdeflect_core::control_summary`]).

use std::collections::VecDeque;
use std::time::Instant;

use tagdeflect_core::control_summary::{InvalidStretch, Latency, OutputSummary};

use crate::signal::{SignalRule, SignalState};

/// Tests kept after their last line (the stop's folder is written a moment later).
const KEPT_TESTS: usize = 4;
/// Most latencies kept per test (about 10 h at 30 frame sets/s).
const MAX_LATENCIES: usize = 1 << 20;

/// The figures of a test by its id, from a running control output (the binary writes them
/// into the stopped test's `control.json`).
pub type TestSummaries = std::sync::Arc<dyn Fn(&str) -> Option<OutputSummary> + Send + Sync>;

/// One frame set's verdict: the valid line high after it, or low and why.
pub type Verdict = Result<(), String>;

/// The signal's verdict right after a line was taken at `now` (`taken`: the line carried a
/// value): valid by the rule, or why not.
pub fn verdict(st: &SignalState, rule: &SignalRule, taken: bool, now: Instant) -> Verdict {
    if st.valid_at(rule, now, tagdeflect_core::clock::now_epoch_ns()) {
        return Ok(());
    }
    Err(match st.sample {
        _ if !taken => format!("no value (its tags not solved in {} frame set(s): a lost camera, the tags hidden)", rule.stale_sets),
        Some(s) if s.sigma > rule.max_sigma_mm => format!("σ above max_sigma_mm ({:.4} > {} mm)", s.sigma, rule.max_sigma_mm),
        _ => "the value exposed too long ago (the pipeline late)".into(),
    })
}

/// The pause between frame sets beyond which the signal is stale, s (once a period is known).
pub fn stall_s(st: &SignalState, rule: &SignalRule) -> Option<f64> {
    st.period_s().map(|p| (rule.stale_sets as f64 + 0.5) * p)
}

/// The open stretch of invalid sets.
#[derive(Debug, Clone)]
struct Open {
    from_t_ns: i64,
    sets: u64,
    cause: String,
}

/// One test's figures so far.
#[derive(Debug, Clone, Default)]
struct TestFigures {
    id: String,
    first_seq: u64,
    last_seq: u64,
    frame_sets: u64,
    valid_sets: u64,
    stretches: u64,
    longest: Option<InvalidStretch>,
    open: Option<Open>,
    last_t_ns: Option<i64>,
    latencies_ms: Vec<f32>,
    values_written: u64,
    superseded: u64,
    outages: u64,
}

impl TestFigures {
    /// Ends the open stretch at `t_ns`.
    fn close(&mut self, t_ns: i64) {
        let Some(o) = self.open.take() else { return };
        let s =
            InvalidStretch { from_t_ns: o.from_t_ns, duration_ms: (t_ns - o.from_t_ns) as f64 * 1e-6, frame_sets: o.sets, cause: o.cause };
        self.stretches += 1;
        if self
            .longest
            .as_ref()
            .is_none_or(|l| s.duration_ms > l.duration_ms || (s.duration_ms == l.duration_ms && s.frame_sets > l.frame_sets))
        {
            self.longest = Some(s);
        }
    }

    fn take(&mut self, t_ns: i64, verdict: &Verdict, stall_s: Option<f64>) {
        // A pause longer than the staleness: the line was low from the last set on.
        if let (Some(last), Some(stall_s)) = (self.last_t_ns, stall_s) {
            let gap_s = (t_ns - last) as f64 * 1e-9;
            if gap_s > stall_s && self.open.is_none() {
                let cause = format!("no frame set for {:.0} ms (a stalled pipeline or a lost camera stream)", gap_s * 1e3);
                self.open = Some(Open { from_t_ns: last, sets: 0, cause });
            }
        }
        self.frame_sets += 1;
        self.last_t_ns = Some(t_ns);
        match verdict {
            Ok(()) => {
                self.valid_sets += 1;
                self.close(t_ns);
            }
            Err(cause) => {
                let open = self.open.get_or_insert_with(|| Open { from_t_ns: t_ns, sets: 0, cause: cause.clone() });
                open.sets += 1;
            }
        }
    }

    /// The summary as of now (an open stretch counted to the last set).
    fn summary(&self) -> OutputSummary {
        let mut f = self.clone();
        if let Some(t) = f.last_t_ns {
            f.close(t);
        }
        OutputSummary {
            frame_sets: f.frame_sets,
            valid_sets: f.valid_sets,
            invalid_stretches: f.stretches,
            longest_invalid: f.longest,
            latency: Latency::of(f.latencies_ms.iter().map(|&v| v as f64).collect()),
            values_written: f.values_written,
            superseded: f.superseded,
            outages: f.outages,
            ..OutputSummary::default()
        }
    }
}

/// The record of the tests a control output served: the running one and the last few.
#[derive(Debug, Default)]
pub struct SignalLog {
    current: Option<TestFigures>,
    finished: VecDeque<TestFigures>,
}

impl SignalLog {
    /// Takes one frame set: its test (`None` outside a test), `seq`, time and verdict;
    /// `stall_s` is the pause between sets beyond which the signal was stale.
    pub fn take(&mut self, test: Option<&str>, seq: u64, t_ns: i64, verdict: &Verdict, stall_s: Option<f64>) {
        if self.current.as_ref().map(|c| c.id.as_str()) != test {
            if let Some(done) = self.current.take() {
                self.finished.push_back(done);
                if self.finished.len() > KEPT_TESTS {
                    self.finished.pop_front();
                }
            }
            self.current = test.map(|id| TestFigures { id: id.to_string(), first_seq: seq, ..TestFigures::default() });
        }
        if let Some(c) = self.current.as_mut() {
            c.last_seq = seq;
            c.take(t_ns, verdict, stall_s);
        }
    }

    /// A value of frame set `seq` written (acknowledged) `latency_ms` after its exposure (to
    /// the test whose sets it is among: its last value may be acknowledged after the next
    /// test's, or no test's, first line came).
    pub fn written(&mut self, seq: u64, latency_ms: f64) {
        let of = |c: &&mut TestFigures| c.first_seq <= seq && seq <= c.last_seq;
        if let Some(c) = self.current.iter_mut().chain(self.finished.iter_mut().rev()).find(of) {
            c.values_written += 1;
            if c.latencies_ms.len() < MAX_LATENCIES {
                c.latencies_ms.push(latency_ms as f32);
            }
        }
    }

    /// A value was replaced by a newer one before its write.
    pub fn superseded(&mut self) {
        if let Some(c) = self.current.as_mut() {
            c.superseded += 1;
        }
    }

    /// An outage began.
    pub fn outage(&mut self) {
        if let Some(c) = self.current.as_mut() {
            c.outages += 1;
        }
    }

    /// The figures of test `id` (running or among the last few), without the output's own
    /// description (`kind`, `target`, the rule, the scaling: the caller's).
    pub fn summary(&self, id: &str) -> Option<OutputSummary> {
        self.current.iter().chain(self.finished.iter().rev()).find(|t| t.id == id).map(TestFigures::summary)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: i64 = 1_000_000;

    #[test]
    fn the_longest_invalid_stretch_and_the_valid_share_are_counted_per_test() {
        let mut log = SignalLog::default();
        let stall = Some(0.05);
        log.take(None, 0, 0, &Ok(()), stall);
        let lost = Err("its tags not solved".to_string());
        // Test "a": 10 sets at 33 ms, sets 3–4 invalid, then a 200 ms pause, then valid.
        for k in 1..=10u64 {
            let v = if (3..=4).contains(&k) { lost.clone() } else { Ok(()) };
            log.take(Some("a"), k, k as i64 * 33 * MS, &v, stall);
            log.written(k, 20.0 + k as f64);
        }
        log.take(Some("a"), 11, 530 * MS, &Ok(()), stall);
        log.take(None, 12, 563 * MS, &Ok(()), stall);
        log.written(12, 99.0); // outside the test: not counted
        log.written(11, 25.0); // the test's last value, acknowledged after the next line
        let s = log.summary("a").expect("test a");
        assert_eq!((s.frame_sets, s.valid_sets, s.invalid_stretches), (11, 9, 2));
        let longest = s.longest_invalid.expect("a stretch");
        assert!(longest.cause.starts_with("no frame set for 200 ms"), "{longest:?}");
        assert!((longest.duration_ms - 200.0).abs() < 1e-6 && longest.frame_sets == 0, "{longest:?}");
        let lat = s.latency.expect("latencies");
        assert_eq!((lat.values, lat.max_ms), (11, 30.0));
        assert_eq!(s.values_written, 11);
        assert!(log.summary("b").is_none());
    }
}
