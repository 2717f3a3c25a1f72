//! One camera's detection as one component: [`CameraDetector`] plans what to look for in
//! each frame ([`super::plan`]), confirms the tags it follows at their predicted places
//! ([`super::confirm`]), searches windows of the tags it could not confirm and the sweep's
//! tiles with the AprilTag library, sorts what it found into background and specimen tags
//! and remembers, per tag, what the next frame needs (where it was, its edge fits' levels,
//! the pixels they were fitted on, the contrast of the tags it follows).
//!
//! What the cameras of a rig share is in [`RigDetectors`]: the one AprilTag [`Detector`]
//! (its tag36h11 decoding table is 37 MB, so one for all cameras; its searches take their
//! options per call and run on several C workers at once), the [`TagConfirmer`] with the
//! known tags' bitmaps and the rig's [`TagRoles`]. Cameras are independent, so the
//! measurement detects all of a frame set's cameras in parallel.
//!
//! **A missed window searched again**: windows are searched decimated and with a contrast
//! filter (see [`super::plan`]); a tag seen the last time it was looked for, not confirmed
//! and not found there is searched for once more in its window at the configured resolution
//! and contrast filter, in the same frame ([`DetectReport::window_retries`]) — a steep,
//! foreshortened tag that full-frame mode finds is found in tracking mode too. A tag already
//! missing (occluded, out of view) is not retried: it waits for the sweep.
//!
//! **Background searches** (on by default in tracking mode, live and replay alike): a
//! whole-frame search after the first frame — the sweep after a tag was lost, or the
//! search of a camera that follows no tag — runs on a thread of its own on a copy of the
//! frame, so it stalls no frame set. Its tags are taken in at the first frame at least
//! [`BACKGROUND_SEARCH_LAG_NS`] after the searched frame (the detector waits for the
//! search there if it has not finished, which on an idle PC it has long done), and are
//! confirmed there, where they were found. The moment a result is taken in depends only on
//! the frames' times, never on how fast the search ran, so a live run and the replay of its
//! recording give the same feed.
//!
//! **Start-up search**: the first search of a camera in tracking mode (no tag followed yet)
//! runs at quad decimation [`STARTUP_DECIMATE`] (the library fits quads on half the pixels;
//! corners are refined at full resolution, so they are as good as a full-resolution
//! search's); when it did not find every specimen tag of the rig, the same frame is searched
//! again at the configured resolution, so a camera that sees every specimen tag is ready in
//! a quarter of the time and no tag is lost to the decimation.
//!
//! **A camera that moved** ([`CameraDetector::search_again`]): when the background tags of
//! a frame were mostly lost or jumped ([`DetectReport::background`], or the pose tracker's
//! bump statistic), the measurement has the same frame searched whole at the configured
//! resolution, in the frame set, before it poses the camera — the windows were placed where
//! the tags no longer are, and a background search would deliver them half a second late
//! at places the camera may have left again. Its tags replace the frame's detections and
//! their sightings; a background search under way is abandoned (its tags are of the old
//! view). A background tag lost while the others stay put (occluded, blurred) costs no
//! search in the frame: the camera keeps its pose and the sweeps look for the tag.

use std::collections::{HashMap, HashSet};
use std::sync::mpsc;
use std::sync::Arc;
use std::time::Instant;

use rayon::prelude::*;

use super::apriltag::{Detector, SearchOptions};
use super::confirm::{ConfirmMiss, ConfirmedTag, Prediction, TagConfirmer};
use super::detect_report::DetectReport;
use super::learned::{CameraProfile, TagKey};
use super::plan::{masked_tile, merge_rects, Plan, PlannedTag, RoiPlanner};
use super::refine::{refine_corners_warm, EdgeMemory};
use super::{Detection, Rect};
use tagdeflect_core::camera::{CameraIntrinsics, IdealPixelMap, Lens};
use tagdeflect_core::frame::GrayImage;
use tagdeflect_core::tags::TagFamily;

/// Searches in tracking mode skip image regions whose contrast is below this fraction of
/// the weakest tracked tag's (a new tag printed and lit like the others has about their
/// contrast; a third of it leaves room for shadows) — the beam's low-contrast texture is
/// then not searched at all, which is most of a search's cost on a textured specimen.
const SEARCH_CONTRAST_FRACTION: f64 = 0.3;
/// Cap of the contrast filter of tracking-mode searches, grey levels.
const MAX_SEARCH_WHITE_BLACK_DIFF: f64 = 40.0;

