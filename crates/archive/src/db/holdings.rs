//! What the archive holds of every test it has written to: runs and held seqs (for the gap
//! log and the acknowledgement the rigs read), read from the database and kept up to date.

use tagdeflect_wire::{RunHeld, SeqRanges};

/// What the archive holds of one run of a test.
#[derive(Debug, Clone, PartialEq)]
pub struct RunState {
    /// The run's number (1, 2, ... in the order met).
    pub run: i32,
    /// Smallest `t_ns` held.
    pub min_t: i64,
    /// Largest `t_ns` held.
    pub max_t: i64,
    /// The seqs held.
    pub held: SeqRanges,
}

/// What the archive holds of one test: its runs.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Holdings {
    /// The runs, by number.
    pub runs: Vec<RunState>,
}

impl Holdings {
    /// The run a line belongs to (see migrations/0002): the run whose time span holds its
    /// `t_ns`; else the run just after it in time if the seq comes before all of that run's,
    /// or the run just before it if the seq comes after all of that run's; else a new run
    /// (a test id used again, a run restarted). Returns the run and whether it is new.
    pub fn assign(&mut self, seq: u64, t: i64) -> (i32, bool) {
        let idx = if let Some(i) = self.runs.iter().position(|r| r.min_t <= t && t <= r.max_t) {
            Some(i)
        } else {
            let next = self.runs.iter().enumerate().filter(|(_, r)| r.min_t > t).min_by_key(|(_, r)| r.min_t).map(|(i, _)| i);
            let prev = self.runs.iter().enumerate().filter(|(_, r)| r.max_t < t).max_by_key(|(_, r)| r.max_t).map(|(i, _)| i);
            let fits_next = next.filter(|&i| self.runs[i].held.bounds().is_none_or(|(lo, _)| seq < lo));
            let fits_prev = prev.filter(|&i| self.runs[i].held.bounds().is_none_or(|(_, hi)| seq > hi));
            fits_next.or(fits_prev)
        };
        match idx {
            Some(i) => {
                let r = &mut self.runs[i];
                r.min_t = r.min_t.min(t);
                r.max_t = r.max_t.max(t);
                r.held.insert(seq);
                (r.run, false)
            }
            None => (self.new_run(seq, t), true),
        }
    }

    /// Starts a new run with one line.
    pub fn new_run(&mut self, seq: u64, t: i64) -> i32 {
        let run = self.runs.iter().map(|r| r.run).max().unwrap_or(0) + 1;
        let mut held = SeqRanges::new();
        held.insert(seq);
        self.runs.push(RunState { run, min_t: t, max_t: t, held });
        run
    }

    /// The run with this number.
    pub fn run(&self, run: i32) -> Option<&RunState> {
        self.runs.iter().find(|r| r.run == run)
    }

    /// What a rig reads: every run's high water and gaps.
    pub fn ack_runs(&self) -> Vec<RunHeld> {
        self.runs.iter().filter_map(|r| RunHeld::from_held(r.run, r.min_t, r.max_t, &r.held)).collect()
    }

    /// The missing seqs of a run below its high water.
    pub fn missing(&self, run: i32) -> SeqRanges {
        let mut m = SeqRanges::new();
        if let Some(r) = self.run(run) {
            if let Some((_, hi)) = r.held.bounds() {
                for (a, b) in r.held.gaps_up_to(hi) {
                    m.insert_range(a, b);
                }
            }
        }
        m
    }
}

/// The held seqs of a test as islands, per run.
const HOLDINGS_SQL: &str = r#"
SELECT run, min(seq), max(seq), min(t_ns), max(t_ns)
FROM (SELECT run, seq, t_ns, seq - row_number() OVER (PARTITION BY run ORDER BY seq) AS grp
      FROM frame_sets WHERE test_id = $1) s
GROUP BY run, grp ORDER BY run, 2
"#;

