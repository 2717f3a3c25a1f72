//! What the report takes from the specimen tags of a feed's lines once the rig's config says
//! which direction is down and which tags have roles: each tag's lines, views and σ along
//! `world.up` (the QC section), each tag's σ in the first line that gives one (the zero
//! reference of the net deflection) and each line's σ of the net deflection from its role tags.
//!
//! Gathered as the feed is read when the reader is given the rig ([`crate::Feed::read_runs_for`],
//! every route of the report: one pass over the file for the numbers), else by a second read
//! of the feed ([`crate::Feed::for_each_line`]).

use std::collections::BTreeMap;

use tagdeflect_core::feed::FeedTag;
use tagdeflect_core::rig::TagRole;

use crate::error::ReportError;
use crate::feed_reader::Feed;
use crate::report::TestRig;

/// One tag over the feed's lines.
#[derive(Debug, Clone, Default, PartialEq)]
pub(crate) struct TagLines {
    /// Lines that solved it.
    pub lines: usize,
    /// Cameras that saw it, summed over those lines.
    pub views: usize,
    /// Its σ along `world.up` on each line that gives one, mm.
    pub sigma_up_mm: Vec<f64>,
}

/// The tags of a feed (see the module doc).
#[derive(Debug, Clone, Default, PartialEq)]
pub(crate) struct TagStats {
    /// Per tag id.
    pub tags: BTreeMap<u32, TagLines>,
    /// Per tag id, its σ along `world.up` in the first line that gives one, mm.
    pub first_sigma_up_mm: BTreeMap<u32, f64>,
    /// Per line, the σ of its net deflection from its role tags (NaN: a role missing or
    /// without σ); empty when the feed has no tags.
    role_sigma_mm: Vec<f64>,
}

impl TagStats {
    /// `feed`'s tags for `config`: those gathered as it was read for this rig (taken from the
    /// feed: a second call reads again), else read again (nothing to read when no line has tags).
    pub(crate) fn of(feed: &Feed, config: &TestRig) -> Result<TagStats, ReportError> {
        if let Some(s) = feed.take_tag_stats(config) {
            return Ok(s);
        }
        let mut s = TagStats::default();
        if feed.summary.tag_lines.is_empty() {
            return Ok(s);
        }
        // Each list at its size (counted as the feed was read): no spare room doubling them.
        for (&id, &lines) in &feed.summary.tag_lines {
            s.tags.insert(id, TagLines { sigma_up_mm: Vec::with_capacity(lines), ..Default::default() });
        }
        s.role_sigma_mm.reserve_exact(feed.len());
        feed.for_each_line(|_, l| s.fold(&l.tags, config))?;
        Ok(s)
    }

    /// Adds one line's tags.
    pub(crate) fn fold(&mut self, tags: &[FeedTag], config: &TestRig) {
        let up = config.world.up;
        let down_sigma = |s: [f64; 3]| ((up[0] * s[0]).powi(2) + (up[1] * s[1]).powi(2) + (up[2] * s[2]).powi(2)).sqrt();
        for t in tags {
            let e = self.tags.entry(t.id).or_default();
            e.lines += 1;
            e.views += t.views;
            if let Some(sig) = t.sigma_mm {
                let d = down_sigma(sig);
                e.sigma_up_mm.push(d);
                self.first_sigma_up_mm.entry(t.id).or_insert(d);
            }
        }
        self.role_sigma_mm.push(role_sigma(tags, config, &down_sigma).unwrap_or(f64::NAN));
    }

    /// Once every line is folded: no per-line σ when no line had tags (as a read again
    /// gives), the lists without spare room.
    pub(crate) fn finish(&mut self) {
        if self.tags.is_empty() {
            self.role_sigma_mm = Vec::new();
        }
        self.role_sigma_mm.shrink_to_fit();
        for t in self.tags.values_mut() {
            t.sigma_up_mm.shrink_to_fit();
        }
    }

    /// The σ of line `k`'s net deflection from its role tags, `None` when a role tag has no
    /// σ or a role has no tag.
    pub(crate) fn role_sigma(&self, k: usize) -> Option<f64> {
        self.role_sigma_mm.get(k).copied().filter(|s| !s.is_nan())
    }
}

/// σ of a line's net deflection from its role tags, `None` when a role tag has no σ.
fn role_sigma(tags: &[FeedTag], config: &TestRig, down_sigma: &dyn Fn([f64; 3]) -> f64) -> Option<f64> {
    let mut mid = Vec::new();
    let mut sup = Vec::new();
    for t in tags {
        match config.role_of(t.id) {
            Some(TagRole::Midspan) => mid.push(down_sigma(t.sigma_mm?)),
            Some(TagRole::Support) => sup.push(down_sigma(t.sigma_mm?)),
            None => {}
        }
    }
    if mid.is_empty() || sup.is_empty() {
        return None;
    }
    let var = |v: &[f64]| v.iter().map(|s| s * s).sum::<f64>() / (v.len() * v.len()) as f64;
    Some((var(&mid) + var(&sup)).sqrt())
}