/// Time (frame time, ns) after a background search's frame at which its tags are taken in
/// (see the module docs): 0.5 s — a full-resolution search of a 1920x1080 frame takes
/// ~0.3 s of one core, and a tag lost for half a second more costs nothing a lost tag has
/// not already cost.
const BACKGROUND_SEARCH_LAG_NS: i64 = 500_000_000;
/// Quad decimation of a camera's start-up search in tracking mode (see the module docs).
const STARTUP_DECIMATE: f32 = 2.0;

/// The tags confirmed in a frame.
struct Confirmed {
    tags: Vec<Detection>,
    /// How many of them reused their pixels from an earlier frame.
    reused_bands: u64,
}

/// The tags of one camera's frame, sorted by role (others are ignored).
#[derive(Debug, Clone, Default)]
pub struct CameraDetections {
    /// Background tags (known world positions).
    pub background: Vec<Detection>,
    /// Specimen tags.
    pub specimen: Vec<Detection>,
}

/// Which detected tags are background and which specimen tags.
#[derive(Debug, Clone)]
pub struct TagRoles {
    /// Family of the background tags.
    pub background_family: TagFamily,
    /// Their ids.
    pub background: HashSet<u32>,
    /// Family of the specimen tags.
    pub specimen_family: TagFamily,
    /// Their ids.
    pub specimen: HashSet<u32>,
}

impl TagRoles {
    /// Sorts detections into background and specimen tags; when both share a family, an id
    /// of both lists is a background tag.
    pub(crate) fn classify(&self, dets: Vec<Detection>) -> CameraDetections {
        let same_family = self.background_family == self.specimen_family;
        let mut out = CameraDetections::default();
        for d in dets {
            let is_sp =
                d.family == self.specimen_family && self.specimen.contains(&d.id) && !(same_family && self.background.contains(&d.id));
            let is_bg = d.family == self.background_family && self.background.contains(&d.id);
            if is_sp {
                out.specimen.push(d);
            } else if is_bg {
                out.background.push(d);
            }
        }
        out
    }

    /// Every known tag (family, id).
    pub fn known(&self) -> impl Iterator<Item = (TagFamily, u32)> + '_ {
        let bg = self.background.iter().map(|id| (self.background_family, *id));
        bg.chain(self.specimen.iter().map(|id| (self.specimen_family, *id)))
    }
}

/// What the cameras of a rig share (see the module docs).
#[derive(Debug)]
pub struct RigDetectors {
    /// The AprilTag library.
    pub library: Detector,
    /// Confirms tags at their predicted places.
    pub confirmer: TagConfirmer,
    /// Which tags are which.
    pub roles: TagRoles,
}

/// One camera's detection: plan, confirmation, searches and every per-tag state (see the
/// module docs).
#[derive(Debug)]
pub struct CameraDetector {
    intrinsics: CameraIntrinsics,
    planner: RoiPlanner,
    /// What each followed tag's last fit left for its next (see [`EdgeMemory`]).
    edge_memory: HashMap<(TagFamily, u32), EdgeMemory>,
    /// The camera's learned edge profile (see [`super::learned`]).
    profile: CameraProfile,
    /// Contrast (grey levels) of the weakest tag confirmed in the last frame that confirmed any.
    tag_contrast: Option<f64>,
    /// The sweep's masked copy of a tile (reused).
    tile: GrayImage,
    /// The ideal coordinates of the pixels the followed tags' edge fits use (kept: the
    /// tags stay in the same few blocks of the image).
    pixel_map: Option<IdealPixelMap>,
    /// Whole-frame searches after the first frame run in the background.
    background: bool,
    /// Tracking mode (the start-up search is decimated).
    tracking: bool,
    /// A frame has been searched (the first search is never in the background).
    searched_once: bool,
    /// The background search under way: its frame's time and where its tags will come.
    pending: Option<(i64, mpsc::Receiver<Vec<Detection>>)>,
}

impl CameraDetector {
    /// The detector of a camera with these intrinsics; `roi_tracking = false` searches
    /// every frame whole. `phase` (e.g. the camera's index) staggers the cameras' sweeps.
    pub fn new(intrinsics: CameraIntrinsics, roi_tracking: bool, full_search_interval_s: f64, phase: u32) -> Self {
        Self {
            intrinsics,
            planner: RoiPlanner::new(intrinsics, roi_tracking, full_search_interval_s).with_phase(phase),
            edge_memory: HashMap::new(),
            profile: CameraProfile::default(),
            tag_contrast: None,
            tile: GrayImage::new(0, 0),
            pixel_map: None,
            background: roi_tracking,
            tracking: roi_tracking,
            searched_once: false,
            pending: None,
        }
    }

