//! The measurement of one frame set, in stages, each a method with a typed input and
//! result in its own file, [`Measurement::process`] the story that calls them:
//!
//! 1. `detect`: the tags in every camera's frame (each camera's `detect::CameraDetector`,
//!    cameras in parallel) → `Detected`;
//! 2. `pose`: each camera's held pose from its background tags, a camera that moved
//!    searched whole first → `CameraPoses` (the cameras' health);
//! 3. `solve`: each specimen tag over its views from the posed cameras → `SolvedTags`;
//! 4. `estimate`: each tag's position and σ from this set and its history (the temporal
//!    or the per-set estimator) → `Estimates`;
//! 5. `gauges`: the virtual gauges from the estimates → their readings;
//! 6. `line`: the feed line (tags, net deflection, load and stroke, the clock check).
//!
//! The measurement holds what carries over from one frame set to the next: the cameras'
//! poses and detectors (`camera`), each tag's history (warm start, first position,
//! filter), the pooled corner noise and the UTM history.
//!
//! **A camera that moved** (see `estimate::held_pose`, `detect::plan`): before a camera is
//! posed from a frame, its background tags are checked — most of the followed ones lost
//! (searched, not seen: fewer than two left, or fewer left than missing) or the bump
//! statistic above its threshold (an infinite shift included: the held pose cannot even
//! project them) — and if so that same frame, still at hand in the frame
//! set, is searched whole at the configured resolution ([`CameraDetector::search_again`](tagdeflect_detect::CameraDetector::search_again)) and
//! the camera is posed (and its specimen tags measured) from what that search found; the
//! windows had been placed where the tags were. While a re-pose is refused the search is
//! repeated only when the tags moved again in the image. A camera whose pose failed its
//! checks (`pose` refused by the held pose) has no pose: the frame set is solved without
//! its views, its health says `posed: false` (with `bumped`), and a WARN names it. One
//! background tag lost while the others are seen where they were (occluded, blurred) costs
//! no search in the frame: the held pose stands, checked by the tags left, and the
//! detector's sweeps and background searches look for the missing tag.

mod camera;
mod common_shift;
mod detect;
mod disp_sigma;
mod estimate;
mod gauges;
mod line;
mod model_drift;
mod pose;
mod rig;
mod solve;
mod stats;

use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;
use std::time::Instant;

use nalgebra::Vector3;
use tagdeflect_core::camera::Pose;
use tagdeflect_core::feed::FeedLine;
use tagdeflect_core::frame::FrameSet;
use tagdeflect_core::observed::{Observed, SeenTag};
use tagdeflect_core::rig::TagRole;
use tagdeflect_core::utm_sample::UtmHistory;
use tagdeflect_detect::apriltag::DetectError;
use tagdeflect_detect::RigDetectors;

use crate::PixelNoisePool;
use camera::RigCamera;
use estimate::TagHistory;
use gauges::LineGauges;

pub use model_drift::model_drift_switch;
pub use rig::MeasurementRig;
pub use stats::{MeasureStats, StageTimes};
pub use tagdeflect_detect::DetectParts;

/// The share of one full set's pixel-noise variance below which a temporal estimate's σ is
/// not given when two or more cameras saw the tag (σ ≥ 0.71× one set's). Measured on the
/// control test's renders (`control::partial_sets_…`, optics that blur before the pixels
/// integrate; 2026-12-05), net deflection errors within 2σ, live (smoothed): the posterior
/// alone 84–92 % of the lines, the whole set's variance 98–100 % (100 %), half of it 86–93 %
/// (93–97 %) — the nearest to the ≈ 95 % an honest σ gives. Per tag and axis on
/// the accuracy scenes: 93.5–96.9 % (whole: 95.6–98.0 %).
pub const FULL_SET_FLOOR_SHARE: f64 = 0.5;

/// The stateful frame-set processor shared by `replay`, `bench`, `run` and `demo`.
pub struct Measurement {
    config: MeasurementRig,
    up: Vector3<f64>,
    cameras: Vec<RigCamera>,
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
    /// Virtual gauges and the clock check (`estimate::gauges`, `estimate::clock_offset`).
    gauges: LineGauges,
    /// Time of the run's first frame set (the first-pose search's window, `pose`).
    first_set_t_ns: Option<i64>,
    /// The position error the edge model's error causes, pooled over the tags
    /// (`model_drift`: in the displacement's σ; in the position's with
    /// `TAGDEFLECT_SIGMA_WIDENING=on`).
    model_drift: model_drift::ModelDrift,
}

impl Measurement {
    /// Builds the processor; `roi_tracking = false` forces full-frame detection everywhere.
    pub fn new(config: &MeasurementRig, roi_tracking: bool) -> Result<Measurement, DetectError> {
        let rig = Arc::new(detect::rig_detectors(config)?);
        let cameras =
            config.cameras.iter().enumerate().map(|(i, cam)| RigCamera::new(cam, &config.measure, roi_tracking, i as u32)).collect();
        let n = config.cameras.len();
        Ok(Measurement {
            config: config.clone(),
            up: Vector3::from(config.world.up).normalize(),
            cameras,
            rig,
            background_world: config.background.tags.iter().map(|t| (t.id, t.corners_mm.map(Vector3::from))).collect(),
            specimen_ids: config.specimen.tags.iter().map(|t| (t.id, t.role)).collect(),
            tags: BTreeMap::new(),
            utm: utm_history(config.utm_poll_hz),
            noise: PixelNoisePool::default(),
            stats: MeasureStats::default(),
            last_seen: Vec::new(),
            pose_age_sets: vec![0; n],
            rejected_by_camera: vec![0; n],
            pose_epochs: vec![0; n],
            last_steps: None,
            gauges: LineGauges::new(config),
            first_set_t_ns: None,
            model_drift: model_drift::ModelDrift::default(),
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

    /// Processes one frame set into a feed line: detect → pose cameras → solve tags →
    /// temporal estimate → gauges → line.
    pub fn process(&mut self, set: &FrameSet) -> (FeedLine, StageTimes) {
        let mut times = StageTimes::default();
        let t0 = Instant::now();
        let mut detected = self.detect(set);
        times.detect = t0.elapsed().as_secs_f64();
        let t1 = Instant::now();
        let cameras = self.pose_cameras(set, &mut detected);
        times.pose = t1.elapsed().as_secs_f64();
        times.detect_parts = detected.parts;
        self.last_seen = detected.seen();
        let t2 = Instant::now();
        let solved = self.solve_tags(set.seq, &detected);
        let estimates = self.estimate_tags(set.t_ns, solved);
        self.stats.model_drift_px2 = self.model_drift.variance_px2();
        self.stats.white_noise_px2 = self.model_drift.white_variance_px2();
        times.solve = t2.elapsed().as_secs_f64();
        let gauges = self.gauges.process(&estimates.tags);
        (self.line(set, cameras, estimates, gauges), times)
    }
}

/// The UTM history of a run: no load across a UTM outage (at most five missed polls, and
/// 0.5 s, are bridged).
fn utm_history(poll_hz: Option<f64>) -> UtmHistory {
    UtmHistory::unbounded().with_max_gap(poll_hz.map_or(0, |hz| ((5.0 / hz).max(0.5) * 1e9) as i64))
}
