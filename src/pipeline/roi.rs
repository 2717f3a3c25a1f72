//! Region-of-interest planning: which parts of the next frame of one camera to search.
//!
//! Once tags have been found, the next frame is searched only in windows around where
//! each tag is expected: its last detected corners moved by its image velocity, grown by
//! a margin that scales with the tag's size in the image and its motion. A full-frame
//! search runs
//! - at the start and whenever no tag is tracked;
//! - at once when a tracked tag is lost (once; if it stays lost it is left to the sweep);
//! - as a *sweep*: every frame also searches one horizontal strip of the image, the
//!   strips (with an overlap larger than the biggest tag) covering the whole frame once
//!   per `full_search_interval_s`, so new or re-appearing tags are picked up without a
//!   frame that stalls on a full-frame search.
//!
//! Window corners are identical in quality to full-frame ones: the detector runs on a
//! view into the same frame and maps corners back (see `detect::apriltag`).

use nalgebra::Point2;
use std::collections::HashMap;

use crate::camera::{CameraIntrinsics, Pose};
use crate::detect::{Detection, Rect};
use crate::frame::GrayImage;
use crate::tags::TagFamily;

fn x1(r: &Rect) -> u32 {
    r.x + r.width
}
fn y1(r: &Rect) -> u32 {
    r.y + r.height
}
fn overlaps(a: &Rect, b: &Rect) -> bool {
    a.x < x1(b) && b.x < x1(a) && a.y < y1(b) && b.y < y1(a)
}
fn union(a: &Rect, b: &Rect) -> Rect {
    let (x, y) = (a.x.min(b.x), a.y.min(b.y));
    Rect { x, y, width: x1(a).max(x1(b)) - x, height: y1(a).max(y1(b)) - y }
}

#[derive(Debug, Clone)]
struct Track {
    corners: [Point2<f64>; 4],
    velocity: nalgebra::Vector2<f64>,
    t_ns: i64,
    /// Frames since last seen.
    missed: u32,
}

/// Plans the searches of one camera.
#[derive(Debug)]
pub struct RoiPlanner {
    enabled: bool,
    width: u32,
    height: u32,
    interval_ns: i64,
    tracks: HashMap<(TagFamily, u32), Track>,
    last_full_ns: Option<i64>,
    full_requested: bool,
    frame_dt_ns: i64,
    last_t_ns: Option<i64>,
    sweep_index: u32,
}

impl RoiPlanner {
    /// A planner for one camera; `enabled = false` always asks for full-frame searches.
    pub fn new(intrinsics: CameraIntrinsics, enabled: bool, full_search_interval_s: f64) -> Self {
        Self {
            enabled,
            width: intrinsics.width,
            height: intrinsics.height,
            interval_ns: (full_search_interval_s * 1e9) as i64,
            tracks: HashMap::new(),
            last_full_ns: None,
            full_requested: true,
            frame_dt_ns: 0,
            last_t_ns: None,
            sweep_index: 0,
        }
    }

    /// The windows to search in the frame at `t_ns`, or `None` for a full-frame search.
    pub fn plan(&mut self, t_ns: i64, image: &GrayImage) -> Option<Vec<Rect>> {
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
        if !self.enabled || self.full_requested || self.tracks.is_empty() {
            self.last_full_ns = Some(t_ns);
            self.full_requested = false;
            self.sweep_index = 0;
            return None;
        }
        let mut rects: Vec<Rect> = Vec::new();
        let mut max_extent: f64 = 0.0;
        for tr in self.tracks.values() {
            let dt = (t_ns - tr.t_ns) as f64 * 1e-9;
            let shift = tr.velocity * dt;
            let (mut x0, mut y0, mut x1, mut y1) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
            for c in &tr.corners {
                x0 = x0.min(c.x + shift.x);
                y0 = y0.min(c.y + shift.y);
                x1 = x1.max(c.x + shift.x);
                y1 = y1.max(c.y + shift.y);
            }
            let extent = (x1 - x0).max(y1 - y0);
            max_extent = max_extent.max(extent);
            // Room for the white border and quiet zone, the motion and a tag missed a while.
            let margin = 0.45 * extent + 8.0 + 2.0 * shift.norm() + 0.25 * extent * tr.missed as f64;
            if let Some(r) = self.clip(x0 - margin, y0 - margin, x1 + margin, y1 + margin) {
                rects.push(r);
            }
        }
        // The sweep: one strip per frame, the whole frame once per interval.
        let frames_per_sweep = if self.frame_dt_ns > 0 { (self.interval_ns / self.frame_dt_ns).max(1) as u32 } else { 8 };
        let overlap = (max_extent * 1.6 + 16.0).min(self.height as f64);
        let strip_h = self.height as f64 / frames_per_sweep as f64;
        let k = self.sweep_index % frames_per_sweep;
        let y0 = k as f64 * strip_h - overlap / 2.0;
        let y1 = (k + 1) as f64 * strip_h + overlap / 2.0;
        if let Some(r) = self.clip(0.0, y0, self.width as f64, y1) {
            rects.push(r);
        }
        self.sweep_index = (k + 1) % frames_per_sweep;
        if self.sweep_index == 0 {
            self.last_full_ns = Some(t_ns);
        }
        Some(merge_rects(rects))
    }