    /// How much this camera's corners' σ is to be widened for its edge fits' model error:
    /// their residuals on the edges against the camera's noise there
    /// ([`ModelExcess::factor`](crate::refine::ModelExcess::factor) with `TAGDEFLECT_SIGMA_WIDENING=residuals`; 1 while the
    /// fits are at the noise level and before the edge profile is learned).
    pub fn corner_sigma_factor(&self) -> f64 {
        self.profile.sigma_factor()
    }

    /// Runs whole-frame searches after the first frame in the background (the default in
    /// tracking mode; see the module docs) or, with `false`, each in its own frame.
    pub fn set_background_searches(&mut self, on: bool) {
        self.background = on;
    }

    /// Takes the tags of the background search under way into the plan when they are due
    /// at the frame at `t_ns` (waiting for the search if it has not finished); returns the
    /// time waited, seconds.
    fn take_background_result(&mut self, t_ns: i64, rig: &RigDetectors) -> f64 {
        let due = self.pending.as_ref().is_some_and(|(t_search, _)| t_ns.saturating_sub(*t_search) >= BACKGROUND_SEARCH_LAG_NS);
        let Some((t_search, rx)) = self.pending.take_if(|_| due) else { return 0.0 };
        let c0 = Instant::now();
        let result = rx.recv();
        let waited = c0.elapsed().as_secs_f64();
        match result {
            Ok(dets) => {
                let dets = rig.roles.classify(dets);
                self.planner.add_found(t_search, &dets.background, &dets.specimen);
            }
            Err(_) => tracing::warn!("a background search ended without a result"),
        }
        waited
    }

    /// Starts a search of the whole `image` in the background unless one is under way;
    /// true when one was started.
    fn start_background_search(&mut self, t_ns: i64, image: &GrayImage, options: SearchOptions, rig: &Arc<RigDetectors>) -> bool {
        if self.pending.is_some() {
            return false;
        }
        let (tx, rx) = mpsc::channel();
        let (image, rig, intrinsics) = (image.clone(), Arc::clone(rig), self.intrinsics);
        let spawned = std::thread::Builder::new().name("background-search".into()).spawn(move || {
            let found = rig.library.search(&image, None, &options, Lens::new(Some(&intrinsics)));
            let _ = tx.send(found);
        });
        match spawned {
            Ok(_) => {
                self.pending = Some((t_ns, rx));
                true
            }
            Err(e) => {
                tracing::warn!("cannot start a background search: {e}");
                false
            }
        }
    }

    /// The in-frame search of the whole `image` (see the module docs for the decimated
    /// start-up search); returns the tags, the number of searches run and whether one was
    /// at the configured resolution.
    fn search_whole_frame(&mut self, image: &GrayImage, rig: &RigDetectors) -> (Vec<Detection>, u64, bool) {
        let configured = SearchOptions::of(rig.library.options());
        self.prepare_pixel_map(image);
        let lens = self.pixel_map.as_ref().map_or(Lens::new(Some(&self.intrinsics)), Lens::with_map);
        let startup = self.tracking && !self.searched_once && configured.quad_decimate < STARTUP_DECIMATE;
        if startup {
            let options = SearchOptions { quad_decimate: STARTUP_DECIMATE, ..configured };
            let found = rig.library.search(image, None, &options, lens);
            let seen: HashSet<u32> = found.iter().filter(|d| d.family == rig.roles.specimen_family).map(|d| d.id).collect();
            if rig.roles.specimen.iter().all(|id| seen.contains(id)) {
                return (found, 1, false);
            }
            tracing::debug!(
                found = seen.len(),
                specimen_tags = rig.roles.specimen.len(),
                "decimated start-up search missed specimen tags: searching at full resolution"
            );
            return (rig.library.search(image, None, &configured, lens), 2, true);
        }
        (rig.library.search(image, None, &configured, lens), 1, true)
    }

