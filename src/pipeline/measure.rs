//! The measurement of one frame set: detect → pose cameras → solve specimen tags → feed
//! line. Owns all state carried between frame sets (detectors, camera pose trackers,
//! region-of-interest windows, each tag's warm start and first position, UTM history).

use nalgebra::{Matrix6, Vector3};
use std::collections::{BTreeMap, HashMap};
use std::time::Instant;

use crate::camera::{CameraIntrinsics, Pose};
use crate::config::{Config, TagRole};
use crate::detect::apriltag::{DetectError, Detector, DetectorOptions};
use crate::detect::refine::RefineOptions;
use crate::detect::{refine_corners_with, Detection, EdgeLevels, Prediction, Rect, TagTracker, TrackMiss, TrackOptions, TrackedTag};
use crate::feed::{round_mm, CameraHealth, FeedLine, FeedTag};
use crate::frame::FrameSet;
use crate::pipeline::roi::{masked_tile, merge_rects, Plan, PlannedTag, RoiPlanner};
use crate::solve::{solve_tag, BackgroundTagObservation, CameraPoseTracker, PixelNoisePool, TagMotion, TagView};
use crate::tags::TagFamily;
use crate::utm::UtmHistory;
use rayon::prelude::*;

/// Wall-clock time spent in each stage of one frame set, seconds.
#[derive(Debug, Clone, Copy, Default)]
pub struct StageTimes {
    /// Tag detection (all cameras, in parallel; wall time).
    pub detect: f64,
    /// Detection time by kind of work.
    pub detect_parts: DetectParts,
    /// Camera pose tracking.
    pub pose: f64,
    /// Specimen tag solving.
    pub solve: f64,
}

/// Time of one frame set's detection by kind of work, seconds.
#[derive(Debug, Clone, Copy, Default)]
pub struct DetectParts {
    /// CPU time confirming tracked tags at their predicted place (refinement and
    /// read-back), summed over the cameras (which run in parallel).
    pub tracking: f64,
    /// Wall time of the window searches of tags not confirmed and of the sweep's tiles
    /// (one camera after another, each on the library's worker threads).
    pub search: f64,
    /// Wall time of full-frame searches (likewise).
    pub full_frame: f64,
}

impl DetectParts {
    /// Adds another frame set's times (totals over a run).
    pub fn add(&mut self, other: &DetectParts) {
        self.tracking += other.tracking;
        self.search += other.search;
        self.full_frame += other.full_frame;
    }
}

/// CPU time of the calling thread, seconds.
fn thread_cpu_s() -> f64 {
    let mut ts = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: clock_gettime writes the timespec it is given; CLOCK_THREAD_CPUTIME_ID exists on Linux.
    unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut ts) };
    ts.tv_sec as f64 + ts.tv_nsec as f64 * 1e-9
}

/// Counters over a whole run.
#[derive(Debug, Clone, Default)]
pub struct MeasureStats {
    /// Frame sets processed.
    pub sets: u64,
    /// Full-frame detections run.
    pub full_frame_searches: u64,
    /// Window (region-of-interest) and sweep-tile detections run.
    pub window_searches: u64,
    /// Tag views confirmed at their predicted place (no search needed).
    pub tracked_tags: u64,
    /// Specimen tag views rejected as outliers.
    pub rejected_views: u64,
    /// Camera bumps detected.
    pub bumps: u64,
}

struct CameraState {
    name: String,
    intrinsics: CameraIntrinsics,
    tracker: CameraPoseTracker,
    roi: RoiPlanner,
    /// Each tracked tag's last edge-fit levels in this camera (warm start of its next fit).
    edge_levels: HashMap<(TagFamily, u32), EdgeLevels>,
    /// Contrast (grey levels) of the weakest tag confirmed in the last frame that confirmed any.
    tag_contrast: Option<f64>,
}

