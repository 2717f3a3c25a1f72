//! Ground truth of the simulated rig: the specimen tags' poses, the crack mouth opening,
//! the gauges' true values, and one [`SimTruthLine`] per frame set (`sim_truth.jsonl`).

use nalgebra::{Rotation3, Unit, Vector3};
use serde::{Deserialize, Serialize};

use tagdeflect_core::camera::Pose;
use tagdeflect_core::rig::TagRole;
use tagdeflect_core::tags::tag_corners;
use tagdeflect_estimate::gauges::{GaugeTag, Gauges};

use super::law::SimTest;
use super::SimRig;

/// One camera's true pose in a [`SimTruthLine`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SimTruthCamera {
    /// Camera name.
    pub name: String,
    /// Rotation vector, `x_cam = R x_world + t`.
    pub rvec: [f64; 3],
    /// Translation, mm.
    pub tvec_mm: [f64; 3],
    /// True once the camera has been bumped.
    pub bumped: bool,
    /// This camera's frame time in this set; absent when the frame was dropped.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frame_t_ns: Option<i64>,
    /// True when this frame carries motion blur.
    #[serde(default)]
    pub motion_blur: bool,
    /// Specimen tag hidden from this camera in this frame.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub hidden_tag: Option<u32>,
}

/// One specimen tag's true pose in a [`SimTruthLine`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SimTruthTag {
    /// Specimen tag id.
    pub id: u32,
    /// Centre of the black square, world, mm.
    pub center_mm: [f64; 3],
    /// Rotation vector of tag frame → world.
    pub rvec: [f64; 3],
    /// Corners of the black square, world, mm (SPEC order).
    pub corners_mm: [[f64; 3]; 4],
    /// Role, when it has one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub role: Option<TagRole>,
}

/// One line of `sim_truth.jsonl`: everything true about one frame set.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SimTruthLine {
    /// Frame-set number from 0.
    pub set: u64,
    /// Nominal time of the set (as in truth.jsonl), ns.
    pub t_ns: i64,
    /// Midspan deflection of the neutral axis, mm, positive downward.
    pub midspan_deflection_mm: f64,
    /// Net deflection as the feed defines it (mean downward displacement of the midspan
    /// tags minus that of the support tags), mm; absent without both roles.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub net_deflection_mm: Option<f64>,
    /// True load, kN.
    #[serde(rename = "load_kN")]
    pub load_kn: f64,
    /// True stroke, mm.
    pub stroke_mm: f64,
    /// Every camera's pose and frame facts.
    pub cameras: Vec<SimTruthCamera>,
    /// Every specimen tag's pose.
    pub tags: Vec<SimTruthTag>,
    /// Crack mouth opening at the bottom face (notched test), mm.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cmod_mm: Option<f64>,
    /// True values of the config's gauges (same names and units as the feed's `gauges`),
    /// from the true tag poses with the tags at rest as reference.
    #[serde(default, skip_serializing_if = "std::collections::BTreeMap::is_empty")]
    pub gauges: std::collections::BTreeMap<String, f64>,
}

impl SimRig {
    /// Pose (tag frame → world) of every specimen tag at `t_ns`, with its id.
    pub(crate) fn tag_poses(&self, t_ns: i64) -> Vec<(u32, Pose)> {
        self.tag_poses_at(self.midspan_deflection(t_ns))
    }

    /// Pose (tag frame → world) of every specimen tag at midspan deflection `d` (mm).
    pub(crate) fn tag_poses_at(&self, d: f64) -> Vec<(u32, Pose)> {
        let zc = 0.5 * self.params.beam_height_mm;
        let motion = self.motion_at(d);
        // Tag axes at rest: x → world x, y → world z, z (out of the face) → world -y.
        let r0 = Rotation3::from_matrix_unchecked(nalgebra::Matrix3::new(1.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 1.0, 0.0));
        let toward_viewer = Unit::new_normalize(-Vector3::y());
        self.layout
            .specimen
            .iter()
            .map(|s| {
                let (dx, dz, rot) = motion.displace(s.x, s.zeta);
                let r = Rotation3::from_axis_angle(&toward_viewer, rot) * r0;
                (s.id, Pose { rotation: r, translation: Vector3::new(s.x + dx, 0.0, zc + s.zeta + dz) })
            })
            .collect()
    }

