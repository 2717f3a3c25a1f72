//! The end-to-end acknowledgement between an archive and a rig: what the archive holds of
//! a (rig, test), published retained on `<topic>/archive` ([`crate::ACK_SUFFIX`]; how the
//! publisher uses it: `tagdeflect_sinks::mqtt`), and the sets of frame-set numbers both sides
//! keep.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

/// At most this many gaps per run in one acknowledgement; beyond them `high` is lowered to
/// the last gap listed, so the message never claims a line it does not list.
pub const MAX_ACK_GAPS: usize = 1000;

/// A set of frame-set numbers as disjoint, non-adjacent closed ranges.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct SeqRanges {
    /// start → end (inclusive).
    ranges: BTreeMap<u64, u64>,
}

impl SeqRanges {
    /// An empty set.
    pub fn new() -> SeqRanges {
        SeqRanges::default()
    }

    /// True when the set holds nothing.
    pub fn is_empty(&self) -> bool {
        self.ranges.is_empty()
    }

    /// Numbers in the set.
    pub fn len(&self) -> u64 {
        self.ranges.iter().map(|(a, b)| b - a + 1).sum()
    }

    /// True when `seq` is in the set.
    pub fn contains(&self, seq: u64) -> bool {
        self.ranges.range(..=seq).next_back().is_some_and(|(_, &e)| e >= seq)
    }

    /// Smallest and largest number.
    pub fn bounds(&self) -> Option<(u64, u64)> {
        Some((*self.ranges.keys().next()?, *self.ranges.values().next_back()?))
    }

    /// Adds `a..=b`.
    pub fn insert_range(&mut self, a: u64, b: u64) {
        if a > b {
            return;
        }
        let (mut a, mut b) = (a, b);
        // Merge with a range that starts before and touches.
        if let Some((&s, &e)) = self.ranges.range(..=a).next_back() {
            if e.saturating_add(1) >= a {
                a = s;
                b = b.max(e);
                self.ranges.remove(&s);
            }
        }
        // Swallow ranges that start inside or just after.
        loop {
            let next = self.ranges.range(a..).next().map(|(&s, &e)| (s, e));
            match next {
                Some((s, e)) if s <= b.saturating_add(1) => {
                    b = b.max(e);
                    self.ranges.remove(&s);
                }
                _ => break,
            }
        }
        self.ranges.insert(a, b);
    }

    /// Adds one number.
    pub fn insert(&mut self, seq: u64) {
        self.insert_range(seq, seq);
    }

    /// Removes `a..=b`.
    pub fn remove_range(&mut self, a: u64, b: u64) {
        if a > b {
            return;
        }
        // Ends grow with starts: walking back from `b`, the first range ending before `a` ends the hits.
        let hit: Vec<(u64, u64)> = self.ranges.range(..=b).rev().take_while(|(_, &e)| e >= a).map(|(&s, &e)| (s, e)).collect();
        for (s, e) in hit {
            self.ranges.remove(&s);
            if s < a {
                self.ranges.insert(s, a - 1);
            }
            if e > b {
                self.ranges.insert(b + 1, e);
            }
        }
    }

    /// Removes one number.
    pub fn remove(&mut self, seq: u64) {
        self.remove_range(seq, seq);
    }

    /// The ranges in order.
    pub fn iter(&self) -> impl Iterator<Item = (u64, u64)> + '_ {
        self.ranges.iter().map(|(&a, &b)| (a, b))
    }

    /// The smallest number, removed.
    pub fn pop_first(&mut self) -> Option<u64> {
        let (&s, &e) = self.ranges.iter().next()?;
        self.ranges.remove(&s);
        if e > s {
            self.ranges.insert(s + 1, e);
        }
        Some(s)
    }

    /// The first `n` numbers (not removed).
    pub fn first_n(&self, n: usize) -> Vec<u64> {
        let mut out = Vec::new();
        for (a, b) in self.iter() {
            let mut s = a;
            while s <= b && out.len() < n {
                out.push(s);
                s += 1;
            }
            if out.len() >= n {
                break;
            }
        }
        out
    }

    /// The gaps of `0..=high` that the set does not hold (seqs count from 0).
    pub fn gaps_up_to(&self, high: u64) -> Vec<(u64, u64)> {
        let mut out = Vec::new();
        let mut next = 0u64;
        for (a, b) in self.iter() {
            if a > high {
                break;
            }
            if a > next {
                out.push((next, a - 1));
            }
            next = b.saturating_add(1);
        }
        if next <= high {
            out.push((next, high));
        }
        out
    }
}