/// Searches in tracking mode skip image regions whose contrast is below this fraction of
/// the weakest tracked tag's (a new tag printed and lit like the others has about their
/// contrast; a third of it leaves room for shadows) — the beam's low-contrast texture is
/// then not searched at all, which is most of a search's cost on a textured specimen.
pub const SEARCH_CONTRAST_FRACTION: f64 = 0.3;
/// Cap of the contrast filter of tracking-mode searches, grey levels.
pub const MAX_SEARCH_WHITE_BLACK_DIFF: f64 = 40.0;

struct TagTrack {
    /// Last solution tag → world (warm start).
    pose: Pose,
    /// Centre in the first frame set that solved the tag.
    first_centre: Vector3<f64>,
    /// Recent multi-view solutions: the depth of a monocular view (see `solve::motion`).
    motion: TagMotion,
}

/// What phase 1 of the detection leaves to phase 2 for one camera.
struct SearchJob {
    camera: usize,
    /// Index of the camera's frame in the frame set.
    frame: usize,
    /// Tags confirmed (then everything found).
    found: Vec<Detection>,
    /// Search the whole frame.
    full: bool,
    /// Windows of tracked tags not confirmed.
    windows: Vec<Rect>,
    /// Sweep tiles.
    sweep: Vec<Rect>,
    /// Quad decimation of windows and tiles.
    decimate: f32,
}

/// Per-camera result of the detection stage.
struct CameraDetections {
    background: Vec<Detection>,
    specimen: Vec<Detection>,
}

/// The stateful frame-set processor shared by `replay`, `bench`, `run` and `demo`.
pub struct Measurement {
    config: Config,
    up: Vector3<f64>,
    cameras: Vec<CameraState>,
    /// The AprilTag library, shared by the cameras: searches run one at a time on the
    /// library's worker threads (its decoding tables take ~37 MB for tag36h11 per
    /// detector, so one detector instead of one per camera).
    detector: Detector,
    /// Confirms tracked tags at their predicted places (shared by the cameras' threads).
    tag_tracker: TagTracker,
    /// The sweep's masked copy of a tile (reused).
    tile: crate::frame::GrayImage,
    background_world: HashMap<u32, [Vector3<f64>; 4]>,
    specimen_ids: HashMap<u32, Option<TagRole>>,
    tags: BTreeMap<u32, TagTrack>,
    utm: UtmHistory,
    /// Pooled specimen corner noise, px (scales every tag's σ).
    noise: PixelNoisePool,
    stats: MeasureStats,
    /// Virtual gauges and the clock check (`solve::gauges`, `solve::clock_offset`).
    gauges: crate::solve::gauges::LineGauges,
}

impl Measurement {
    /// Builds the processor; `roi_tracking = false` forces full-frame detection everywhere.
    pub fn new(config: &Config, roi_tracking: bool) -> Result<Measurement, DetectError> {
        let families: Vec<TagFamily> = if config.background.family == config.specimen.family {
            vec![config.background.family]
        } else {
            vec![config.specimen.family, config.background.family]
        };
        let opts = DetectorOptions {
            quad_decimate: config.measure.quad_decimate,
            nthreads: config.measure.detector_threads.max(1),
            subpixel: config.measure.refine_corners.then(RefineOptions::default),
            ..DetectorOptions::for_families(&families)
        };
        let detector = Detector::new(opts)?;
        let mut cameras = Vec::new();
        for cam in &config.cameras {
            let intrinsics = cam.intrinsics();
            let fixed = cam.rvec.zip(cam.tvec_mm).map(|(r, t)| Pose::from_rvec_tvec(r, t));
            cameras.push(CameraState {
                name: cam.name.clone(),
                intrinsics,
                tracker: CameraPoseTracker::new(intrinsics, fixed),
                roi: RoiPlanner::new(intrinsics, roi_tracking && config.measure.roi_tracking, config.measure.full_search_interval_s)
                    .with_phase(cameras.len() as u32),
                edge_levels: HashMap::new(),
                tag_contrast: None,
            });
        }
        let known_tags = config.background.tags.iter().map(|t| (config.background.family, t.id));
        let tag_tracker =
            TagTracker::new(TrackOptions::default(), known_tags.chain(config.specimen.tags.iter().map(|t| (config.specimen.family, t.id))));
        let background_world = config.background.tags.iter().map(|t| (t.id, t.corners_mm.map(Vector3::from))).collect();
        let specimen_ids = config.specimen.tags.iter().map(|t| (t.id, t.role)).collect();
        let up = Vector3::from(config.world.up).normalize();
        Ok(Measurement {
            config: config.clone(),
            up,
            cameras,
            detector,
            tag_tracker,
            tile: crate::frame::GrayImage::new(0, 0),
            background_world,
            specimen_ids,
            tags: BTreeMap::new(),
            // No load across a UTM outage: at most five missed polls (and 0.5 s) are bridged.
            utm: UtmHistory::unbounded().with_max_gap(config.utm.as_ref().map_or(0, |u| ((5.0 / u.poll_hz).max(0.5) * 1e9) as i64)),
            noise: PixelNoisePool::default(),
            stats: MeasureStats::default(),
            gauges: crate::solve::gauges::LineGauges::new(config),
        })
    }