    /// Detects the tags of the frame at `t_ns`: the tags followed are confirmed where they
    /// are predicted (in parallel), then the searches still needed — the full frame, windows
    /// of tags not confirmed, sweep tiles — run on the rig's shared detector; what was found
    /// is remembered for the next frame.
    pub fn detect(&mut self, t_ns: i64, image: &GrayImage, rig: &Arc<RigDetectors>) -> (CameraDetections, DetectReport) {
        let mut report = DetectReport::default();
        report.parts.background_wait = self.take_background_result(t_ns, rig);
        let background = self.background && self.searched_once;
        let mut confirmed_keys = HashSet::new();
        let mut found = match self.planner.plan(t_ns, image) {
            Plan::FullFrame if background && self.planner.is_empty() => {
                if self.start_background_search(t_ns, image, SearchOptions::of(rig.library.options()), rig) {
                    report.background_searches = 1;
                }
                Vec::new()
            }
            Plan::FullFrame => {
                let c0 = Instant::now();
                let (found, searches, searched_whole) = self.search_whole_frame(image, rig);
                report.full_frame_searches = searches;
                report.searched_whole = searched_whole;
                report.parts.full_frame = c0.elapsed().as_secs_f64();
                found
            }
            Plan::Windows { decimate, sweep_decimate, tags, mut sweep, whole_frame } => {
                if background && whole_frame {
                    let options = self.search_options(rig, sweep_decimate);
                    if self.start_background_search(t_ns, image, options, rig) {
                        report.background_searches = 1;
                    }
                    sweep.clear();
                }
                let (confirmed, missed, cpu) = self.confirm(image, tags, rig);
                let windows = merge_rects(missed.iter().map(|t| t.window).collect());
                report.parts.tracking = cpu;
                report.confirmed_tags = confirmed.tags.len() as u64;
                report.reused_bands = confirmed.reused_bands;
                confirmed_keys.extend(confirmed.tags.iter().map(|d| (d.family, d.id)));
                let mut found = confirmed.tags;
                let c0 = Instant::now();
                let more = self.search(rig, image, &windows, &sweep, &found, decimate, sweep_decimate);
                found.extend(more);
                let c1 = Instant::now();
                let (again, retries) = self.retry_missed(rig, image, &missed, &found, decimate);
                found.extend(again);
                dedup_detections(&mut found);
                report.window_searches = (windows.len() + sweep.len()) as u64 + retries;
                report.window_retries = retries;
                report.parts.retry = c1.elapsed().as_secs_f64();
                report.parts.search = c0.elapsed().as_secs_f64();
                found
            }
        };
        self.searched_once = true;
        self.learn_profile(image, &mut found, &confirmed_keys, rig);
        let dets = rig.roles.classify(found);
        report.background = self.planner.observe(t_ns, &dets.background, &dets.specimen);
        (dets, report)
    }

    /// Searches the frame at `t_ns`, already detected, whole at the configured resolution
    /// (the camera moved: see the module docs); its tags are the frame's detections and are
    /// followed from where they are found.
    pub fn search_again(&mut self, t_ns: i64, image: &GrayImage, rig: &RigDetectors) -> (CameraDetections, DetectReport) {
        let mut report = DetectReport::default();
        let c0 = Instant::now();
        let configured = SearchOptions::of(rig.library.options());
        self.prepare_pixel_map(image);
        let lens = self.pixel_map.as_ref().map_or(Lens::new(Some(&self.intrinsics)), Lens::with_map);
        let mut found = rig.library.search(image, None, &configured, lens);
        self.learn_profile(image, &mut found, &HashSet::new(), rig);
        report.full_frame_searches = 1;
        report.searched_whole = true;
        report.parts.full_frame = c0.elapsed().as_secs_f64();
        self.pending = None;
        let dets = rig.roles.classify(found);
        for d in dets.background.iter().chain(&dets.specimen) {
            self.edge_memory.remove(&(d.family, d.id));
        }
        self.planner.refound(t_ns, &dets.background, &dets.specimen);
        (dets, report)
    }

    /// The frame's tags teach the camera's edge profile and are fitted with it (see
    /// [`super::learned`]); `confirmed`: the tags confirmed at their predicted place.
    fn learn_profile(&mut self, image: &GrayImage, found: &mut [Detection], confirmed: &HashSet<TagKey>, rig: &RigDetectors) {
        let Some(opts) = rig.library.options().subpixel.as_ref() else { return };
        self.prepare_pixel_map(image);
        let lens = self.pixel_map.as_ref().map_or(Lens::new(Some(&self.intrinsics)), Lens::with_map);
        self.profile.after_frame(image, found, confirmed, &mut self.edge_memory, lens, opts);
    }

    /// Makes the camera's pixel map fit `image` (a new one when the frame size changed).
    fn prepare_pixel_map(&mut self, image: &GrayImage) {
        if self.pixel_map.as_ref().map(|m| m.size()) != Some((image.width, image.height)) {
            self.pixel_map = Some(IdealPixelMap::new(self.intrinsics, image.width, image.height));
        }
    }

