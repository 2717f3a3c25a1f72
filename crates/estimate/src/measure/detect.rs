//! Stage 1, detect: the tags in every frame of the set, the cameras in parallel (each
//! camera's [`CameraDetector`](tagdeflect_detect::CameraDetector)).

use rayon::prelude::*;
use tagdeflect_core::frame::FrameSet;
use tagdeflect_core::observed::SeenTag;
use tagdeflect_core::tags::TagFamily;
use tagdeflect_detect::apriltag::{DetectError, Detector, DetectorOptions};
use tagdeflect_detect::refine::RefineOptions;
use tagdeflect_detect::{CameraDetections, ConfirmOptions, DetectParts, DetectReport, Detection, RigDetectors, TagConfirmer, TagRoles};

use super::{Measurement, MeasurementRig};

/// What the detect stage found in a frame set.
pub(super) struct Detected {
    /// Each camera's detections as (camera index, detections), in the order of the cameras'
    /// first frames in the set; cameras without a frame are absent.
    pub(super) cameras: Vec<(usize, CameraDetections)>,
    /// Each camera's detection report, by camera index (`None` without a frame).
    pub(super) reports: Vec<Option<DetectReport>>,
    /// Detection time by kind of work (the pose stage adds its whole-frame searches).
    pub(super) parts: DetectParts,
}

impl Detected {
    /// Camera `ci`'s detections, if it had a frame.
    pub(super) fn of(&self, ci: usize) -> Option<&CameraDetections> {
        self.cameras.iter().find(|(i, _)| *i == ci).map(|(_, d)| d)
    }

    /// What the live page outlines of each camera's detections ([`SeenTag`]).
    pub(super) fn seen(&self) -> Vec<(usize, Vec<SeenTag>)> {
        self.cameras.iter().map(|(ci, d)| (*ci, seen_tags(d))).collect()
    }
}

impl Measurement {
    /// Detects tags in every frame of the set, the cameras in parallel (the first frame of a
    /// camera in the set counts).
    pub(super) fn detect(&mut self, set: &FrameSet) -> Detected {
        let (frame_of, order) = first_frames(set, self.cameras.len());
        let rig = &self.rig;
        let mut results: Vec<Option<(CameraDetections, DetectReport)>> = self
            .cameras
            .par_iter_mut()
            .zip(frame_of.par_iter())
            .map(|(cam, fi)| fi.map(|fi| cam.detector.detect(set.frames[fi].t_ns, &set.frames[fi].image, rig)))
            .collect();
        let mut detected =
            Detected { cameras: Vec::with_capacity(order.len()), reports: vec![None; self.cameras.len()], parts: DetectParts::default() };
        for ci in order {
            let Some((dets, report)) = results[ci].take() else { continue };
            detected.reports[ci] = Some(report);
            detected.parts.add(&report.parts);
            self.stats.add_detection(&report);
            detected.cameras.push((ci, dets));
        }
        detected
    }
}

/// Each camera's first frame in the set (index into `set.frames`, by camera index) and the
/// cameras in the order of those frames.
fn first_frames(set: &FrameSet, cameras: usize) -> (Vec<Option<usize>>, Vec<usize>) {
    let mut frame_of: Vec<Option<usize>> = vec![None; cameras];
    let mut order = Vec::new();
    for (fi, f) in set.frames.iter().enumerate() {
        if let Some(slot) = frame_of.get_mut(f.camera) {
            if slot.is_none() {
                *slot = Some(fi);
                order.push(f.camera);
            }
        }
    }
    (frame_of, order)
}

/// What the cameras' detectors share: the one AprilTag library (its tag36h11 decoding table
/// takes ~37 MB), the confirmer, the tags' roles.
pub(super) fn rig_detectors(config: &MeasurementRig) -> Result<RigDetectors, DetectError> {
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
    let roles = TagRoles {
        background_family: config.background.family,
        background: config.background.tags.iter().map(|t| t.id).collect(),
        specimen_family: config.specimen.family,
        specimen: config.specimen.tags.iter().map(|t| t.id).collect(),
    };
    let confirmer = TagConfirmer::new(ConfirmOptions::default(), roles.known());
    Ok(RigDetectors { library, confirmer, roles })
}

/// The live page's view of one camera's detections (see [`SeenTag`]).
fn seen_tags(d: &CameraDetections) -> Vec<SeenTag> {
    let tag = |t: &Detection, specimen: bool| SeenTag { family: t.family, id: t.id, specimen, corners: t.corners };
    d.specimen.iter().map(|t| tag(t, true)).chain(d.background.iter().map(|t| tag(t, false))).collect()
}