    /// Counters so far.
    pub fn stats(&self) -> &MeasureStats {
        &self.stats
    }

    /// The UTM history (the pipeline pushes samples into it).
    pub fn utm_mut(&mut self) -> &mut UtmHistory {
        &mut self.utm
    }

    /// Current pose of each camera (world → camera), `None` until posed.
    pub fn camera_poses(&self) -> Vec<Option<Pose>> {
        self.cameras.iter().map(|c| c.tracker.pose()).collect()
    }

    /// Processes one frame set into a feed line.
    pub fn process(&mut self, set: &FrameSet) -> (FeedLine, StageTimes) {
        let mut times = StageTimes::default();
        let t0 = Instant::now();
        let (detections, cpu) = self.detect(set);
        times.detect = t0.elapsed().as_secs_f64();
        times.detect_parts = cpu;

        // Camera poses from the background tags.
        let t1 = Instant::now();
        let mut health = Vec::with_capacity(self.cameras.len());
        for (ci, cam) in self.cameras.iter_mut().enumerate() {
            let det = detections.iter().find(|(i, _)| *i == ci).map(|(_, d)| d);
            let mut h = CameraHealth {
                name: cam.name.clone(),
                frame: det.is_some(),
                background_tags: 0,
                specimen_tags: 0,
                pose_reproj_px: None,
                posed: cam.tracker.pose().is_some(),
                bumped: false,
            };
            if let Some(d) = det {
                h.background_tags = d.background.len();
                h.specimen_tags = d.specimen.len();
                let obs: Vec<BackgroundTagObservation> = d
                    .background
                    .iter()
                    .filter_map(|det| {
                        self.background_world.get(&det.id).map(|w| BackgroundTagObservation { id: det.id, pixels: det.corners, world: *w })
                    })
                    .collect();
                let status = cam.tracker.update(&obs);
                h.posed = status.pose.is_some();
                h.pose_reproj_px = status.rms_px;
                h.bumped = status.bumped;
                if status.bumped {
                    self.stats.bumps += 1;
                    tracing::warn!(camera = %cam.name, seq = set.seq, "camera moved: background tags shifted in the image; re-posed");
                }
            }
            health.push(h);
        }
        times.pose = t1.elapsed().as_secs_f64();

        // Specimen tags over all views.
        let t2 = Instant::now();
        let mut views_by_tag: BTreeMap<u32, (Vec<TagView>, Vec<usize>)> = BTreeMap::new();
        for (ci, d) in &detections {
            let cam = &self.cameras[*ci];
            let Some(pose) = cam.tracker.pose() else { continue };
            let cov: Option<Matrix6<f64>> = cam.tracker.covariance();
            for det in &d.specimen {
                let entry = views_by_tag.entry(det.id).or_default();
                entry.0.push(TagView { intrinsics: cam.intrinsics, camera_pose: pose, camera_pose_covariance: cov, corners: det.corners });
                entry.1.push(*ci);
            }
        }
        let pooled = self.noise.sigma_px();
        let size = self.config.specimen.size_mm;
        let mut tags_out = Vec::new();
        let mut sq_sum = 0.0;
        let mut sq_n = 0.0;
        for (id, (views, view_cameras)) in &views_by_tag {
            let warm = self.tags.get(id).map(|t| t.pose);
            match solve_tag(views, size, warm.as_ref(), pooled) {
                Ok(sol) => {
                    self.stats.rejected_views += sol.rejected_views.len() as u64;
                    for r in &sol.rejected_views {
                        tracing::info!(tag = id, camera = %self.cameras[view_cameras[*r]].name, seq = set.seq, "specimen tag view rejected as an outlier (its corners disagree with the other views)");
                    }
                    self.noise.add_solution(&sol);
                    let n_res = 8.0 * sol.views as f64;
                    sq_sum += sol.rms_px * sol.rms_px * n_res;
                    sq_n += n_res;
                    let track = self.tags.entry(*id).or_insert(TagTrack {
                        pose: sol.tag_to_world,
                        first_centre: sol.centre_mm,
                        motion: TagMotion::default(),
                    });
                    let (mut c, mut sigma) = (sol.centre_mm, sol.sigma_mm);
                    let mut pose = sol.tag_to_world;
                    let mut fused_cov = None;
                    if sol.views >= 2 {
                        track.motion.observe(set.t_ns, c, sol.centre_covariance);
                    } else if let Some((fc, fcov)) = track.motion.fuse(set.t_ns, c, sol.centre_covariance) {
                        c = fc;
                        sigma = Vector3::new(fcov[(0, 0)].sqrt(), fcov[(1, 1)].sqrt(), fcov[(2, 2)].sqrt());
                        pose.translation = fc;
                        fused_cov = Some(fcov);
                    }
                    self.gauges.add_tag(*id, &pose, &sol, fused_cov);
                    track.pose = pose;
                    let disp = c - track.first_centre;
                    tags_out.push(FeedTag {
                        id: *id,
                        pos_mm: [round_mm(c.x), round_mm(c.y), round_mm(c.z)],
                        disp_mm: [round_mm(disp.x), round_mm(disp.y), round_mm(disp.z)],
                        views: sol.views,
                        sigma_mm: Some(sigma.map(|s| round_mm(s.max(1e-5))).into()),
                        reproj_px: Some((sol.rms_px * 1e3).round() / 1e3),
                    });
                }
                Err(e) => tracing::debug!(tag = id, seq = set.seq, "tag not solved: {e}"),
            }
        }
        times.solve = t2.elapsed().as_secs_f64();

        // Region-of-interest windows for the next frame set.
        let solved: Vec<(u32, Pose)> = self.tags.iter().map(|(id, t)| (*id, t.pose)).collect();
        for (ci, d) in &detections {
            let cam = &mut self.cameras[*ci];
            cam.roi.observe(set.t_ns, cam.tracker.pose().as_ref(), &d.background, &d.specimen, &solved, size);
        }

        let net = self.net_deflection(&tags_out);
        let (load, stroke) = match self.utm.interpolate(set.t_ns) {
            Some((l, s)) => (Some(l), s),
            None => (None, None),
        };
        let reproj = if sq_n > 0.0 { Some(((sq_sum / sq_n).sqrt() * 1e3).round() / 1e3) } else { None };
        self.stats.sets += 1;
        let line = FeedLine {
            seq: set.seq,
            t_ns: set.t_ns,
            load_kn: load,
            stroke_mm: stroke,
            tags: tags_out,
            net_deflection_mm: net,
            reproj_px: reproj,
            cameras: health,
            utm: None,
            dropped_sets: None,
            latency_ms: None,
            gauges: Default::default(),
            clock_offset_ms: None,
        };
        let line = self.gauges.finish_line(line, &self.utm);
        (line, times)
    }

