//! Stage 3, solve tags: each specimen tag's pose over all its views from the posed cameras
//! ([`solve_tag`]), warm-started from its last solution, weighted by the pooled corner noise.

use std::collections::BTreeMap;

use super::camera::RigCamera;
use super::detect::Detected;
use super::Measurement;
use crate::{solve_tag, TagSolution, TagView};

/// One specimen tag's views in a frame set: `views[i]` was seen by camera `cameras[i]`.
#[derive(Default)]
pub(super) struct TagViews {
    /// The views, from posed cameras only.
    pub(super) views: Vec<TagView>,
    /// The camera index of each view.
    pub(super) cameras: Vec<usize>,
}

/// One specimen tag solved over its views.
pub(super) struct SolvedTag {
    /// Specimen tag id.
    pub(super) id: u32,
    /// The views it was solved from.
    pub(super) views: TagViews,
    /// The solve.
    pub(super) solution: TagSolution,
}

/// What the solve stage made of a frame set's specimen tags.
pub(super) struct SolvedTags {
    /// The tags solved, by id.
    pub(super) tags: Vec<SolvedTag>,
    /// The pooled corner noise the solves were weighted with (before this set's), px.
    pub(super) pooled_sigma_px: Option<f64>,
    /// RMS reprojection error over all the solved views, px (to 0.001 px).
    pub(super) reproj_px: Option<f64>,
}

impl Measurement {
    /// Solves every specimen tag seen by a posed camera; views rejected as outliers are
    /// counted per camera, every solution feeds the pooled corner noise.
    pub(super) fn solve_tags(&mut self, seq: u64, detected: &Detected) -> SolvedTags {
        let by_tag = tag_views(&self.cameras, detected);
        let pooled = self.noise.sigma_px();
        let mut tags = Vec::with_capacity(by_tag.len());
        let (mut sq_sum, mut sq_n) = (0.0, 0.0);
        for (id, views) in by_tag {
            let warm = self.tags.get(&id).map(|t| t.pose);
            match solve_tag(&views.views, self.config.specimen.size_mm, warm.as_ref(), pooled) {
                Ok(solution) => {
                    self.note_rejected_views(id, seq, &views, &solution);
                    self.noise.add_solution(&solution);
                    let n_res = 8.0 * solution.views as f64;
                    sq_sum += solution.rms_px * solution.rms_px * n_res;
                    sq_n += n_res;
                    tags.push(SolvedTag { id, views, solution });
                }
                Err(e) => tracing::debug!(tag = id, seq, "tag not solved: {e}"),
            }
        }
        let reproj_px = if sq_n > 0.0 { Some(((sq_sum / sq_n).sqrt() * 1e3).round() / 1e3) } else { None };
        SolvedTags { tags, pooled_sigma_px: pooled, reproj_px }
    }

    /// Counts (per camera) and logs the views a solve rejected as outliers.
    fn note_rejected_views(&mut self, id: u32, seq: u64, views: &TagViews, solution: &TagSolution) {
        self.stats.rejected_views += solution.rejected_views.len() as u64;
        for r in &solution.rejected_views {
            let ci = views.cameras[*r];
            self.rejected_by_camera[ci] += 1;
            tracing::debug!(tag = id, camera = %self.cameras[ci].name, seq, "specimen tag view rejected as an outlier (its corners disagree with the other views)");
        }
    }
}

/// Each specimen tag's views from the cameras posed (cameras in detection order).
fn tag_views(cameras: &[RigCamera], detected: &Detected) -> BTreeMap<u32, TagViews> {
    let mut by_tag: BTreeMap<u32, TagViews> = BTreeMap::new();
    for (ci, d) in &detected.cameras {
        for det in &d.specimen {
            let Some(view) = cameras[*ci].view(det.corners) else { break };
            let entry = by_tag.entry(det.id).or_default();
            entry.views.push(view);
            entry.cameras.push(*ci);
        }
    }
    by_tag
}