    /// Centre of every specimen tag's black square at `t_ns` (world, mm), with its id.
    pub fn tag_centres(&self, t_ns: i64) -> Vec<(u32, Vector3<f64>)> {
        self.tag_poses(t_ns).into_iter().map(|(id, p)| (id, p.translation)).collect()
    }

    /// World corners (SPEC order) of every specimen tag's black square at `t_ns`.
    pub fn tag_corners_world(&self, t_ns: i64) -> Vec<(u32, [Vector3<f64>; 4])> {
        let s = self.params.specimen_tag_mm;
        self.tag_poses(t_ns).into_iter().map(|(id, p)| (id, tag_corners(s).map(|c| p.transform(&c)))).collect()
    }

    /// Crack mouth opening (notched test): the change of the distance between the notch's
    /// two edges at the bottom face, mm.
    pub fn cmod_at(&self, d: f64) -> Option<f64> {
        if self.params.test != SimTest::ThreePointNotched {
            return None;
        }
        let m = self.motion_at(d);
        let (w, hh) = (0.5 * self.params.notch_width_mm, 0.5 * self.params.beam_height_mm);
        let (dl, ..) = m.displace(-w, -hh);
        let (dr, ..) = m.displace(w, -hh);
        Some(dr - dl)
    }

    /// True values of the config's gauges at midspan deflection `d` (tags referenced to rest).
    pub fn gauge_truth(&self, d: f64) -> std::collections::BTreeMap<String, f64> {
        let config = self.sections();
        let mut gauges = Gauges::new(&config.gauges, config.world.up, &config.specimen);
        let exact = |poses: Vec<(u32, Pose)>| poses.into_iter().map(|(id, p)| GaugeTag::exact(id, p)).collect::<Vec<_>>();
        gauges.evaluate(&exact(self.tag_poses_at(0.0)));
        gauges.evaluate(&exact(self.tag_poses_at(d))).into_iter().map(|(k, v)| (k, v.value)).collect()
    }

    /// Everything true about frame set `k` (the `sim_truth.jsonl` line).
    pub fn truth_line(&self, k: u64) -> SimTruthLine {
        let t = self.set_time_ns(k);
        let d = self.midspan_deflection(t);
        let utm = self.utm_sample(t);
        let size = self.params.specimen_tag_mm;
        let rest: Vec<(u32, Vector3<f64>)> = self.tag_poses_at(0.0).into_iter().map(|(id, p)| (id, p.translation)).collect();
        let poses = self.tag_poses(t);
        let mut mid = Vec::new();
        let mut sup = Vec::new();
        let tags = poses
            .iter()
            .zip(&self.layout.specimen)
            .zip(&rest)
            .map(|(((id, pose), s), (_, c0))| {
                let down = c0.z - pose.translation.z;
                match s.role {
                    Some(TagRole::Midspan) => mid.push(down),
                    Some(TagRole::Support) => sup.push(down),
                    None => {}
                }
                let v = pose.rotation.scaled_axis();
                SimTruthTag {
                    id: *id,
                    center_mm: [pose.translation.x, pose.translation.y, pose.translation.z],
                    rvec: [v.x, v.y, v.z],
                    corners_mm: tag_corners(size).map(|c| {
                        let w = pose.transform(&c);
                        [w.x, w.y, w.z]
                    }),
                    role: s.role,
                }
            })
            .collect();
        let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
        let net = (!mid.is_empty() && !sup.is_empty()).then(|| mean(&mid) - mean(&sup));
        let cameras = (0..self.camera_count())
            .map(|c| {
                let pose = self.camera_pose(c, t);
                SimTruthCamera {
                    name: self.layout.names[c].clone(),
                    rvec: pose.rvec(),
                    tvec_mm: [pose.translation.x, pose.translation.y, pose.translation.z],
                    bumped: self.pose_epoch(c, t) == 1,
                    frame_t_ns: self.frame_time_ns(c, k),
                    motion_blur: self.has_motion_blur(c, k as i64),
                    hidden_tag: self.hidden_tag(c, k as i64),
                }
            })
            .collect();
        SimTruthLine {
            set: k,
            t_ns: t,
            midspan_deflection_mm: d,
            net_deflection_mm: net,
            load_kn: utm.load_kn,
            stroke_mm: utm.stroke_mm.unwrap_or(0.0),
            cameras,
            tags,
            cmod_mm: self.cmod_at(d),
            gauges: if self.real_test() { self.gauge_truth(d) } else { Default::default() },
        }
    }
}