    /// Detects tags in every frame of the set: first the tracked tags of every camera are
    /// confirmed at their predicted places (no search; the tags of all cameras spread over
    /// the cores, so three cameras on two cores still balance), then the searches still
    /// needed — full frames, windows of tags not confirmed, sweep tiles — run one camera
    /// after another on the shared detector, each on the library's worker threads.
    fn detect(&mut self, set: &FrameSet) -> (Vec<(usize, CameraDetections)>, DetectParts) {
        let refine = self.detector.options().subpixel.clone();
        let mut jobs: Vec<SearchJob> = Vec::new();
        let mut planned: Vec<(usize, PlannedTag)> = Vec::new();
        for (fi, f) in set.frames.iter().enumerate() {
            let Some(cam) = self.cameras.get_mut(f.camera) else { continue };
            if jobs.iter().any(|j| j.camera == f.camera) {
                continue;
            }
            let mut job = SearchJob {
                camera: f.camera,
                frame: fi,
                found: Vec::new(),
                full: false,
                windows: Vec::new(),
                sweep: Vec::new(),
                decimate: 1.0,
            };
            match cam.roi.plan(f.t_ns, &f.image) {
                Plan::FullFrame => job.full = true,
                Plan::Track { decimate, tags, sweep } => {
                    job.sweep = sweep;
                    job.decimate = decimate;
                    planned.extend(tags.into_iter().map(|t| (jobs.len(), t)));
                }
            }
            jobs.push(job);
        }

        // Phase 1: tracked tags confirmed where they are predicted, in parallel.
        let (cameras, tracker) = (&self.cameras, &self.tag_tracker);
        let confirm = |(j, t): &(usize, PlannedTag)| {
            let c0 = thread_cpu_s();
            let cam = &cameras[jobs[*j].camera];
            let levels = cam.edge_levels.get(&(t.family, t.id)).copied().unwrap_or([None; 4]);
            let prediction = Prediction { family: t.family, id: t.id, corners: t.predicted, levels };
            let result = match &refine {
                Some(opts) => tracker.track(&set.frames[jobs[*j].frame].image, &prediction, Some(&cam.intrinsics), opts),
                None => Err(TrackMiss::Unsupported),
            };
            (result, thread_cpu_s() - c0)
        };
        let results: Vec<(Result<TrackedTag, TrackMiss>, f64)> =
            if planned.len() > 1 { planned.par_iter().map(confirm).collect() } else { planned.iter().map(confirm).collect() };
        let mut cpu = DetectParts::default();
        let mut weakest: Vec<Option<f64>> = vec![None; jobs.len()];
        for ((j, t), (result, cpu_s)) in planned.into_iter().zip(results) {
            cpu.tracking += cpu_s;
            match result {
                Ok(tag) => {
                    weakest[j] = Some(weakest[j].map_or(tag.contrast, |w: f64| w.min(tag.contrast)));
                    self.cameras[jobs[j].camera].edge_levels.insert((t.family, t.id), tag.levels);
                    jobs[j].found.push(tag.detection);
                }
                Err(_) => {
                    self.cameras[jobs[j].camera].edge_levels.remove(&(t.family, t.id));
                    jobs[j].windows.push(t.window);
                }
            }
        }
        for (job, weakest) in jobs.iter_mut().zip(weakest) {
            if weakest.is_some() {
                self.cameras[job.camera].tag_contrast = weakest;
            }
            job.windows = merge_rects(std::mem::take(&mut job.windows));
        }

        // Phase 2: the searches, one camera at a time on the shared detector.
        let mut out = Vec::with_capacity(jobs.len());
        for mut job in jobs {
            self.stats.tracked_tags += job.found.len() as u64;
            let cam = &self.cameras[job.camera];
            let frame = &set.frames[job.frame];
            let c0 = Instant::now();
            self.detector.set_intrinsics(Some(cam.intrinsics));
            if job.full {
                job.found = self.detector.detect(&frame.image);
                self.stats.full_frame_searches += 1;
                cpu.full_frame += c0.elapsed().as_secs_f64();
            } else {
                let found = search(&mut self.detector, cam, &frame.image, &job, &mut self.tile);
                job.found.extend(found);
                dedup_detections(&mut job.found);
                self.stats.window_searches += (job.windows.len() + job.sweep.len()) as u64;
                cpu.search += c0.elapsed().as_secs_f64();
            }
            out.push((job.camera, self.classify(job.found)));
        }
        (out, cpu)
    }

