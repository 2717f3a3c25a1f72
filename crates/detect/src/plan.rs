//! Region-of-interest planning: what to look for in the next frame of one camera.
//!
//! Once tags have been found, each is expected where its last refined corners, moved by
//! its image velocity, put it (`PlannedTag::predicted`). The measurement first tries to
//! *confirm* it there without any search (sub-pixel refinement from the prediction, then
//! the tag's code read back: see `detect::confirm`); only a tag that cannot be confirmed is
//! searched for with the AprilTag library in its *window*, the predicted box grown by a
//! margin that scales with the tag's size in the image and its motion (decimated for big
//! tags; a tag seen last time and missed there is searched again in its window at the
//! configured resolution: `PlannedTag::expected`, see `detect::camera_detector`).
//!
//! - **Specimen tags** are looked for every frame.
//! - **Background tags** only serve to catch a bump of the camera once it is posed (the pose
//!   is held, see `solve::held_pose`), so after a settling period only a rotating subset of
//!   `BACKGROUND_TAGS_PER_FRAME` of them is looked for per frame; the tracker's bump
//!   statistic is a median over the corners seen, so a few tags suffice to catch a bump in
//!   the same frame set. When the background tags seen have shifted in the image (a bump),
//!   all of them are looked for again for `SETTLE_FRAMES` frames so the re-posing
//!   averages every tag. A background tag missing from its window (occluded, blurred) is
//!   searched again at once, then after 1, 3, 7 … frames (up to 2^`MAX_WAIT_DOUBLINGS`):
//!   the camera keeps its held pose on the tags left, and a tag hidden for long costs a
//!   few window searches, not one a frame.
//! - **Sweep**: new or re-appearing tags are found by a search of the whole frame once per
//!   `full_search_interval_s`, spread over the frames in overlapping *tiles* (the overlap
//!   is larger than the biggest tag, so each tag lies wholly inside some tile), with the
//!   tags already found blanked out ([`masked_tile`]). Tiles are searched with quad
//!   decimation `SEARCH_DECIMATE` when the tags are big enough
//!   (`MIN_EXTENT_TO_DECIMATE_SWEEP`; corners are refined at full resolution), and the
//!   cameras' tiles are staggered (`with_phase`) so no frame set stalls.
//! - **Full frame** (full resolution) at the start, when the image size changes and
//!   whenever no tag is tracked; when a tracked tag is lost the next frame sweeps the whole
//!   frame at once (decimated), then the tag is left to the periodic sweep.
//!
//! - **Background tags lost or jumped** (the camera moved): a background tag searched for
//!   and not seen, or the background tags' bump statistic above its threshold, makes the
//!   measurement search the *same frame* whole at the configured resolution before the
//!   camera is posed from it (see `detect::camera_detector` and `estimate::measure`); the
//!   frame is still at hand then, so it is never deferred to the next one. The tags found
//!   there replace their sightings ([`RoiPlanner::refound`]): followed from where they are
//!   now, with no velocity (a jump is not a motion to extrapolate).
//!
//! Corners are identical in quality whichever way a tag was found: windows are searched on
//! a view into the same frame with corners mapped back (see `detect::apriltag`), and every
//! tag — confirmed, found in a window or in a tile — gets the same sub-pixel refinement on
//! the full frame (see `detect::camera_detector`).

use nalgebra::{Point2, Vector2};
use std::collections::HashMap;

use super::{Detection, Rect};
use tagdeflect_core::camera::CameraIntrinsics;
use tagdeflect_core::frame::GrayImage;
use tagdeflect_core::tags::TagFamily;

mod rects;
use rects::{bounds, centre, clip};
pub use rects::{masked_tile, merge_rects, sweep_tiles};

