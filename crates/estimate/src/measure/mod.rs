//! The measurement of one frame set: detect → pose cameras → solve specimen tags → feed
//! line. Only orchestrates: each camera's detection is its `detect::CameraDetector`
//! (cameras in parallel); it holds the cameras' poses, each tag's warm start and first
//! position, and the UTM history.
//!
//! **A camera that moved** (see `estimate::held_pose`, `detect::plan`): before a camera is
//! posed from a frame, its background tags are checked — a followed one lost (searched, not
//! seen) or the bump statistic above its threshold (an infinite shift included: the held
//! pose cannot even project them) — and if so that same frame, still at hand in the frame
//! set, is searched whole at the configured resolution ([`CameraDetector::search_again`]) and
//! the camera is posed (and its specimen tags measured) from what that search found; the
//! windows had been placed where the tags were. While a re-pose is refused the search is
//! repeated only when the tags moved again in the image. A camera whose pose failed its
//! checks (`pose` refused by the held pose) has no pose: the frame set is solved without
//! its views, its health says `posed: false` (with `bumped`), and a WARN names it.

use nalgebra::{Matrix6, Vector3};
use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;
use std::time::Instant;

use crate::temporal::Estimator;
use crate::{solve_tag, BackgroundTagObservation, HeldCameraPose, PixelNoisePool, TagMotion, TagView};
use rayon::prelude::*;
use tagdeflect_core::camera::{CameraIntrinsics, Pose};
use tagdeflect_core::camera_config::CameraConfig;
use tagdeflect_core::feed::{round_mm, CameraHealth, FeedLine, FeedTag};
use tagdeflect_core::frame::FrameSet;
use tagdeflect_core::rig::TagRole;
use tagdeflect_core::rig::{BackgroundConfig, SpecimenConfig, WorldConfig};
use tagdeflect_core::tags::TagFamily;
use tagdeflect_core::utm_sample::UtmHistory;
use tagdeflect_detect::apriltag::{DetectError, Detector, DetectorOptions};
use tagdeflect_detect::refine::RefineOptions;
use tagdeflect_detect::{CameraDetections, CameraDetector, ConfirmOptions, DetectReport, RigDetectors, TagConfirmer, TagRoles};

pub use tagdeflect_detect::DetectParts;

/// The share of one full set's pixel-noise variance below which a temporal estimate's σ is
/// not given when two or more cameras saw the tag (σ ≥ 0.71× one set's). Measured on the
/// control test's renders (`control::partial_sets_…`, optics that blur before the pixels
/// integrate; 2026-12-05), net deflection errors within 2σ, live (smoothed): the posterior
/// alone 84–92 % of the lines, the whole set's variance 98–100 % (100 %), half of it 86–93 %
/// (93–97 %) — the nearest to the ≈ 95 % an honest σ gives. Per tag and axis on
/// the accuracy scenes: 93.5–96.9 % (whole: 95.6–98.0 %).
pub const FULL_SET_FLOOR_SHARE: f64 = 0.5;

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

/// Counters over a whole run.
#[derive(Debug, Clone, Default)]
pub struct MeasureStats {
    /// Frame sets processed.
    pub sets: u64,
    /// Full-frame detections run.
    pub full_frame_searches: u64,
    /// Window (region-of-interest) and sweep-tile detections run.
    pub window_searches: u64,
    /// Whole-frame searches run in the background (see `detect::camera_detector`).
    pub background_searches: u64,
    /// Tag views confirmed at their predicted place (no search needed).
    pub tracked_tags: u64,
    /// Of those, fitted on pixels selected in an earlier frame.
    pub reused_band_tags: u64,
    /// Specimen tag views rejected as outliers.
    pub rejected_views: u64,
    /// Camera bumps detected.
    pub bumps: u64,
    /// Whole-frame searches of a frame whose background tags were lost or jumped (in
    /// `full_frame_searches` too).
    pub moved_camera_searches: u64,
    /// Frame-set views of cameras left out because their re-pose failed its checks.
    pub refused_poses: u64,
    /// Tag solutions of partial sets referred to the tag's last full sets (temporal
    /// estimator, `estimate::partial`).
    pub referred_partial_views: u64,
}