    /// Sorts detections into background and specimen tags (others are ignored).
    fn classify(&self, dets: Vec<Detection>) -> CameraDetections {
        let (bg_family, sp_family) = (self.config.background.family, self.config.specimen.family);
        let same_family = bg_family == sp_family;
        let mut out = CameraDetections { background: Vec::new(), specimen: Vec::new() };
        for d in dets {
            let is_sp = d.family == sp_family
                && self.specimen_ids.contains_key(&d.id)
                && !(same_family && self.background_world.contains_key(&d.id));
            let is_bg = d.family == bg_family && self.background_world.contains_key(&d.id);
            if is_sp {
                out.specimen.push(d);
            } else if is_bg {
                out.background.push(d);
            }
        }
        out
    }

    /// Mean downward displacement of midspan tags minus that of support tags.
    fn net_deflection(&self, tags: &[FeedTag]) -> Option<f64> {
        let down = |t: &FeedTag| -Vector3::from(t.disp_mm).dot(&self.up);
        let mean = |role: TagRole| {
            let v: Vec<f64> = tags.iter().filter(|t| self.specimen_ids.get(&t.id).copied().flatten() == Some(role)).map(down).collect();
            (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
        };
        Some(round_mm(mean(TagRole::Midspan)? - mean(TagRole::Support)?))
    }
}

/// Searches a camera's windows around tracked tags that could not be confirmed, and its
/// sweep tiles, with the job's quad decimation (at least the configured one) and with
/// low-contrast regions skipped (see [`SEARCH_CONTRAST_FRACTION`]). Window detections are
/// refined as usual. Tiles are searched without refinement; only the tags not already
/// found (confirmed, or in the windows) are then refined — corners as good as a full-frame
/// search's without refining every tracked tag twice. The detector's options are restored.
fn search(
    detector: &mut Detector,
    cam: &CameraState,
    image: &crate::frame::GrayImage,
    job: &SearchJob,
    scratch: &mut crate::frame::GrayImage,
) -> Vec<Detection> {
    let (windows, tiles, found, search_decimate) = (&job.windows, &job.sweep, &job.found, job.decimate);
    let mut out: Vec<Detection> = Vec::new();
    if windows.is_empty() && tiles.is_empty() {
        return out;
    }
    let configured = detector.options().clone();
    let min_diff = configured.min_white_black_diff as f64;
    let white_black_diff =
        cam.tag_contrast.map_or(min_diff, |c| (SEARCH_CONTRAST_FRACTION * c).clamp(min_diff, MAX_SEARCH_WHITE_BLACK_DIFF.max(min_diff)));
    let options = DetectorOptions {
        quad_decimate: configured.quad_decimate.max(search_decimate),
        min_white_black_diff: white_black_diff as u8,
        ..configured.clone()
    };
    if !windows.is_empty() && detector.set_options(options.clone()).is_ok() {
        for r in windows {
            out.extend(detector.detect_window(image, *r));
        }
    }
    if !tiles.is_empty() && detector.set_options(DetectorOptions { subpixel: None, ..options }).is_ok() {
        let mut new: Vec<Detection> = Vec::new();
        let known: Vec<Detection> = found.iter().chain(out.iter()).cloned().collect();
        for r in tiles {
            // The tile with the tags already found blanked out (see `roi::masked_tile`).
            masked_tile(image, *r, &known, scratch);
            let whole = Rect { x: 0, y: 0, width: r.width, height: r.height };
            for mut d in detector.detect_window(scratch, whole) {
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
                refine_corners_with(image, d, Some(&cam.intrinsics), opts);
            }
        }
        out.extend(new);
    }
    // The configured options were valid when the detector was built.
    let _ = detector.set_options(configured);
    out
}

/// Removes duplicate detections of one tag found in overlapping windows (keeps the one
/// with the highest decision margin).
fn dedup_detections(dets: &mut Vec<Detection>) {
    dets.sort_by(|a, b| (a.family.name(), a.id).cmp(&(b.family.name(), b.id)).then(b.decision_margin.total_cmp(&a.decision_margin)));
    dets.dedup_by(|b, a| a.family == b.family && a.id == b.id);
}