    /// Records what the frame at `t_ns` showed, for the next plan. Tags expected but not
    /// seen trigger one full-frame search; a tag missing for a second of frames is dropped
    /// from tracking (the sweep picks it up again).
    pub fn observe(
        &mut self,
        t_ns: i64,
        _pose: Option<&Pose>,
        background: &[Detection],
        specimen: &[Detection],
        _solved: &[(u32, Pose)],
        _size_mm: f64,
    ) {
        let mut seen = std::collections::HashSet::new();
        for d in background.iter().chain(specimen) {
            let key = (d.family, d.id);
            seen.insert(key);
            let c_new = centre(&d.corners);
            match self.tracks.get_mut(&key) {
                Some(tr) => {
                    let dt = (t_ns - tr.t_ns) as f64 * 1e-9;
                    if dt > 0.0 {
                        let v = (c_new - centre(&tr.corners)) / dt;
                        tr.velocity = if tr.missed == 0 { tr.velocity * 0.5 + v * 0.5 } else { v };
                    }
                    tr.corners = d.corners;
                    tr.t_ns = t_ns;
                    tr.missed = 0;
                }
                None => {
                    self.tracks.insert(key, Track { corners: d.corners, velocity: nalgebra::Vector2::zeros(), t_ns, missed: 0 });
                }
            }
        }
        let max_missed = if self.frame_dt_ns > 0 { (self.interval_ns / self.frame_dt_ns).clamp(2, 60) as u32 } else { 10 };
        let mut lost_now = false;
        self.tracks.retain(|k, tr| {
            if seen.contains(k) {
                return true;
            }
            tr.missed += 1;
            if tr.missed == 1 {
                lost_now = true;
            }
            tr.missed <= max_missed
        });
        if lost_now {
            self.full_requested = true;
        }
    }
}

impl RoiPlanner {
    fn clip(&self, x0: f64, y0: f64, x1: f64, y1: f64) -> Option<Rect> {
        let cx0 = x0.floor().max(0.0) as u32;
        let cy0 = y0.floor().max(0.0) as u32;
        let cx1 = (x1.ceil().max(0.0) as u32).min(self.width);
        let cy1 = (y1.ceil().max(0.0) as u32).min(self.height);
        (cx1 > cx0 + 8 && cy1 > cy0 + 8).then_some(Rect { x: cx0, y: cy0, width: cx1 - cx0, height: cy1 - cy0 })
    }
}

fn centre(c: &[Point2<f64>; 4]) -> nalgebra::Vector2<f64> {
    (c[0].coords + c[1].coords + c[2].coords + c[3].coords) / 4.0
}