    /// Confirms the planned tags at their predicted places; returns the confirmed tags, the
    /// others (to be searched in their windows) and the CPU time spent.
    fn confirm(&mut self, image: &GrayImage, tags: Vec<PlannedTag>, rig: &RigDetectors) -> (Confirmed, Vec<PlannedTag>, f64) {
        let refine = rig.library.options().subpixel.as_ref();
        self.prepare_pixel_map(image);
        let memories = &self.edge_memory;
        let profile = self.profile.profile();
        let lens = self.pixel_map.as_ref().map_or(Lens::new(Some(&self.intrinsics)), Lens::with_map);
        let one = |t: &PlannedTag| {
            let c0 = tagdeflect_core::clock::thread_cpu_s();
            let memory = memories.get(&(t.family, t.id)).cloned().unwrap_or_default().with_profile(profile.clone());
            let prediction = Prediction { family: t.family, id: t.id, corners: t.predicted, memory };
            let result = match refine {
                Some(opts) => rig.confirmer.confirm(image, &prediction, lens, opts),
                None => Err(ConfirmMiss::Unsupported),
            };
            (result, tagdeflect_core::clock::thread_cpu_s() - c0)
        };
        let results: Vec<(Result<ConfirmedTag, ConfirmMiss>, f64)> =
            if tags.len() > 1 { tags.par_iter().map(one).collect() } else { tags.iter().map(one).collect() };
        let (mut confirmed, mut windows, mut cpu, mut reused) = (Vec::new(), Vec::new(), 0.0, 0);
        let mut weakest: Option<f64> = None;
        for (t, (result, cpu_s)) in tags.into_iter().zip(results) {
            cpu += cpu_s;
            match result {
                Ok(tag) => {
                    weakest = Some(weakest.map_or(tag.contrast, |w: f64| w.min(tag.contrast)));
                    reused += tag.memory.reused_bands() as u64;
                    self.edge_memory.insert((t.family, t.id), tag.memory);
                    confirmed.push(tag.detection);
                }
                Err(_) => {
                    self.edge_memory.remove(&(t.family, t.id));
                    windows.push(t);
                }
            }
        }
        if weakest.is_some() {
            self.tag_contrast = weakest;
        }
        (Confirmed { tags: confirmed, reused_bands: reused }, windows, cpu)
    }

    /// The windows of `missed` tags (not confirmed) that were seen the last time they were
    /// looked for and that the search at quad decimation `search_decimate` (with the
    /// contrast filter of [`Self::search_options`]) did not find either (not in `found`),
    /// searched again at the configured resolution and contrast filter — the decimated
    /// quads miss a steep, foreshortened tag that a full-resolution search finds. Bounded:
    /// only a tag's first miss (a tag already missing waits for the sweep), and none when
    /// the windows already ran at the configured options. Returns the tags found and the
    /// number of windows searched.
    fn retry_missed(
        &mut self,
        rig: &RigDetectors,
        image: &GrayImage,
        missed: &[PlannedTag],
        found: &[Detection],
        search_decimate: f32,
    ) -> (Vec<Detection>, u64) {
        let searched = self.search_options(rig, search_decimate);
        let configured = retry_options(searched, SearchOptions::of(rig.library.options()));
        if searched == configured {
            return (Vec::new(), 0);
        }
        let windows = retry_windows(missed, found);
        if windows.is_empty() {
            return (Vec::new(), 0);
        }
        self.prepare_pixel_map(image);
        let lens = self.pixel_map.as_ref().map_or(Lens::new(Some(&self.intrinsics)), Lens::with_map);
        let again = windows.iter().flat_map(|r| rig.library.search(image, Some(*r), &configured, lens)).collect();
        (again, windows.len() as u64)
    }

    /// The options of window and sweep searches: decimation `search_decimate` (at least the
    /// configured one), the contrast filter at a fraction of the weakest followed tag's.
    fn search_options(&self, rig: &RigDetectors, search_decimate: f32) -> SearchOptions {
        let configured = rig.library.options();
        let min_diff = configured.min_white_black_diff as f64;
        let white_black_diff = self
            .tag_contrast
            .map_or(min_diff, |c| (SEARCH_CONTRAST_FRACTION * c).clamp(min_diff, MAX_SEARCH_WHITE_BLACK_DIFF.max(min_diff)));
        SearchOptions {
            quad_decimate: configured.quad_decimate.max(search_decimate),
            min_white_black_diff: white_black_diff as u8,
            refine: configured.subpixel.is_some(),
        }
    }