struct CameraState {
    name: String,
    intrinsics: CameraIntrinsics,
    /// The camera's pose, held while static, re-posed after a bump.
    pose: HeldCameraPose,
    /// The camera's detection (plan, confirmation, searches, per-tag state).
    detector: CameraDetector,
}

/// What the feed needs of each specimen tag from one frame set to the next.
struct TagHistory {
    /// Last solution tag → world (warm start).
    pose: Pose,
    /// Centre in the first frame set that solved the tag.
    first_centre: Vector3<f64>,
    /// Recent multi-view solutions: the depth of a monocular view (see `solve::motion`;
    /// the per-set estimator).
    motion: TagMotion,
    /// The temporal estimator's state (see `estimate::temporal`).
    filter: Option<crate::temporal::TagFilter>,
    /// How many cameras usually see the tag (a set with fewer is partial).
    usual_views: crate::temporal::UsualViews,
    /// The pixel-noise covariance of the tag's last full set's solve, mm².
    full_noise: Option<nalgebra::Matrix3<f64>>,
    /// The camera poses' part of the last full set's covariance, mm² (the absolute σ of a
    /// position referred to the full sets).
    full_pose_cov: Option<nalgebra::Matrix3<f64>>,
    /// The last full sets' views (a partial set is referred to them: `estimate::partial`).
    recent_full: crate::partial::RecentFull,
}

/// What the net deflection needs of one solved tag: its downward-relevant displacement
/// covariance (pixel noise only, mm²) and its rate (mm/s) when the temporal estimator runs.
struct NetInput {
    cov: nalgebra::Matrix3<f64>,
    rate: Option<Vector3<f64>>,
}

/// A tag detected in one camera's frame of the last frame set (what the live page outlines
/// on the camera thumbnails; see [`Measurement::last_seen`]).
#[derive(Debug, Clone, PartialEq)]
pub struct SeenTag {
    /// Tag family.
    pub family: TagFamily,
    /// Tag id within the family.
    pub id: u32,
    /// A specimen tag (else a background tag).
    pub specimen: bool,
    /// Corners in the frame, pixels (OpenCV convention), the detector's order.
    pub corners: [nalgebra::Point2<f64>; 4],
}

/// What the measurement saw in a frame set, for the sinks that show it (the live page's
/// thumbnails and camera poses): part of its output, like the feed line.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Observed {
    /// The tags detected in each camera's frame, as (camera index, tags); cameras without a
    /// frame in the set are absent.
    pub seen: Vec<(usize, Vec<SeenTag>)>,
    /// Each camera's pose (world → camera) after the set, `None` until posed.
    pub camera_poses: Vec<Option<Pose>>,
}

/// The live page's view of one camera's detections (see [`SeenTag`]).
fn seen_tags(d: &CameraDetections) -> Vec<SeenTag> {
    let tag = |t: &tagdeflect_detect::Detection, specimen: bool| SeenTag { family: t.family, id: t.id, specimen, corners: t.corners };
    d.specimen.iter().map(|t| tag(t, true)).chain(d.background.iter().map(|t| tag(t, false))).collect()
}

/// What a [`Measurement`] is built from: the rig it measures and the sections it owns
/// (`[measure]`, `[[gauge]]`, `[clock_check]`), each already validated.
#[derive(Debug, Clone, PartialEq)]
pub struct MeasurementConfig {
    /// `[world]`.
    pub world: WorldConfig,
    /// The cameras, in config order (intrinsics, optional fixed poses).
    pub cameras: Vec<CameraConfig>,
    /// `[background]`.
    pub background: BackgroundConfig,
    /// `[specimen]`.
    pub specimen: SpecimenConfig,
    /// `[measure]`.
    pub measure: crate::measure_config::MeasureConfig,
    /// `[[gauge]]`.
    pub gauges: Vec<crate::gauges::GaugeConfig>,
    /// `[clock_check]`.
    pub clock_check: Option<crate::clock_offset::ClockCheckConfig>,
    /// The UTM's polling rate when one is configured, Hz: load is not interpolated across
    /// a gap longer than five polling periods (at least 0.5 s).
    pub utm_poll_hz: Option<f64>,
}