/// Background tags searched per frame once the camera has settled (a rotating subset).
const BACKGROUND_TAGS_PER_FRAME: usize = 3;
/// Frames during which every background tag is searched after the first full-frame search
/// or a suspected bump (covers the pose tracker's averaging of the corners).
const SETTLE_FRAMES: u32 = 12;
/// Quad decimation of the windows and the sweep's tiles when every tracked tag is at least
/// [`MIN_EXTENT_TO_DECIMATE`] px across: the library fits the quads on the full image and
/// the corners are refined at full resolution, so only the quad search (the costliest part
/// on a textured specimen) runs on fewer pixels.
const SEARCH_DECIMATE: f32 = 2.0;
/// Smallest tag extent (px, bounding box) for which window searches are decimated: a tag
/// that could not be confirmed is often blurred or partly hidden, and the window search is
/// small, so it keeps full resolution for tags below this.
const MIN_EXTENT_TO_DECIMATE: f64 = 36.0;
/// Smallest tag extent (px) for which the sweep (tiles, and the whole frame after a lost
/// tag) is decimated. The sweep only looks for tags not followed yet, it is most of the
/// searching cost in steady state, and the decimated start-up search finds 28-px tags as
/// the full-resolution one does (`bench` on clean and noisy 3 × 1080p scenes: the same tags
/// and the same accuracy); below 24 px (12 px at half resolution, 1.5-px border bits) the
/// sweep keeps full resolution.
const MIN_EXTENT_TO_DECIMATE_SWEEP: f64 = 24.0;
/// A missing background tag's wait between window searches doubles up to 2^this frames
/// (32: about a second at 30 fps).
const MAX_WAIT_DOUBLINGS: u32 = 5;
/// Median shift (px) of the background tags seen, against their last positions, taken as
/// a possible bump (the pose tracker's default bump floor).
const BACKGROUND_SHIFT_PX: f64 = 1.0;

/// Where a tag was last seen in this camera and how it moved.
#[derive(Debug, Clone)]
struct Sighting {
    corners: [Point2<f64>; 4],
    velocity: Vector2<f64>,
    t_ns: i64,
    /// Searched frames since last seen.
    missed: u32,
    /// A background tag (searched in rotation once settled).
    background: bool,
    /// Its window was searched in the current frame.
    searched: bool,
    /// Frames to skip before a missing background tag's window is searched again.
    wait: u32,
}

/// A tracked tag expected in the next frame.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct PlannedTag {
    /// Its family.
    pub family: TagFamily,
    /// Its id.
    pub id: u32,
    /// Its corners as predicted (last corners moved by the tag's image velocity), SPEC order.
    pub predicted: [Point2<f64>; 4],
    /// The window to search with the detector if the prediction cannot be confirmed.
    pub window: Rect,
    /// The tag was seen the last time it was looked for: if the (decimated, contrast
    /// filtered) search of its window misses it, the window is searched again at the
    /// configured resolution in the same frame (a tag that was already missing is not).
    pub expected: bool,
}

/// What to search in one frame of one camera.
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum Plan {
    /// The whole frame, at the detector's configured resolution.
    FullFrame,
    /// Tracked tags (each confirmed at its predicted place, else searched in its window)
    /// plus sweep tiles (possibly none this frame).
    Windows {
        /// Quad decimation to search windows with ([`SEARCH_DECIMATE`] for tags of at
        /// least [`MIN_EXTENT_TO_DECIMATE`] px, else 1: the configured resolution).
        decimate: f32,
        /// Quad decimation of the sweep's tiles and of the whole-frame sweep
        /// ([`SEARCH_DECIMATE`] for tags of at least [`MIN_EXTENT_TO_DECIMATE_SWEEP`] px).
        sweep_decimate: f32,
        /// The tracked tags to look for.
        tags: Vec<PlannedTag>,
        /// Tiles of the periodic sweep (or the whole frame after a lost tag).
        sweep: Vec<Rect>,
        /// `sweep` is the whole frame at once (after a lost tag), not the periodic tiles.
        whole_frame: bool,
    },
}