    /// Searches the windows around tags that could not be confirmed with quad decimation
    /// `search_decimate`, and the sweep tiles with `sweep_decimate` (each at least the
    /// configured one), with
    /// low-contrast regions skipped (see [`SEARCH_CONTRAST_FRACTION`]). Window detections
    /// are refined as usual. Tiles are searched without refinement; only the tags not
    /// already found (confirmed, or in the windows) are then refined — corners as good as a
    /// full-frame search's without refining every confirmed tag twice.
    #[allow(clippy::too_many_arguments)]
    fn search(
        &mut self,
        rig: &RigDetectors,
        image: &GrayImage,
        windows: &[Rect],
        tiles: &[Rect],
        found: &[Detection],
        search_decimate: f32,
        sweep_decimate: f32,
    ) -> Vec<Detection> {
        let mut out: Vec<Detection> = Vec::new();
        if windows.is_empty() && tiles.is_empty() {
            return out;
        }
        let configured = rig.library.options();
        let options = self.search_options(rig, search_decimate);
        self.prepare_pixel_map(image);
        let lens = self.pixel_map.as_ref().map_or(Lens::new(Some(&self.intrinsics)), Lens::with_map);
        for r in windows {
            out.extend(rig.library.search(image, Some(*r), &options, lens));
        }
        if !tiles.is_empty() {
            let tile_options = SearchOptions { refine: false, ..self.search_options(rig, sweep_decimate) };
            let mut new: Vec<Detection> = Vec::new();
            let known: Vec<Detection> = found.iter().chain(out.iter()).cloned().collect();
            for r in tiles {
                // The tile with the tags already found blanked out (see `plan::masked_tile`).
                masked_tile(image, *r, &known, &mut self.tile);
                let whole = Rect { x: 0, y: 0, width: r.width, height: r.height };
                for mut d in rig.library.search(&self.tile, Some(whole), &tile_options, Lens::new(None)) {
                    for c in d.corners.iter_mut() {
                        *c += nalgebra::Vector2::new(r.x as f64, r.y as f64);
                    }
                    let known = known.iter().chain(new.iter()).any(|f| f.family == d.family && f.id == d.id);
                    if !known {
                        new.push(d);
                    }
                }
            }
            if let Some(opts) = &configured.subpixel {
                for d in &mut new {
                    refine_corners_warm(image, d, lens, opts, &mut EdgeMemory::default());
                }
            }
            out.extend(new);
        }
        out
    }
}

/// Removes duplicate detections of one tag found in overlapping windows (keeps the one
/// with the highest decision margin).
fn dedup_detections(dets: &mut Vec<Detection>) {
    dets.sort_by(|a, b| (a.family.name(), a.id).cmp(&(b.family.name(), b.id)).then(b.decision_margin.total_cmp(&a.decision_margin)));
    dets.dedup_by(|b, a| a.family == b.family && a.id == b.id);
}

/// The windows searched again by [`CameraDetector::retry_missed`]: those of the `missed` tags
/// seen the last time they were looked for and not in `found`, merged where they overlap.
fn retry_windows(missed: &[PlannedTag], found: &[Detection]) -> Vec<Rect> {
    let is_found = |t: &PlannedTag| found.iter().any(|d| d.family == t.family && d.id == t.id);
    merge_rects(missed.iter().filter(|t| t.expected && !is_found(t)).map(|t| t.window).collect())
}

/// The retry's options: the configured ones; `TAGDEFLECT_RETRY_OPTIONS=decimation` (or
/// `contrast`) lifts only that one of the window search's `searched` options, the other kept
/// (a measurement of which one misses a tag: docs/performance.md, "Why a window misses").
fn retry_options(searched: SearchOptions, configured: SearchOptions) -> SearchOptions {
    static ONLY: std::sync::OnceLock<Option<String>> = std::sync::OnceLock::new();
    match ONLY.get_or_init(|| std::env::var("TAGDEFLECT_RETRY_OPTIONS").ok()).as_deref() {
        Some("decimation") => SearchOptions { quad_decimate: configured.quad_decimate, ..searched },
        Some("contrast") => SearchOptions { min_white_black_diff: configured.min_white_black_diff, ..searched },
        _ => configured,
    }
}

#[cfg(test)]
#[path = "camera_detector_tests.rs"]
mod tests;