/// The stateful frame-set processor shared by `replay`, `bench`, `run` and `demo`.
pub struct Measurement {
    config: MeasurementConfig,
    up: Vector3<f64>,
    cameras: Vec<CameraState>,
    /// What the cameras' detectors share: the one AprilTag library (its tag36h11
    /// decoding table takes ~37 MB), the confirmer, the tags' roles.
    rig: Arc<RigDetectors>,
    background_world: HashMap<u32, [Vector3<f64>; 4]>,
    specimen_ids: HashMap<u32, Option<TagRole>>,
    tags: BTreeMap<u32, TagHistory>,
    utm: UtmHistory,
    /// Pooled specimen corner noise, px (scales every tag's σ).
    noise: PixelNoisePool,
    stats: MeasureStats,
    /// Tags detected per camera in the last frame set (the live page's thumbnails).
    last_seen: Vec<(usize, Vec<SeenTag>)>,
    /// Per camera: frame sets since its pose was last checked against background tags, and
    /// specimen views rejected as outliers (cumulative; logged as a summary by live runs).
    pose_age_sets: Vec<u64>,
    rejected_by_camera: Vec<u64>,
    /// Per camera: a counter raised whenever its pose was re-made or refused (a bump), so
    /// that views kept from before are not read with the new pose (see `estimate::partial`).
    pose_epochs: Vec<u64>,
    /// Each tag's filter step of the last frame set, kept for a smoother when asked
    /// ([`Measurement::keep_steps`]).
    last_steps: Option<Vec<crate::smooth::TagStep>>,
    /// Virtual gauges and the clock check (`solve::gauges`, `solve::clock_offset`).
    gauges: crate::gauges::LineGauges,
}

impl Measurement {
    /// Builds the processor; `roi_tracking = false` forces full-frame detection everywhere.
    pub fn new(config: &MeasurementConfig, roi_tracking: bool) -> Result<Measurement, DetectError> {
        let families: Vec<TagFamily> = if config.background.family == config.specimen.family {
            vec![config.background.family]
        } else {
            vec![config.specimen.family, config.background.family]
        };
        let opts = DetectorOptions {
            quad_decimate: config.measure.quad_decimate,
            // One thread per search: searches run side by side on several C workers (cameras
            // in parallel) instead of on the library's own pool, whose every phase waits for
            // its slowest thread — on a busy machine, for a thread the scheduler put aside.
            nthreads: 1,
            subpixel: config.measure.refine_corners.then(RefineOptions::default),
            ..DetectorOptions::for_families(&families)
        };
        // A worker per thread of the pool and one per camera for its background search.
        let workers = (config.measure.detector_threads as usize).max(rayon::current_num_threads()) + config.cameras.len();
        let library = Detector::with_workers(opts, workers)?;
        let mut cameras = Vec::new();
        for cam in &config.cameras {
            let intrinsics = cam.intrinsics();
            let fixed = cam.rvec.zip(cam.tvec_mm).map(|(r, t)| Pose::from_rvec_tvec(r, t));
            let phase = cameras.len() as u32;
            cameras.push(CameraState {
                name: cam.name.clone(),
                intrinsics,
                pose: HeldCameraPose::with_options(
                    intrinsics,
                    fixed,
                    crate::HeldPoseOptions { drift: crate::DriftConfig::from_measure(&config.measure), ..Default::default() },
                ),
                detector: CameraDetector::new(
                    intrinsics,
                    roi_tracking && config.measure.roi_tracking,
                    config.measure.full_search_interval_s,
                    phase,
                ),
            });
        }
        let roles = TagRoles {
            background_family: config.background.family,
            background: config.background.tags.iter().map(|t| t.id).collect(),
            specimen_family: config.specimen.family,
            specimen: config.specimen.tags.iter().map(|t| t.id).collect(),
        };
        let confirmer = TagConfirmer::new(ConfirmOptions::default(), roles.known());
        let rig = Arc::new(RigDetectors { library, confirmer, roles });
        let background_world = config.background.tags.iter().map(|t| (t.id, t.corners_mm.map(Vector3::from))).collect();
        let specimen_ids = config.specimen.tags.iter().map(|t| (t.id, t.role)).collect();
        let up = Vector3::from(config.world.up).normalize();
        Ok(Measurement {
            config: config.clone(),
            up,
            cameras,
            rig,
            background_world,
            specimen_ids,
            tags: BTreeMap::new(),
            // No load across a UTM outage: at most five missed polls (and 0.5 s) are bridged.
            utm: UtmHistory::unbounded().with_max_gap(config.utm_poll_hz.map_or(0, |hz| ((5.0 / hz).max(0.5) * 1e9) as i64)),
            noise: PixelNoisePool::default(),
            stats: MeasureStats::default(),
            last_seen: Vec::new(),
            pose_age_sets: vec![0; config.cameras.len()],
            rejected_by_camera: vec![0; config.cameras.len()],
            pose_epochs: vec![0; config.cameras.len()],
            last_steps: None,
            gauges: crate::gauges::LineGauges::new(config),
        })
    }