/// What one frame's observation told about the camera's background tags.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct BackgroundCheck {
    /// A followed background tag was searched for and not seen (first miss).
    pub lost: bool,
    /// Background tags seen in the frame.
    pub seen: usize,
    /// Followed background tags searched for in the frame and not seen (first misses and
    /// tags already missing).
    pub missing: usize,
    /// Median shift (px) of the background tags seen against their predicted places.
    pub shift_px: Option<f64>,
    /// Followed tags of either role searched for and not seen for the first time (a camera
    /// not posed yet that lost tags may have moved: see `estimate::measure::pose`).
    pub followed_lost: usize,
}

/// Plans the searches of one camera.
#[derive(Debug)]
pub(crate) struct RoiPlanner {
    enabled: bool,
    width: u32,
    height: u32,
    interval_ns: i64,
    sightings: HashMap<(TagFamily, u32), Sighting>,
    full_requested: bool,
    sweep_all_requested: bool,
    frame_dt_ns: i64,
    last_t_ns: Option<i64>,
    /// Frames planned since the last full-frame search.
    frame_index: u64,
    /// Offset of this camera's sweep schedule (frames).
    phase: u64,
    /// Frames left during which every background tag is searched.
    settle: u32,
    /// Round-robin position among the background tags.
    bg_cursor: usize,
}

impl RoiPlanner {
    /// A planner for one camera; `enabled = false` always asks for full-frame searches.
    pub fn new(intrinsics: CameraIntrinsics, enabled: bool, full_search_interval_s: f64) -> Self {
        Self {
            enabled,
            width: intrinsics.width,
            height: intrinsics.height,
            interval_ns: (full_search_interval_s.max(0.0) * 1e9) as i64,
            sightings: HashMap::new(),
            full_requested: true,
            sweep_all_requested: false,
            frame_dt_ns: 0,
            last_t_ns: None,
            frame_index: 0,
            phase: 0,
            settle: SETTLE_FRAMES,
            bg_cursor: 0,
        }
    }

    /// Offsets this camera's sweep schedule by `phase` frames (e.g. the camera's index), so
    /// the cameras of a rig do not search their sweep tiles in the same frame set.
    pub fn with_phase(mut self, phase: u32) -> Self {
        self.phase = phase as u64;
        self
    }