/// What an archive holds of one run of a (rig, test).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RunHeld {
    /// The run's number in the archive (1 for the first run met with this test id).
    pub run: i32,
    /// Smallest and largest `t_ns` held.
    pub first_t_ns: i64,
    /// Largest `t_ns` held.
    pub last_t_ns: i64,
    /// Largest seq covered by this message: every seq in `0..=high` outside `gaps` is held.
    pub high: u64,
    /// Missing seqs below `high`, as inclusive ranges.
    pub gaps: Vec<(u64, u64)>,
    /// Lines held in all (also above a lowered `high`).
    pub lines: u64,
}

impl RunHeld {
    /// The seqs this message says are held.
    pub fn held(&self) -> SeqRanges {
        let mut s = SeqRanges::new();
        s.insert_range(0, self.high);
        for &(a, b) in &self.gaps {
            s.remove_range(a, b);
        }
        s
    }

    /// The acknowledgement of a run from the seqs held.
    pub fn from_held(run: i32, first_t_ns: i64, last_t_ns: i64, held: &SeqRanges) -> Option<RunHeld> {
        let (_, mut high) = held.bounds()?;
        let mut gaps = held.gaps_up_to(high);
        if gaps.len() > MAX_ACK_GAPS {
            gaps.truncate(MAX_ACK_GAPS);
            // Claim nothing past the last gap listed.
            high = gaps.last().map_or(0, |g| g.1);
        }
        Some(RunHeld { run, first_t_ns, last_t_ns, high, gaps, lines: held.len() })
    }
}

/// The retained message an archive publishes on `<topic>/archive` after each commit that
/// touched the (rig, test): what it holds of every run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ArchiveAck {
    /// The rig (from the topic).
    pub rig: String,
    /// The test id as published.
    pub test: String,
    /// Every run of the test the archive holds lines of.
    pub runs: Vec<RunHeld>,
    /// When the archive wrote this (its clock, ns since the epoch).
    pub at_ns: i64,
}

impl ArchiveAck {
    /// The run a rig whose first line has `first_t_ns` is: the one with lines at or after
    /// it (earlier runs of the same test id ended before this one started).
    pub fn run_of(&self, first_t_ns: i64) -> Option<&RunHeld> {
        self.runs.iter().filter(|r| r.last_t_ns >= first_t_ns).max_by_key(|r| r.lines)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ranges_merge_split_and_report_gaps() {
        let mut s = SeqRanges::new();
        for x in [5, 3, 4, 10, 11, 0, 7] {
            s.insert(x);
        }
        assert_eq!(s.iter().collect::<Vec<_>>(), vec![(0, 0), (3, 5), (7, 7), (10, 11)]);
        assert_eq!(s.len(), 7);
        assert!(s.contains(4) && !s.contains(6) && s.contains(11) && !s.contains(12));
        assert_eq!(s.gaps_up_to(11), vec![(1, 2), (6, 6), (8, 9)]);
        s.insert_range(1, 9);
        assert_eq!(s.iter().collect::<Vec<_>>(), vec![(0, 11)]);
        s.remove_range(3, 4);
        s.remove(11);
        assert_eq!(s.iter().collect::<Vec<_>>(), vec![(0, 2), (5, 10)]);
        assert_eq!(s.pop_first(), Some(0));
        assert_eq!(s.first_n(4), vec![1, 2, 5, 6]);
        s.remove_range(0, 100);
        assert!(s.is_empty());
    }

    #[test]
    fn an_acknowledgement_round_trips_and_never_claims_more_than_it_lists() {
        let mut held = SeqRanges::new();
        held.insert_range(2, 5);
        held.insert_range(9, 20);
        let r = RunHeld::from_held(1, 10, 20, &held).unwrap();
        assert_eq!(r.high, 20);
        assert_eq!(r.gaps, vec![(0, 1), (6, 8)]);
        assert_eq!(r.held(), held);
        let mut many = SeqRanges::new();
        for i in 0..(MAX_ACK_GAPS as u64 + 10) {
            many.insert(2 * i + 1);
        }
        let r = RunHeld::from_held(1, 0, 1, &many).unwrap();
        assert_eq!(r.gaps.len(), MAX_ACK_GAPS);
        let claimed = r.held();
        assert!(claimed.iter().all(|(a, b)| (a..=b).all(|x| many.contains(x))));
        let ack = ArchiveAck { rig: "r".into(), test: "t".into(), runs: vec![r], at_ns: 5 };
        let back: ArchiveAck = serde_json::from_str(&serde_json::to_string(&ack).unwrap()).unwrap();
        assert_eq!(back, ack);
        assert!(back.run_of(2).is_none() && back.run_of(1).is_some());
    }
}