/// Reads what is held of a test.
pub(super) async fn load_holdings(tx: &tokio_postgres::Transaction<'_>, test_id: i64) -> Result<Holdings, tokio_postgres::Error> {
    let mut h = Holdings::default();
    for r in tx.query(HOLDINGS_SQL, &[&test_id]).await? {
        let (run, lo, hi, t0, t1): (i32, i64, i64, i64, i64) = (r.get(0), r.get(1), r.get(2), r.get(3), r.get(4));
        match h.runs.iter_mut().find(|x| x.run == run) {
            Some(x) => {
                x.held.insert_range(lo as u64, hi as u64);
                x.min_t = x.min_t.min(t0);
                x.max_t = x.max_t.max(t1);
            }
            None => {
                let mut held = SeqRanges::new();
                held.insert_range(lo as u64, hi as u64);
                h.runs.push(RunState { run, min_t: t0, max_t: t1, held });
            }
        }
    }
    Ok(h)
}

/// Logs the gaps (missing seqs below a run's high water) that opened and those filled.
pub(super) fn log_gaps(rig: &str, test: &str, before: &Holdings, after: &Holdings) {
    let mut logged = 0;
    for r in &after.runs {
        let was = before.missing(r.run);
        let now = after.missing(r.run);
        let mut opened = now.clone();
        for (a, b) in was.iter() {
            opened.remove_range(a, b);
        }
        let mut filled = was.clone();
        for (a, b) in now.iter() {
            filled.remove_range(a, b);
        }
        for (a, b) in opened.iter() {
            if logged < 20 {
                tracing::warn!(
                    rig,
                    test,
                    run = r.run,
                    first = a,
                    last = b,
                    "archive: gap opened: rig {rig} test {test} run {} lacks seq {a}..={b} ({} lines)",
                    r.run,
                    b - a + 1
                );
            }
            logged += 1;
        }
        for (a, b) in filled.iter() {
            if logged < 20 {
                tracing::info!(
                    rig,
                    test,
                    run = r.run,
                    first = a,
                    last = b,
                    "archive: gap filled: rig {rig} test {test} run {} seq {a}..={b} ({} lines)",
                    r.run,
                    b - a + 1
                );
            }
            logged += 1;
        }
    }
    if logged > 20 {
        tracing::info!(rig, test, "archive: {} more gap changes not logged", logged - 20);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lines_join_their_run_and_a_seq_again_later_starts_a_new_one() {
        let mut h = Holdings::default();
        // Run 1: seq 0..=9 at t 100..=109, seq 5 arriving late.
        for s in (0..10).filter(|s| *s != 5) {
            assert_eq!(h.assign(s, 100 + s as i64), (1, s == 0));
        }
        assert_eq!(h.missing(1).iter().collect::<Vec<_>>(), vec![(5, 5)]);
        assert_eq!(h.assign(5, 105), (1, false), "a late line inside the run's span");
        assert!(h.missing(1).is_empty());
        assert_eq!(h.assign(3, 103), (1, false), "a redelivery");
        // A restart: seq 0 again, later.
        assert_eq!(h.assign(0, 500), (2, true));
        assert_eq!(h.assign(1, 501), (2, false));
        // A trailing line of run 1 that arrives now still fits run 1 (before run 2 in time).
        assert_eq!(h.assign(10, 110), (1, false));
        // Run 2's line that arrives after a later one of it: before run 2's span in time
        // and seq, after run 1's span but not after all of run 1's seqs: run 2.
        let mut g = Holdings::default();
        for s in 0..10 {
            g.assign(s, 100 + s as i64);
        }
        assert_eq!(g.assign(4, 504), (2, true));
        assert_eq!(g.assign(2, 502), (2, false));
        assert_eq!(
            g.ack_runs().iter().map(|r| (r.run, r.high, r.gaps.clone())).collect::<Vec<_>>(),
            vec![(1, 9, vec![]), (2, 4, vec![(0, 1), (3, 3)])]
        );
    }
}