    /// Keeps each tag's filter step of every frame set for a smoother ([`Self::last_steps`],
    /// [`Self::smoother`]); only the temporal estimator has steps.
    pub fn keep_steps(&mut self) {
        self.last_steps = Some(Vec::new());
    }

    /// The tags' filter steps of the last frame set (empty unless [`Self::keep_steps`]).
    pub fn last_steps(&self) -> &[crate::smooth::TagStep] {
        self.last_steps.as_deref().unwrap_or(&[])
    }

    /// A fixed-lag smoother for this rig's lines (`estimate::smooth`).
    pub fn smoother(&self, lag_sets: usize) -> crate::smooth::FixedLag {
        crate::smooth::FixedLag::new(lag_sets, self.up, self.specimen_ids.clone())
    }

    /// Runs every whole-frame search in its own frame set instead of in the background
    /// (the default in tracking mode; see `detect::camera_detector`).
    pub fn without_background_searches(mut self) -> Self {
        for cam in &mut self.cameras {
            cam.detector.set_background_searches(false);
        }
        self
    }

    /// Counters so far.
    pub fn stats(&self) -> &MeasureStats {
        &self.stats
    }

    /// The UTM history (the pipeline pushes samples into it).
    pub fn utm_mut(&mut self) -> &mut UtmHistory {
        &mut self.utm
    }

    /// Specimen tag views rejected as outliers so far, per camera.
    pub fn rejected_views_by_camera(&self) -> &[u64] {
        &self.rejected_by_camera
    }

    /// Current pose of each camera (world → camera), `None` until posed.
    pub fn camera_poses(&self) -> Vec<Option<Pose>> {
        self.cameras.iter().map(|c| c.pose.pose()).collect()
    }

    /// The tags detected in each camera's frame of the last frame set processed, as
    /// (camera index, tags); cameras without a frame in that set are absent.
    pub fn last_seen(&self) -> &[(usize, Vec<SeenTag>)] {
        &self.last_seen
    }

    /// What the last frame set processed showed ([`Observed`]).
    pub fn observed(&self) -> Observed {
        Observed { seen: self.last_seen.clone(), camera_poses: self.camera_poses() }
    }