    /// The searches to run in the frame at `t_ns`.
    pub fn plan(&mut self, t_ns: i64, image: &GrayImage) -> Plan {
        if let Some(last) = self.last_t_ns {
            let dt = t_ns - last;
            if dt > 0 {
                self.frame_dt_ns = if self.frame_dt_ns == 0 { dt } else { (self.frame_dt_ns * 7 + dt) / 8 };
            }
        }
        self.last_t_ns = Some(t_ns);
        if image.width != self.width || image.height != self.height {
            self.width = image.width;
            self.height = image.height;
            self.full_requested = true;
        }
        for tr in self.sightings.values_mut() {
            tr.searched = false;
        }
        if !self.enabled || self.full_requested || self.sightings.is_empty() {
            self.full_requested = false;
            self.sweep_all_requested = false;
            self.frame_index = 0;
            self.settle = SETTLE_FRAMES;
            for tr in self.sightings.values_mut() {
                tr.searched = true;
            }
            return Plan::FullFrame;
        }
        self.frame_index += 1;

        // Which sightings get a window: every specimen tag, and the background tags in rotation.
        let mut bg_keys: Vec<(TagFamily, u32)> = self.sightings.iter().filter(|(_, t)| t.background).map(|(k, _)| *k).collect();
        bg_keys.sort_by_key(|(f, id)| (f.name(), *id));
        let all_bg = self.settle > 0 || bg_keys.len() <= BACKGROUND_TAGS_PER_FRAME;
        self.settle = self.settle.saturating_sub(1);
        let mut chosen: Vec<(TagFamily, u32)> = Vec::new();
        if all_bg {
            chosen.extend(&bg_keys);
        } else {
            for i in 0..BACKGROUND_TAGS_PER_FRAME {
                chosen.push(bg_keys[(self.bg_cursor + i) % bg_keys.len()]);
            }
            self.bg_cursor = (self.bg_cursor + BACKGROUND_TAGS_PER_FRAME) % bg_keys.len();
            // A background tag missing from its last search is searched again (when its wait is over).
            chosen.extend(bg_keys.iter().filter(|k| self.sightings[*k].missed > 0));
        }
        // A background tag missing from its searches waits 0, 1, 3, 7 … frames before the
        // next (see `observe`): the camera keeps its held pose on the tags left, and a tag
        // occluded for long costs a few window searches, not one a frame.
        chosen.retain(|k| self.sightings[k].wait == 0);
        for tr in self.sightings.values_mut().filter(|t| t.background && t.wait > 0) {
            tr.wait -= 1;
        }
        let mut tags: Vec<PlannedTag> = Vec::new();
        let mut max_extent: f64 = 0.0;
        let mut min_extent: f64 = f64::INFINITY;
        let (w, h) = (self.width, self.height);
        for (key, tr) in self.sightings.iter_mut() {
            let (lo, hi) = bounds(&tr.corners);
            max_extent = max_extent.max((hi - lo).max());
            min_extent = min_extent.min((hi - lo).max());
            if tr.background && !chosen.contains(key) {
                continue;
            }
            tr.searched = true;
            let dt = (t_ns - tr.t_ns) as f64 * 1e-9;
            let shift = tr.velocity * dt;
            let (lo, hi) = (lo + shift, hi + shift);
            let extent = (hi - lo).max();
            // Room for the white border and quiet zone (the detector thresholds in 4 px
            // tiles), the motion, and a tag missed a while.
            let margin = 0.3 * extent + 10.0 + 2.0 * shift.norm() + 0.25 * extent * tr.missed as f64;
            if let Some(window) = clip(w, h, lo.x - margin, lo.y - margin, hi.x + margin, hi.y + margin) {
                let predicted = tr.corners.map(|c| c + shift);
                tags.push(PlannedTag { family: key.0, id: key.1, predicted, window, expected: tr.missed == 0 });
            }
        }

        // The sweep: the tiles of the whole frame once per interval, staggered by phase.
        let overlap = 1.3 * max_extent + 16.0;
        let tiles = sweep_tiles(w, h, overlap);
        let whole_frame = self.sweep_all_requested;
        let sweep = if self.sweep_all_requested {
            self.sweep_all_requested = false;
            clip(w, h, 0.0, 0.0, w as f64, h as f64).into_iter().collect()
        } else {
            let frames_per_sweep = if self.frame_dt_ns > 0 { (self.interval_ns / self.frame_dt_ns).max(1) as u64 } else { 8 };
            let n = tiles.len() as u64;
            // This frame's share of the cycle: tiles i·n/F .. (i+1)·n/F.
            let i = (self.frame_index + self.phase) % frames_per_sweep;
            let (first, end) = ((i * n / frames_per_sweep) as usize, ((i + 1) * n / frames_per_sweep) as usize);
            let out: Vec<Rect> = tiles.get(first..end).map(|t| t.to_vec()).unwrap_or_default();
            out
        };
        let decimate = if min_extent >= MIN_EXTENT_TO_DECIMATE { SEARCH_DECIMATE } else { 1.0 };
        let sweep_decimate = if min_extent >= MIN_EXTENT_TO_DECIMATE_SWEEP { SEARCH_DECIMATE } else { 1.0 };
        tags.sort_by_key(|t| (t.family.name(), t.id));
        Plan::Windows { decimate, sweep_decimate, tags, sweep, whole_frame }
    }

    /// Starts following tags found by a search of an earlier frame (at `t_ns`) that ran
    /// while later frames were planned: tags already followed are left as they are, the
    /// others are looked for from the next plan on, where they were found.
    pub fn add_found(&mut self, t_ns: i64, background: &[Detection], specimen: &[Detection]) {
        for (d, is_bg) in background.iter().map(|d| (d, true)).chain(specimen.iter().map(|d| (d, false))) {
            self.sightings.entry((d.family, d.id)).or_insert(Sighting {
                corners: d.corners,
                velocity: Vector2::zeros(),
                t_ns,
                missed: 0,
                background: is_bg,
                searched: false,
                wait: 0,
            });
        }
    }