/// Merges overlapping rectangles where the merged one costs no more pixels than the two
/// apart (overlapping windows are otherwise searched as they are: each tag lies wholly
/// inside its own window, and detections found twice are de-duplicated).
pub fn merge_rects(mut rects: Vec<Rect>) -> Vec<Rect> {
    let area = |r: &Rect| r.width as u64 * r.height as u64;
    loop {
        let mut merged = false;
        'outer: for i in 0..rects.len() {
            for j in (i + 1)..rects.len() {
                if overlaps(&rects[i], &rects[j]) {
                    let u = union(&rects[i], &rects[j]);
                    if area(&u) <= area(&rects[i]) + area(&rects[j]) {
                        rects[i] = u;
                        rects.swap_remove(j);
                        merged = true;
                        break 'outer;
                    }
                }
            }
        }
        if !merged {
            return rects;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn det(id: u32, x: f64, y: f64, s: f64) -> Detection {
        Detection {
            family: TagFamily::Tag36h11,
            id,
            corners: [Point2::new(x, y + s), Point2::new(x + s, y + s), Point2::new(x + s, y), Point2::new(x, y)],
            decision_margin: 50.0,
            hamming: 0,
        }
    }

    fn intr() -> CameraIntrinsics {
        CameraIntrinsics { width: 1000, height: 800, fx: 1000.0, fy: 1000.0, cx: 499.5, cy: 399.5, dist: [0.0; 5] }
    }

    #[test]
    fn first_frame_is_full_then_windows_with_a_sweep_strip() {
        let img = GrayImage::new(1000, 800);
        let mut p = RoiPlanner::new(intr(), true, 1.0);
        assert!(p.plan(0, &img).is_none());
        p.observe(0, None, &[], &[det(1, 100.0, 100.0, 40.0), det(2, 600.0, 500.0, 40.0)], &[], 30.0);
        let rects = p.plan(33_000_000, &img).expect("windows");
        // Both tags are inside some window.
        for (x, y) in [(120.0, 120.0), (620.0, 520.0)] {
            assert!(rects
                .iter()
                .any(|r| (r.x as f64) < x - 30.0 && (x1(r) as f64) > x + 30.0 && (r.y as f64) < y - 30.0 && (y1(r) as f64) > y + 30.0));
        }
        let area: u64 = rects.iter().map(|r| r.width as u64 * r.height as u64).sum();
        assert!(area < 1000 * 800 / 2, "windows cover {area} px");
    }

    #[test]
    fn a_lost_tag_triggers_one_full_frame_search() {
        let img = GrayImage::new(1000, 800);
        let mut p = RoiPlanner::new(intr(), true, 1.0);
        p.plan(0, &img);
        p.observe(0, None, &[], &[det(1, 100.0, 100.0, 40.0), det(2, 600.0, 500.0, 40.0)], &[], 30.0);
        assert!(p.plan(33_000_000, &img).is_some());
        p.observe(33_000_000, None, &[], &[det(1, 100.0, 100.0, 40.0)], &[], 30.0);
        assert!(p.plan(66_000_000, &img).is_none(), "lost tag → full frame");
        p.observe(66_000_000, None, &[], &[det(1, 100.0, 100.0, 40.0)], &[], 30.0);
        assert!(p.plan(99_000_000, &img).is_some(), "still lost → back to windows + sweep");
    }

    #[test]
    fn sweep_covers_the_whole_frame_within_the_interval() {
        let img = GrayImage::new(1000, 800);
        let mut p = RoiPlanner::new(intr(), true, 0.3);
        p.plan(0, &img);
        let mut covered = vec![false; 800];
        for k in 1..=12 {
            let t = k * 33_000_000;
            p.observe(t - 33_000_000, None, &[], &[det(1, 100.0, 100.0, 40.0)], &[], 30.0);
            for r in p.plan(t, &img).unwrap() {
                if r.x == 0 && r.width == 1000 {
                    covered[r.y as usize..y1(&r) as usize].iter_mut().for_each(|c| *c = true);
                }
            }
        }
        assert!(covered.iter().all(|&c| c), "every row swept");
    }

    #[test]
    fn overlapping_rects_merge() {
        let r = |x, y, w, h| Rect { x, y, width: w, height: h };
        let m = merge_rects(vec![r(0, 0, 10, 10), r(2, 2, 10, 10), r(50, 50, 10, 10)]);
        assert_eq!(m.len(), 2);
        assert!(m.contains(&r(0, 0, 12, 12)));
        // A full-width strip does not swallow a window that only touches it.
        let m = merge_rects(vec![r(0, 100, 1000, 50), r(400, 140, 40, 40)]);
        assert_eq!(m.len(), 2);
    }
}