    /// Processes one frame set into a feed line.
    pub fn process(&mut self, set: &FrameSet) -> (FeedLine, StageTimes) {
        let mut times = StageTimes::default();
        let t0 = Instant::now();
        let (mut detections, reports, mut cpu) = self.detect(set);
        times.detect = t0.elapsed().as_secs_f64();

        // Camera poses from the background tags.
        let t1 = Instant::now();
        let mut health = Vec::with_capacity(self.cameras.len());
        for (ci, cam) in self.cameras.iter_mut().enumerate() {
            let background_world = &self.background_world;
            let observations = |d: &CameraDetections| -> Vec<BackgroundTagObservation> {
                d.background
                    .iter()
                    .filter_map(|det| {
                        background_world.get(&det.id).map(|w| BackgroundTagObservation { id: det.id, pixels: det.corners, world: *w })
                    })
                    .collect()
            };
            // The camera moved (background tags lost or jumped): the same frame searched
            // whole before the camera is posed from it (see the module docs). The frame's
            // observations are made once and posed from, unless that search replaced them.
            let mut frame_obs = None;
            if let (Some(slot), Some(report)) = (detections.iter_mut().find(|(i, _)| *i == ci), reports[ci].as_ref()) {
                let threshold = cam.pose.bump_threshold_px();
                let above = |s: f64| s.is_nan() || s > threshold;
                let obs = observations(&slot.1);
                let jumped = cam.pose.preview_shift_px(set.t_ns, &obs).is_some_and(above);
                frame_obs = Some(obs);
                let moved_again = report.background.shift_px.is_some_and(above);
                let search = cam.pose.estimated()
                    && (cam.pose.pose().is_some() || cam.pose.refused().is_some())
                    && report.full_frame_searches == 0
                    && (report.background.lost || (jumped && (cam.pose.refused().is_none() || moved_again)));
                if let Some(frame) = set.frames.iter().find(|f| f.camera == ci).filter(|_| search) {
                    let c0 = Instant::now();
                    let (again, r) = cam.detector.search_again(frame.t_ns, &frame.image, &self.rig);
                    tracing::warn!(
                        camera = %cam.name,
                        seq = set.seq,
                        lost = report.background.lost,
                        jumped,
                        background_tags = again.background.len(),
                        "background tags lost or jumped: the frame searched whole before posing"
                    );
                    self.stats.full_frame_searches += r.full_frame_searches;
                    self.stats.moved_camera_searches += 1;
                    cpu.full_frame += c0.elapsed().as_secs_f64();
                    slot.1 = again;
                    frame_obs = None;
                }
            }
            let det = detections.iter().find(|(i, _)| *i == ci).map(|(_, d)| d);
            let mut h = CameraHealth {
                name: cam.name.clone(),
                frame: det.is_some(),
                background_tags: 0,
                specimen_tags: 0,
                pose_reproj_px: None,
                posed: cam.pose.pose().is_some(),
                ..CameraHealth::default()
            };
            let mut checked = false;
            if let Some(d) = det {
                h.background_tags = d.background.len();
                h.specimen_tags = d.specimen.len();
                let obs = frame_obs.take().unwrap_or_else(|| observations(d));
                // Every line the held pose logs names its camera (the span's field).
                let status = tracing::info_span!("pose", camera = %cam.name).in_scope(|| cam.pose.update_at(set.t_ns, &obs));
                if let Some(d) = status.drift {
                    h.drift_deg = Some((d.angle_deg() * 1e6).round() / 1e6);
                    h.drift_mm = Some(round_mm(d.shift_mm()));
                }
                h.posed = status.pose.is_some();
                h.pose_reproj_px = status.rms_px;
                h.bumped = status.bumped;
                checked = status.fixed || !status.stale;
                if status.refused.is_some() || status.bumped {
                    self.pose_epochs[ci] += 1;
                }
                if let Some(why) = &status.refused {
                    self.stats.refused_poses += 1;
                    tracing::warn!(camera = %cam.name, seq = set.seq, reason = %why, "camera moved and its pose failed the checks: the frame set is solved without it");
                } else if status.bumped {
                    self.stats.bumps += 1;
                    tracing::warn!(camera = %cam.name, seq = set.seq, "camera moved: background tags shifted in the image; re-posed");
                }
            }
            // A held pose that no background tag confirmed in this set is reported as stale.
            self.pose_age_sets[ci] = if checked { 0 } else { self.pose_age_sets[ci] + 1 };
            if h.posed && h.frame && !checked {
                (h.stale_pose, h.pose_age_sets) = (true, Some(self.pose_age_sets[ci]));
            }
            health.push(h);
        }
        times.pose = t1.elapsed().as_secs_f64();
        times.detect_parts = cpu;
        self.last_seen = detections.iter().map(|(ci, d)| (*ci, seen_tags(d))).collect();

        // Specimen tags over all views.
        let t2 = Instant::now();
        let mut views_by_tag: BTreeMap<u32, (Vec<TagView>, Vec<usize>)> = BTreeMap::new();
        for (ci, d) in &detections {
            let cam = &self.cameras[*ci];
            let Some(pose) = cam.pose.pose() else { continue };
            let cov: Option<Matrix6<f64>> = cam.pose.covariance();
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
        let mut partial_set = health.iter().any(|h| !h.frame);
        let mut net_inputs: HashMap<u32, NetInput> = HashMap::new();
        let cameras = &self.cameras;
        if let Some(steps) = self.last_steps.as_mut() {
            steps.clear();
        }
        for (id, (views, view_cameras)) in &views_by_tag {
            let warm = self.tags.get(id).map(|t| t.pose);
            match solve_tag(views, size, warm.as_ref(), pooled) {
                Ok(sol) => {
                    self.stats.rejected_views += sol.rejected_views.len() as u64;
                    for r in &sol.rejected_views {
                        self.rejected_by_camera[view_cameras[*r]] += 1;
                        tracing::debug!(tag = id, camera = %cameras[view_cameras[*r]].name, seq = set.seq, "specimen tag view rejected as an outlier (its corners disagree with the other views)");
                    }
                    self.noise.add_solution(&sol);
                    let n_res = 8.0 * sol.views as f64;
                    sq_sum += sol.rms_px * sol.rms_px * n_res;
                    sq_n += n_res;
                    let history = self.tags.entry(*id).or_insert(TagHistory {
                        pose: sol.tag_to_world,
                        first_centre: sol.centre_mm,
                        motion: TagMotion::default(),
                        filter: None,
                        usual_views: Default::default(),
                        full_noise: None,
                        full_pose_cov: None,
                        recent_full: Default::default(),
                    });
                    let partial = history.usual_views.observe(sol.views);
                    partial_set |= partial;
                    let (mut c, mut sigma) = (sol.centre_mm, sol.sigma_mm);
                    let mut pose = sol.tag_to_world;
                    let mut fused_cov = None;
                    let noise_cov: nalgebra::Matrix3<f64> = sol.noise_covariance.fixed_view::<3, 3>(3, 3).into_owned();
                    let mut net_in = NetInput { cov: noise_cov, rate: None };
                    match self.config.measure.estimator {
                        Estimator::PerSet => {
                            if sol.views >= 2 {
                                history.motion.observe(set.t_ns, c, sol.centre_covariance);
                            } else if let Some((fc, fcov)) = history.motion.fuse(set.t_ns, c, sol.centre_covariance) {
                                c = fc;
                                sigma = Vector3::new(fcov[(0, 0)].sqrt(), fcov[(1, 1)].sqrt(), fcov[(2, 2)].sqrt());
                                pose.translation = fc;
                                fused_cov = Some(fcov);
                                net_in.cov = fcov;
                            }
                        }
                        Estimator::Temporal => {
                            // A partial set is referred to the last full sets (their cameras'
                            // pose errors, not this subset's); a full set is kept for that.
                            let used: Vec<usize> =
                                view_cameras.iter().enumerate().filter(|(i, _)| !sol.rejected_views.contains(i)).map(|(_, c)| *c).collect();
                            let referred = if partial {
                                let view_of = |cam: usize, corners: [nalgebra::Point2<f64>; 4]| {
                                    let st: &CameraState = &cameras[cam];
                                    st.pose.pose().map(|p| TagView {
                                        intrinsics: st.intrinsics,
                                        camera_pose: p,
                                        camera_pose_covariance: st.pose.covariance(),
                                        corners,
                                    })
                                };
                                history.recent_full.refer(set.t_ns, c, &noise_cov, &used, &self.pose_epochs, size, pooled, view_of)
                            } else {
                                history.recent_full.push(
                                    set.t_ns,
                                    views,
                                    view_cameras,
                                    &sol.rejected_views,
                                    &self.pose_epochs,
                                    &sol.tag_to_world,
                                );
                                history.full_pose_cov = Some(sol.centre_covariance - noise_cov);
                                None
                            };
                            if referred.is_some() {
                                self.stats.referred_partial_views += 1;
                            }
                            // What this set measures of the tag and how well: referred, the
                            // pixel noise alone; otherwise (a partial set with nothing kept)
                            // the camera poses' part too.
                            let (z, r_partial) = match &referred {
                                Some(r) => (r.centre_mm, r.covariance),
                                None => (c, sol.centre_covariance),
                            };
                            // A referred set is pixel noise alone, like a full one: the filter
                            // takes it as such (a jump included) when two cameras or more saw
                            // the tag. Seen by one camera, it keeps that camera's own corner
                            // bias and a monocular depth: taken as partial (down-weighted
                            // beyond the gate, never a jump, no adaptation) — as a full set one
                            // such set moved a sharp scene's net deflection by 16 µm and a 2-s
                            // one-camera outage drifted by 9 µm (docs/control.md). An
                            // unreferred partial set is taken with its camera poses' part and
                            // never as a jump.
                            let u = match history.filter.as_mut() {
                                Some(f) if referred.is_some() => f.update(set.t_ns, z, &r_partial, &r_partial, used.len() == 1),
                                Some(f) => f.update(set.t_ns, z, &noise_cov, &r_partial, partial),
                                None => {
                                    let f = crate::temporal::TagFilter::new(self.config.measure.temporal(), set.t_ns, c, &noise_cov);
                                    let u = crate::temporal::Update {
                                        centre: f.centre(),
                                        covariance: f.covariance(),
                                        rate: f.rate(),
                                        partial,
                                        jump: false,
                                    };
                                    history.filter = Some(f);
                                    u
                                }
                            };
                            c = u.centre;
                            // The feed's σ of the position adds the camera poses' part back
                            // (the full sets' when the set was referred to them).
                            let pose_part = match (&referred, history.full_pose_cov) {
                                (Some(_), Some(p)) => p,
                                _ => sol.centre_covariance - noise_cov,
                            };
                            pose.translation = c;
                            fused_cov = Some(u.covariance);
                            // The σ given out has a floor: a share of one full set's pixel-noise
                            // variance ([`FULL_SET_FLOOR_SHARE`]; all of it when one camera
                            // saw the tag). The errors of consecutive sets are partly
                            // correlated (the same held poses, a corner bias that changes
                            // with the tag's sub-pixel place; seen by one camera, the tag's
                            // apparent size, which its depth comes from), and the filter's gain
                            // on white noise does not shrink that part.
                            if !partial {
                                history.full_noise = Some(noise_cov);
                            }
                            // A partial set's floor is what it measured with: referred, its
                            // pixel noise and the offset's; else its full covariance (camera
                            // poses included: the held poses' errors no longer cancel).
                            let floor = if partial {
                                r_partial
                            } else {
                                let share = if used.len() > 1 { FULL_SET_FLOOR_SHARE } else { 1.0 };
                                history.full_noise.unwrap_or(noise_cov) * share
                            };
                            let up = self.up;
                            let var = |m: &nalgebra::Matrix3<f64>| (up.transpose() * m * up)[(0, 0)];
                            let cov = if var(&u.covariance) < var(&floor) { floor } else { u.covariance };
                            // The feed's σ of the position adds the camera poses' part back
                            // (an unreferred partial set's floor holds it already).
                            let absolute = if partial && referred.is_none() && cov == floor { cov } else { cov + pose_part };
                            sigma = Vector3::new(absolute[(0, 0)], absolute[(1, 1)], absolute[(2, 2)]).map(|v| v.max(0.0).sqrt());
                            net_in = NetInput { cov, rate: Some(u.rate) };
                            if let (Some(steps), Some(f)) = (self.last_steps.as_mut(), history.filter.as_ref()) {
                                steps.push(crate::smooth::TagStep { id: *id, step: *f.last_step(), pose_part, floor });
                            }
                        }
                    }
                    net_inputs.insert(*id, net_in);
                    self.gauges.add_tag(*id, &pose, &sol, fused_cov);
                    history.pose = pose;
                    let disp = c - history.first_centre;
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

        let net = self.net_deflection(&tags_out, &net_inputs);
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
            net_deflection_mm: net.map(|n| n.0),
            net_deflection_sigma_mm: net.map(|n| round_mm(n.1.max(1e-5))),
            net_deflection_rate_mm_per_min: net.and_then(|n| n.2).map(|r| (r * 60.0 * 1e6).round() / 1e6),
            partial_set,
            smoothed: false,
            reproj_px: reproj,
            cameras: health,
            utm: None,
            dropped_sets: None,
            latency_ms: None,
            mqtt_dropped: None,
            recording: None,
            recorder_dropped: None,
            gauges: Default::default(),
            clock_offset_ms: None,
            test: None,
            events: Vec::new(),
        };
        let line = self.gauges.finish_line(line, &self.utm);
        (line, times)
    }

    /// Detects tags in every frame of the set, the cameras in parallel (each camera's
    /// [`CameraDetector`]; the first frame of a camera in the set counts).
    #[allow(clippy::type_complexity)]
    fn detect(&mut self, set: &FrameSet) -> (Vec<(usize, CameraDetections)>, Vec<Option<DetectReport>>, DetectParts) {
        let mut frame_of: Vec<Option<usize>> = vec![None; self.cameras.len()];
        let mut order = Vec::new();
        for (fi, f) in set.frames.iter().enumerate() {
            if let Some(slot) = frame_of.get_mut(f.camera) {
                if slot.is_none() {
                    *slot = Some(fi);
                    order.push(f.camera);
                }
            }
        }
        let rig = &self.rig;
        let mut results: Vec<Option<(CameraDetections, DetectReport)>> = self
            .cameras
            .par_iter_mut()
            .zip(frame_of.par_iter())
            .map(|(cam, fi)| fi.map(|fi| cam.detector.detect(set.frames[fi].t_ns, &set.frames[fi].image, rig)))
            .collect();
        let mut parts = DetectParts::default();
        let mut out = Vec::with_capacity(order.len());
        let mut reports = vec![None; self.cameras.len()];
        for ci in order {
            let Some((dets, report)) = results[ci].take() else { continue };
            reports[ci] = Some(report);
            parts.add(&report.parts);
            self.stats.full_frame_searches += report.full_frame_searches;
            self.stats.window_searches += report.window_searches;
            self.stats.background_searches += report.background_searches;
            self.stats.tracked_tags += report.confirmed_tags;
            self.stats.reused_band_tags += report.reused_bands;
            out.push((ci, dets));
        }
        (out, reports, parts)
    }

    /// Mean downward displacement of midspan tags minus that of support tags, its 1-σ (mm;
    /// the tags' displacement covariances, tags independent) and its rate (mm/s, when every
    /// tag has one).
    fn net_deflection(&self, tags: &[FeedTag], inputs: &HashMap<u32, NetInput>) -> Option<(f64, f64, Option<f64>)> {
        let down = |t: &FeedTag| -Vector3::from(t.disp_mm).dot(&self.up);
        let mut value = 0.0;
        let mut var = 0.0;
        let mut rate = Some(0.0);
        for (role, sign) in [(TagRole::Midspan, 1.0), (TagRole::Support, -1.0)] {
            let members: Vec<&FeedTag> = tags.iter().filter(|t| self.specimen_ids.get(&t.id).copied().flatten() == Some(role)).collect();
            if members.is_empty() {
                return None;
            }
            let w = sign / members.len() as f64;
            for t in members {
                value += w * down(t);
                match inputs.get(&t.id) {
                    Some(i) => {
                        var += w * w * (self.up.transpose() * i.cov * self.up)[(0, 0)];
                        rate = rate.zip(i.rate).map(|(r, v)| r - w * v.dot(&self.up));
                    }
                    None => rate = None,
                }
            }
        }
        Some((round_mm(value), var.max(0.0).sqrt(), rate))
    }
}
