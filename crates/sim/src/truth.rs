//! Ground truth of the simulated rig: the specimen tags' poses, the crack mouth opening,
//! the gauges' true values, and one [`SimTruthLine`] per frame set (`sim_truth.jsonl`).

use nalgebra::{Rotation3, Unit, Vector3};
use serde::{Deserialize, Serialize};

use tagdeflect_core::camera::Pose;
use tagdeflect_core::gauge::GaugeKind;
use tagdeflect_core::rig::TagRole;
use tagdeflect_core::tags::tag_corners;

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

    /// True values of the config's gauges at midspan deflection `d` (tags referenced to rest),
    /// computed here from the true tag poses with each gauge's definition written out plainly
    /// (SPEC, `[[gauge]]`), not with the product's `Gauges`: a wrong sign or term in the
    /// product's gauge arithmetic shows as an error against this truth. The world's up is
    /// +z; "down" is the displacement along −z.
    pub fn gauge_truth(&self, d: f64) -> std::collections::BTreeMap<String, f64> {
        use std::collections::HashMap;
        let config = self.sections();
        let rest: HashMap<u32, Pose> = self.tag_poses_at(0.0).into_iter().collect();
        let now: HashMap<u32, Pose> = self.tag_poses_at(d).into_iter().collect();
        let role: HashMap<u32, Option<TagRole>> = self.layout.specimen.iter().map(|s| (s.id, s.role)).collect();
        let down = |id: u32| rest[&id].translation.z - now[&id].translation.z;
        let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
        let mut out = std::collections::BTreeMap::new();
        for g in &config.gauges {
            let value = match g.kind {
                GaugeKind::NetDeflection => {
                    // The midspan tags' mean drop, less the supports' line (through the support
                    // tags' drops against their x at rest) at the midspan tags' mean x.
                    let with = |r: TagRole| -> Vec<u32> {
                        let mut ids: Vec<u32> = role.iter().filter(|(_, x)| **x == Some(r)).map(|(id, _)| *id).collect();
                        ids.sort_unstable();
                        ids
                    };
                    let (mid, sup) = (with(TagRole::Midspan), with(TagRole::Support));
                    if mid.is_empty() || sup.is_empty() {
                        continue;
                    }
                    let xs: Vec<f64> = sup.iter().map(|id| rest[id].translation.x).collect();
                    let ds: Vec<f64> = sup.iter().map(|id| down(*id)).collect();
                    let xm = mean(&mid.iter().map(|id| rest[id].translation.x).collect::<Vec<_>>());
                    let (sx, sd) = (mean(&xs), mean(&ds));
                    let sxx: f64 = xs.iter().map(|x| (x - sx).powi(2)).sum();
                    let sxd: f64 = xs.iter().zip(&ds).map(|(x, d)| (x - sx) * (d - sd)).sum();
                    let line = if sxx > 1e-9 { sd + sxd / sxx * (xm - sx) } else { sd };
                    mean(&mid.iter().map(|id| down(*id)).collect::<Vec<_>>()) - line
                }
                GaugeKind::Rotation => {
                    // The tag's rotation from rest, as an angle about the gauge's axis, mrad.
                    let id = g.tags[0];
                    let rel = now[&id].rotation * rest[&id].rotation.inverse();
                    let axis = Vector3::from(g.axis.unwrap_or([0.0, 1.0, 0.0])).normalize();
                    let (a, angle) = rel.axis_angle().map(|(a, t)| (a.into_inner(), t)).unwrap_or((axis, 0.0));
                    axis.dot(&a) * angle * 1e3
                }
                GaugeKind::Curvature => {
                    // Second divided difference of the upward displacements along x, 1/km.
                    let mut pts: Vec<(f64, f64)> = g.tags.iter().map(|id| (rest[id].translation.x, -down(*id))).collect();
                    pts.sort_by(|a, b| a.0.total_cmp(&b.0));
                    let [(xa, ya), (xb, yb), (xc, yc)] = [pts[0], pts[1], pts[2]];
                    2.0 * ((yc - yb) / (xc - xb) - (yb - ya) / (xb - xa)) / (xc - xa) * 1e6
                }
                GaugeKind::Opening => {
                    // The gauge point carried rigidly by each tag; their separation along the
                    // direction (from the first tag toward the second) against rest.
                    let (a, b) = (g.tags[0], g.tags[1]);
                    let at = Vector3::from(g.at_mm.unwrap_or([0.0; 3]));
                    let carried =
                        |id: u32| now[&id].rotation * (rest[&id].rotation.inverse() * (at - rest[&id].translation)) + now[&id].translation;
                    let mut dir = Vector3::from(g.direction.unwrap_or([1.0, 0.0, 0.0])).normalize();
                    if dir.dot(&(rest[&b].translation - rest[&a].translation)) < 0.0 {
                        dir = -dir;
                    }
                    dir.dot(&(carried(b) - carried(a)))
                }
                GaugeKind::Distance => {
                    let (a, b) = (g.tags[0], g.tags[1]);
                    (now[&b].translation - now[&a].translation).norm() - (rest[&b].translation - rest[&a].translation).norm()
                }
            };
            out.insert(g.name.clone(), value);
        }
        out
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