    /// Takes the tags of a whole-frame search of the frame at `t_ns` that was already
    /// observed (the camera moved: see the module docs): each tag found is followed from
    /// where it is now with no velocity; tags not found keep their state (their miss is
    /// counted); every background tag is searched again for the settling period.
    pub fn refound(&mut self, t_ns: i64, background: &[Detection], specimen: &[Detection]) {
        for (d, is_bg) in background.iter().map(|d| (d, true)).chain(specimen.iter().map(|d| (d, false))) {
            self.sightings.insert(
                (d.family, d.id),
                Sighting { corners: d.corners, velocity: Vector2::zeros(), t_ns, missed: 0, background: is_bg, searched: false, wait: 0 },
            );
        }
        self.settle = SETTLE_FRAMES;
        if !background.is_empty() || !specimen.is_empty() {
            // The whole frame was just searched: no decimated sweep of it next frame.
            self.sweep_all_requested = false;
        }
    }

    /// True when no tag is followed.
    pub fn is_empty(&self) -> bool {
        self.sightings.is_empty()
    }

    /// Records what the frame at `t_ns` showed, for the next plan. A tag searched for but
    /// not seen triggers one decimated sweep of the whole frame in the next frame; a tag
    /// missing for a second of frames is dropped from tracking (the sweep picks it up
    /// again). Background tags whose positions shifted (a bump) are all searched again for
    /// a while.
    pub fn observe(&mut self, t_ns: i64, background: &[Detection], specimen: &[Detection]) -> BackgroundCheck {
        let mut seen = std::collections::HashSet::new();
        let mut bg_shifts = Vec::new();
        for (d, is_bg) in background.iter().map(|d| (d, true)).chain(specimen.iter().map(|d| (d, false))) {
            let key = (d.family, d.id);
            seen.insert(key);
            let c_new = centre(&d.corners);
            match self.sightings.get_mut(&key) {
                Some(tr) => {
                    let dt = (t_ns - tr.t_ns) as f64 * 1e-9;
                    if is_bg {
                        bg_shifts.push((c_new - (centre(&tr.corners) + tr.velocity * dt.max(0.0))).norm());
                    }
                    if dt > 0.0 {
                        let v = (c_new - centre(&tr.corners)) / dt;
                        tr.velocity = if tr.missed == 0 { tr.velocity * 0.5 + v * 0.5 } else { v };
                    }
                    tr.corners = d.corners;
                    tr.t_ns = t_ns;
                    tr.missed = 0;
                    tr.wait = 0;
                    tr.background = is_bg;
                }
                None => {
                    self.sightings.insert(
                        key,
                        Sighting {
                            corners: d.corners,
                            velocity: Vector2::zeros(),
                            t_ns,
                            missed: 0,
                            background: is_bg,
                            searched: false,
                            wait: 0,
                        },
                    );
                }
            }
        }
        let mut check = BackgroundCheck { seen: background.len(), ..BackgroundCheck::default() };
        if !bg_shifts.is_empty() {
            bg_shifts.sort_by(f64::total_cmp);
            let shift = bg_shifts[bg_shifts.len() / 2];
            check.shift_px = Some(shift);
            if shift > BACKGROUND_SHIFT_PX {
                self.settle = SETTLE_FRAMES;
            }
        }
        let max_missed = if self.frame_dt_ns > 0 { (self.interval_ns / self.frame_dt_ns).clamp(2, 60) as u32 } else { 10 };
        let mut lost_now = false;
        self.sightings.retain(|k, tr| {
            if seen.contains(k) || !tr.searched {
                return true;
            }
            tr.missed += 1;
            if tr.background {
                tr.wait = (1u32 << (tr.missed - 1).min(MAX_WAIT_DOUBLINGS)) - 1;
            }
            check.missing += tr.background as usize;
            if tr.missed == 1 {
                lost_now = true;
                check.lost |= tr.background;
                check.followed_lost += 1;
            }
            tr.missed <= max_missed
        });
        if lost_now {
            self.sweep_all_requested = true;
        }
        check
    }
}

#[cfg(test)]
mod tests;
