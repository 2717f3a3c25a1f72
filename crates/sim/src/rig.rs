//! [`SimRig`]: the simulated rig built from [`SimParams`] — beam mechanics over time,
//! camera poses (with an optional bump), the scene tracer, cached rendering, ground truth
//! and the UTM model.

use std::sync::{Arc, Mutex, OnceLock};

use nalgebra::{Rotation3, Unit, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};

use tagdeflect_core::camera::{CameraIntrinsics, Pose};
use tagdeflect_core::rig::{BackgroundConfig, BackgroundTag, SpecimenConfig, SpecimenTag, TagRole, WorldConfig};
use tagdeflect_core::beam::BeamConfig;
use tagdeflect_core::camera_config::CameraConfig;
use tagdeflect_io::sync::SyncConfig;
use tagdeflect_core::frame::GrayImage;
use tagdeflect_estimate::gauges::{GaugeConfig, GaugeKind, GaugeTag, Gauges};
use tagdeflect_core::tags::{tag_corners, TagFamily};
use tagdeflect_io::utm::UtmSample;

use super::beam::FourPointBeam;
use super::law::{self, BeamMotion, DeformedShape, SimTest};
use super::render::{blur, gaussian_kernel, motion_blur, quantize, render_rect, CornerRays, Hit, PixelRect};
use super::scene::{shade, Layout};
use super::{SimError, SimParams};

const BEAM_BIT: u32 = 1 << 31;
const FRONT: u32 = BEAM_BIT | (1 << 24);
const TOP: u32 = BEAM_BIT | (2 << 24);
const END: u32 = BEAM_BIT | (3 << 24);
const CARD_CELL: u32 = 0xff;

/// One simulated camera.
#[derive(Debug, Clone, PartialEq)]
pub struct SimCamera {
    /// Name (also the recording's sub-folder).
    pub name: String,
    /// True intrinsics (written to the config).
    pub intrinsics: CameraIntrinsics,
    /// True pose before any bump.
    pub pose: Pose,
    /// `(first frame set, pose)` after a bump, for the bumped camera.
    pub bumped: Option<(u64, Pose)>,
}

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

/// The static image of one camera pose (no beam), before and after optical blur.
struct Background {
    /// The pose's cache key (see `pose_key`).
    epoch: u64,
    raw: Vec<f32>,
    blurred: Vec<f32>,
}

/// Per-camera render state: rays (computed once) and the cached background.
struct CameraState {
    rays: OnceLock<CornerRays>,
    background: Mutex<Option<Arc<Background>>>,
}

/// The deformed beam at one instant, ready for tracing.
struct BeamState {
    /// The deformation (elastic curve, hinge of a cracked notched beam).
    motion: BeamMotion,
    /// The deformed geometry, tabulated.
    shape: DeformedShape,
    /// Per specimen tag: deformed centre (x, z) and (cos, sin) of its in-plane rotation.
    tags: Vec<(f64, f64, f64, f64)>,
    hidden: Option<usize>,
    /// End faces: (point on the face, section direction, normal), for x < 0 and x > 0.
    ends: [(Vector3<f64>, Vector3<f64>, Vector3<f64>); 2],
}

/// The simulated rig: scene, beam mechanics, renderer and truth (see the module docs of
/// [`crate::sim`] for the world frame).
pub struct SimRig {
    params: SimParams,
    beam: FourPointBeam,
    layout: Layout,
    cams: Vec<CameraState>,
    kernel: Vec<f32>,
}

impl std::fmt::Debug for SimRig {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SimRig").field("params", &self.params).finish_non_exhaustive()
    }
}

fn mix(a: u64, b: u64) -> u64 {
    let mut z = a ^ b.wrapping_mul(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

impl SimRig {
    /// Builds the rig; fails when a parameter is out of range.
    pub fn new(params: &SimParams) -> Result<SimRig, SimError> {
        params.validate()?;
        let layout = Layout::new(params);
        let cams = layout.names.iter().map(|_| CameraState { rays: OnceLock::new(), background: Mutex::new(None) }).collect();
        Ok(SimRig {
            params: params.clone(),
            beam: FourPointBeam {
                span: params.span_mm,
                load_span: if params.test == SimTest::ThreePointNotched { 0.0 } else { params.load_span_mm },
            },
            layout,
            cams,
            kernel: gaussian_kernel(params.blur_sigma),
        })
    }

    /// The parameters the rig was built from.
    pub fn params(&self) -> &SimParams {
        &self.params
    }

    /// The beam's mechanics.
    pub fn beam(&self) -> &FourPointBeam {
        &self.beam
    }

    /// Number of cameras.
    pub fn camera_count(&self) -> usize {
        self.layout.names.len()
    }

    /// The cameras: names, true intrinsics and poses.
    pub fn cameras(&self) -> Vec<SimCamera> {
        (0..self.camera_count())
            .map(|i| SimCamera {
                name: self.layout.names[i].clone(),
                intrinsics: self.layout.intrinsics[i],
                pose: self.layout.poses[i],
                bumped: self.layout.bumped.filter(|b| b.0 == i).map(|b| (self.params.bump_at as u64, b.1)),
            })
            .collect()
    }

    /// Nominal time of frame set `k`, ns.
    pub fn set_time_ns(&self, k: u64) -> i64 {
        self.params.start_ns + (k as f64 * 1e9 / self.params.fps).round() as i64
    }

    /// The frame set whose nominal time is nearest to `t_ns` (may be negative before the start).
    pub fn set_index_at(&self, t_ns: i64) -> i64 {
        ((t_ns - self.params.start_ns) as f64 * self.params.fps / 1e9).round() as i64
    }

    /// Capture time of camera `cam`'s frame of set `k`, or `None` when the camera dropped it.
    pub fn frame_time_ns(&self, cam: usize, k: u64) -> Option<i64> {
        let mut rng = ChaCha8Rng::seed_from_u64(mix(mix(self.params.seed, 0x7111), mix(cam as u64, k)));
        let z: f64 = StandardNormal.sample(&mut rng);
        let drop: f64 = rng.gen();
        if drop < self.params.drop_prob {
            return None;
        }
        let jitter_ns = (z.clamp(-3.0, 3.0) * self.params.jitter_ms * 1e6).round() as i64;
        Some(self.set_time_ns(k) + jitter_ns)
    }

    /// Midspan deflection (mm, positive downward) at `t_ns`: zero for `rest_frames` frame
    /// sets, then a linear ramp reaching `max_deflection_mm` at the last frame set (held
    /// after it, or repeated down and up again with `cyclic`).
    pub fn midspan_deflection(&self, t_ns: i64) -> f64 {
        let p = &self.params;
        let s = (t_ns - p.start_ns) as f64 * 1e-9;
        let period = 1.0 / p.fps;
        let rest = p.rest_frames as f64 * period;
        let ramp = (p.frame_sets as f64 - 1.0 - p.rest_frames as f64).max(0.0) * period;
        let max = p.max_deflection_mm;
        if ramp <= 0.0 {
            return if s >= rest { max } else { 0.0 };
        }
        if !p.cyclic {
            return ((s - rest) / ramp).clamp(0.0, 1.0) * max;
        }
        let cycle = rest + 2.0 * ramp;
        let u = s.rem_euclid(cycle);
        if u < rest {
            0.0
        } else if u < rest + ramp {
            (u - rest) / ramp * max
        } else {
            (1.0 - (u - rest - ramp) / ramp) * max
        }
    }

    /// The UTM's reading at true time `t_ns`: load = the load law at the midspan deflection
    /// (elastic: stiffness × deflection, see [`law`]); stroke = the deflection under the
    /// loading points + machine compliance × load.
    pub fn utm_sample(&self, t_ns: i64) -> UtmSample {
        let d = self.midspan_deflection(t_ns);
        let load = law::load_at(&self.params, d);
        let under_load = self.beam.deflection(0.5 * self.beam.load_span, d);
        UtmSample { t_ns, load_kn: load, stroke_mm: Some(under_load + self.params.compliance_mm_per_kn * load) }
    }

    /// UTM samples at `utm_hz` (with `utm_phase_ms` against the frame clock) covering the
    /// recording from 0.25 s (+ the clock offset) before the first frame set to 0.25 s (+ the
    /// offset) after the last, stamped on the UTM's clock (`utm_clock_offset_ms` ahead).
    pub fn utm_samples(&self) -> Vec<UtmSample> {
        let p = &self.params;
        let dt = 1e9 / p.utm_hz;
        let margin = 250_000_000 + (p.utm_clock_offset_ms.abs() * 1e6).round() as i64;
        let t_first = p.start_ns - margin;
        let t_last = self.set_time_ns(p.frame_sets as u64 - 1) + margin;
        let phase = p.utm_phase_ms * 1e6;
        let j0 = ((t_first - p.start_ns) as f64 - phase) / dt;
        let j1 = ((t_last - p.start_ns) as f64 - phase) / dt;
        let outage = self.utm_outage();
        let offset_ns = (p.utm_clock_offset_ms * 1e6).round() as i64;
        (j0.ceil() as i64..=j1.floor() as i64)
            .map(|j| p.start_ns + (phase + j as f64 * dt).round() as i64)
            .filter(|t| outage.is_none_or(|(a, b)| *t < a || *t >= b))
            // Stamped on the UTM's clock: taken at true time `stamp - offset`.
            .map(|stamp| UtmSample { t_ns: stamp, ..self.utm_sample(stamp - offset_ns) })
            .collect()
    }

    /// The simulated UTM outage (`utm_outage_at_s`, `utm_outage_s`) as [start, end) in ns
    /// since the Unix epoch, when one is set.
    pub fn utm_outage(&self) -> Option<(i64, i64)> {
        let p = &self.params;
        p.utm_outage_at_s.map(|a| {
            let start = p.start_ns + (a * 1e9) as i64;
            (start, start + (p.utm_outage_s * 1e9) as i64)
        })
    }

    /// Pose of camera `cam` at `t_ns` (after the bump from frame set `bump_at` on; moved by
    /// the drift of the frame set nearest to `t_ns` for the drifting camera).
    /// Panics if `cam >= camera_count()`.
    pub fn camera_pose(&self, cam: usize, t_ns: i64) -> Pose {
        let base = match self.layout.bumped {
            Some((c, pose)) if c == cam && self.set_index_at(t_ns) >= self.params.bump_at as i64 => pose,
            _ => self.layout.poses[cam],
        };
        match self.drift_step(cam, t_ns) {
            Some(k) => self.drifted(&base, k),
            None => base,
        }
    }

    /// For the drifting camera: the frame set (clamped to the recording) whose drift applies at `t_ns`.
    fn drift_step(&self, cam: usize, t_ns: i64) -> Option<i64> {
        (self.params.drift_camera == Some(cam as u32))
            .then(|| self.set_index_at(t_ns).clamp(0, self.params.frame_sets.saturating_sub(1) as i64))
    }

    /// `base` after the drift of frame set `k`: a linear share `k / (frame_sets − 1)` of
    /// `drift_rot_deg` (about an oblique, mostly horizontal axis through the camera centre —
    /// a tripod head tilting) and of `drift_trans_mm` (the centre moving mostly down — the
    /// floor settling).
    fn drifted(&self, base: &Pose, k: i64) -> Pose {
        let p = &self.params;
        let u = if p.frame_sets > 1 { k as f64 / (p.frame_sets - 1) as f64 } else { 0.0 };
        let axis = Unit::new_normalize(Vector3::new(1.0, 0.3, 0.2));
        let dr = Rotation3::from_axis_angle(&axis, u * p.drift_rot_deg.to_radians());
        let dt = Vector3::new(0.3, 0.2, -1.0).normalize() * (u * p.drift_trans_mm);
        let centre = base.centre() + dt;
        let rotation = dr * base.rotation;
        Pose { rotation, translation: -(rotation * centre) }
    }

    /// Cache key of camera `cam`'s pose at `t_ns` (bump epoch and drift step).
    fn pose_key(&self, cam: usize, t_ns: i64) -> u64 {
        self.pose_epoch(cam, t_ns) as u64 | self.drift_step(cam, t_ns).map_or(0, |k| (k as u64 + 1) << 8)
    }

    fn pose_epoch(&self, cam: usize, t_ns: i64) -> u8 {
        match self.layout.bumped {
            Some((c, _)) if c == cam && self.set_index_at(t_ns) >= self.params.bump_at as i64 => 1,
            _ => 0,
        }
    }

    /// Pose (tag frame → world) of every specimen tag at `t_ns`, with its id.
    pub fn tag_poses(&self, t_ns: i64) -> Vec<(u32, Pose)> {
        self.tag_poses_at(self.midspan_deflection(t_ns))
    }

    /// Pose (tag frame → world) of every specimen tag at midspan deflection `d` (mm).
    pub fn tag_poses_at(&self, d: f64) -> Vec<(u32, Pose)> {
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

    /// The background tags with their world corners (as written to the config).
    pub fn background_tags(&self) -> Vec<BackgroundTag> {
        let s = self.params.background_tag_mm;
        let mut out = Vec::new();
        for (pi, panel) in self.layout.panels.iter().enumerate() {
            for k in 0..panel.tags.len() {
                let c = panel.tag_corners(k, s);
                out.push(BackgroundTag { id: self.layout.background_ids[pi][k], corners_mm: c.map(|v| [v.x, v.y, v.z]) });
            }
        }
        out
    }

    /// Role of every specimen tag, by id.
    pub fn specimen_roles(&self) -> Vec<(u32, Option<TagRole>)> {
        self.layout.specimen.iter().map(|s| (s.id, s.role)).collect()
    }

    /// The rig's description as config sections: true intrinsics, no poses, `source =
    /// "sim"`, the background tags' world corners, specimen tags with roles, and (for a real
    /// test) `[specimen.beam]` and gauges. The binary adds `[sim]` = the parameters and
    /// builds the whole config from it (through the same validation as a file).
    pub fn sections(&self) -> SimRigSections {
        let p = &self.params;
        let cameras = (0..self.camera_count())
            .map(|i| {
                let k = self.layout.intrinsics[i];
                CameraConfig {
                    name: self.layout.names[i].clone(),
                    source: tagdeflect_core::camera_config::CameraSource::Sim,
                    fps: Some(p.fps),
                    width: k.width,
                    height: k.height,
                    fx: k.fx,
                    fy: k.fy,
                    cx: k.cx,
                    cy: k.cy,
                    dist: k.dist,
                    rvec: None,
                    tvec_mm: None,
                }
            })
            .collect();
        let tolerance_ms = (10.0f64).max(6.0 * p.jitter_ms).min(450.0 / p.fps);
        SimRigSections {
            world: WorldConfig { up: [0.0, 0.0, 1.0] },
            sync: SyncConfig { tolerance_ms },
            cameras,
            background: BackgroundConfig { family: TagFamily::Tag25h9, size_mm: p.background_tag_mm, tags: self.background_tags() },
            specimen: SpecimenConfig {
                family: TagFamily::Tag36h11,
                size_mm: p.specimen_tag_mm,
                tags: self.layout.specimen.iter().map(|s| SpecimenTag { id: s.id, role: s.role }).collect(),
                beam: self.real_test().then(|| BeamConfig {
                    width_mm: p.beam_width_mm,
                    depth_mm: p.beam_height_mm,
                    span_mm: p.span_mm,
                    notch_mm: (p.test == SimTest::ThreePointNotched).then_some(p.notch_mm),
                }),
            },
            gauges: if self.real_test() { self.gauges() } else { Vec::new() },
        }
    }

    /// True when the rig simulates more than the default elastic four-point test (a load
    /// law, the notched test or a UTM clock offset): its config then carries
    /// `[specimen.beam]` and gauges (the default rig's config is left as it was).
    pub fn real_test(&self) -> bool {
        let p = &self.params;
        p.test != SimTest::FourPoint || p.load_law != law::LoadLaw::Elastic || p.utm_clock_offset_ms != 0.0
    }

    /// The gauges of a real test's config: `net` (net deflection), `rot1` (rotation of the
    /// left support tag about world y, the beam's end slope), and `cmod` (opening of the
    /// notch mouth from the two tags across it; notched test) or `curv` (curvature through
    /// the supports and midspan; four-point).
    pub fn gauges(&self) -> Vec<GaugeConfig> {
        let g = |name: &str, kind: GaugeKind, tags: Vec<u32>| GaugeConfig {
            name: name.into(),
            kind,
            tags,
            direction: None,
            axis: None,
            gauge_length_mm: None,
            at_mm: None,
        };
        let mut out = vec![g("net", GaugeKind::NetDeflection, Vec::new())];
        out.push(GaugeConfig { axis: Some([0.0, 1.0, 0.0]), ..g("rot1", GaugeKind::Rotation, vec![1]) });
        if self.params.test == SimTest::ThreePointNotched {
            out.push(GaugeConfig {
                direction: Some([1.0, 0.0, 0.0]),
                at_mm: Some([0.0, 0.0, 0.0]),
                ..g("cmod", GaugeKind::Opening, vec![3, 4])
            });
        } else {
            out.push(g("curv", GaugeKind::Curvature, vec![1, 0, 2]));
        }
        out
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

    /// True when camera `cam`'s frame of set `k` carries motion blur.
    pub fn has_motion_blur(&self, cam: usize, k: i64) -> bool {
        let every = self.params.motion_blur_every as i64;
        every > 0
            && k >= 1
            && k % every == every / 2
            && ((k / every) as usize % self.camera_count()) == cam
            && self.params.motion_blur_px > 0.0
    }

    /// The specimen tag hidden from camera `cam` in set `k`, if any.
    pub fn hidden_tag(&self, cam: usize, k: i64) -> Option<u32> {
        let p = &self.params;
        let id = p.hide_tag?;
        (cam == p.hide_camera as usize && k >= p.hide_from as i64 && k < p.hide_from as i64 + p.hide_count as i64).then_some(id)
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

    // ----------------------------------------------------------------------------------
    // Tracing.

    /// The beam's deformation at midspan deflection `d` (mm).
    pub fn motion_at(&self, d: f64) -> BeamMotion {
        BeamMotion::new(&self.params, &self.beam, d)
    }

    fn beam_state(&self, t_ns: i64, hidden: Option<u32>) -> BeamState {
        let d = self.midspan_deflection(t_ns);
        let motion = self.motion_at(d);
        let zc = 0.5 * self.params.beam_height_mm;
        let tags = self
            .layout
            .specimen
            .iter()
            .map(|s| {
                let (dx, dz, rot) = motion.displace(s.x, s.zeta);
                (s.x + dx, zc + s.zeta + dz, rot.cos(), rot.sin())
            })
            .collect();
        let hl = 0.5 * self.params.beam_length_mm;
        let ends = [-hl, hl].map(|x| {
            let (dx, dz, rot) = motion.displace(x, 0.0);
            let a = -rot;
            (Vector3::new(x + dx, 0.0, zc + dz), Vector3::new(a.sin(), 0.0, a.cos()), Vector3::new(a.cos(), 0.0, -a.sin()))
        });
        let hidden = hidden.and_then(|id| self.layout.specimen.iter().position(|s| s.id == id));
        BeamState { motion, shape: DeformedShape::new(&motion, hl), tags, hidden, ends }
    }

    /// Grey level of a printed tag at `(x, y)` of its frame (paper white outside the print).
    #[inline]
    fn tag_shade(bitmap: &tagdeflect_core::tags::TagBitmap, x: f64, y: f64, size: f64) -> f32 {
        match bitmap.cell_at(x, y, size) {
            Some((col, row)) if !bitmap.is_white(col, row) => shade::BLACK,
            _ => shade::WHITE,
        }
    }

    /// The fixed scene (panels with background tags), without the beam.
    fn trace_static(&self, c: &Vector3<f64>, d: &Vector3<f64>) -> Hit {
        let mut best_t = f64::INFINITY;
        let mut hit = (0u32, shade::FAR, [0.0; 2]);
        let size = self.params.background_tag_mm;
        for (pi, p) in self.layout.panels.iter().enumerate() {
            let denom = d.dot(&p.n);
            if denom >= -1e-12 {
                continue;
            }
            let t = (p.origin - c).dot(&p.n) / denom;
            if t <= 0.0 || t >= best_t {
                continue;
            }
            let q = c + d * t - p.origin;
            let (u, v) = (q.dot(&p.u), q.dot(&p.v));
            if u.abs() > p.half.0 || v.abs() > p.half.1 {
                continue;
            }
            best_t = t;
            let base = ((pi as u32 + 1) << 16, p.base + p.texture.at(u, v), [0.0; 2]);
            hit = base;
            for (k, tag) in p.tags.iter().enumerate() {
                let (tx, ty) = (u - tag.centre.0, v - tag.centre.1);
                if let Some((col, row)) = tag.bitmap.cell_at(tx, ty, size) {
                    // One label per colour of a tag (not per cell): a pixel smaller than a cell
                    // whose corners all see one colour lies wholly in that colour.
                    let white = tag.bitmap.is_white(col, row);
                    let label = base.0 | ((k as u32 + 1) << 8) | white as u32;
                    hit = (label, if white { shade::WHITE } else { shade::BLACK }, [tx, ty]);
                    break;
                }
            }
        }
        hit
    }

    /// The deformed beam (front face with tags, top, the end facing the camera).
    fn trace_beam(&self, st: &BeamState, c: &Vector3<f64>, d: &Vector3<f64>) -> Option<Hit> {
        let p = &self.params;
        let (hl, hh, bw) = (0.5 * p.beam_length_mm, 0.5 * p.beam_height_mm, p.beam_width_mm);
        let zc = hh;
        // Front face, plane y = 0 (the face bends in its own plane).
        if d.y > 1e-12 && c.y < 0.0 {
            let t = -c.y / d.y;
            let (x, z) = (c.x + t * d.x, c.z + t * d.z);
            if x.abs() <= hl + 10.0 && (z - zc).abs() <= hh + 10.0 + p.max_deflection_mm {
                // Tags first: they lie well inside the face, and most sub-samples are on them.
                let size = p.specimen_tag_mm;
                for (k, (s, &(cx, cz, ca, sa))) in self.layout.specimen.iter().zip(&st.tags).enumerate() {
                    let (dx, dz) = (x - cx, z - cz);
                    let half = 0.5 * s.bitmap.printed_mm(size) + 3.0;
                    if dx.abs() > 1.5 * half || dz.abs() > 1.5 * half {
                        continue;
                    }
                    let lx = ca * dx + sa * dz;
                    let ly = -sa * dx + ca * dz;
                    if st.hidden == Some(k) {
                        if lx.abs() <= half && ly.abs() <= half {
                            return Some((FRONT | ((k as u32 + 1) << 8) | CARD_CELL, shade::CARD, [lx, ly]));
                        }
                        continue;
                    }
                    if let Some((col, row)) = s.bitmap.cell_at(lx, ly, size) {
                        let white = s.bitmap.is_white(col, row);
                        let v = if white { shade::WHITE } else { shade::BLACK };
                        return Some((FRONT | ((k as u32 + 1) << 8) | white as u32, v, [lx, ly]));
                    }
                }
                let (mx, mz) = st.shape.material_point(x, z - zc);
                if mx.abs() <= hl && mz.abs() <= hh {
                    return Some((FRONT, shade::FACE + self.layout.face_texture.at(mx, mz), [0.0; 2]));
                }
            }
        }
        // Top face: z = top of the deformed section, found by fixed-point iteration.
        if d.z < -1e-12 && c.z > 2.0 * hh {
            let t0 = (2.0 * hh - c.z) / d.z;
            let q0 = c + d * t0;
            let m = 5.0 + p.max_deflection_mm;
            if q0.x.abs() <= hl + m && q0.y >= -m && q0.y <= bw + m {
                let mut q = q0;
                let mut mx = q0.x;
                for _ in 0..2 {
                    let (x, dz) = st.shape.fibre_point(q.x, hh);
                    mx = x;
                    let t = (zc + hh + dz - c.z) / d.z;
                    q = c + d * t;
                }
                if mx.abs() <= hl && q.y >= 0.0 && q.y <= bw {
                    return Some((TOP, shade::TOP + self.layout.top_texture.at(mx, q.y), [0.0; 2]));
                }
            }
        }
        // The end face turned towards the camera.
        for (side, (p0, e, n)) in st.ends.iter().enumerate() {
            let sign = if side == 0 { -1.0 } else { 1.0 };
            if sign * c.x <= hl {
                continue;
            }
            let denom = d.dot(n);
            if denom.abs() < 1e-12 {
                continue;
            }
            let t = (p0 - c).dot(n) / denom;
            if t <= 0.0 {
                continue;
            }
            let q = c + d * t;
            let zeta = (q - p0).dot(e);
            if zeta.abs() <= hh && q.y >= 0.0 && q.y <= bw {
                return Some((END | side as u32, shade::END, [0.0; 2]));
            }
        }
        None
    }

    /// Pixel rectangle that holds the deformed beam (with a margin), clipped to the image.
    fn beam_rect(&self, cam: usize, pose: &Pose, st: &BeamState) -> PixelRect {
        let p = &self.params;
        let k = &self.layout.intrinsics[cam];
        let (hl, hh, bw) = (0.5 * p.beam_length_mm, 0.5 * p.beam_height_mm, p.beam_width_mm);
        let (mut x0, mut y0, mut x1, mut y1) = (f64::INFINITY, f64::INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY);
        let n = 60;
        for i in 0..=n {
            let x = -hl + 2.0 * hl * i as f64 / n as f64;
            for zeta in [-hh, 0.0, hh] {
                let (dx, dz, _) = st.motion.displace(x, zeta);
                for y in [0.0, bw] {
                    let w = Vector3::new(x + dx, y, hh + zeta + dz);
                    if let Some(px) = k.project(&pose.transform(&w)) {
                        x0 = x0.min(px.x);
                        y0 = y0.min(px.y);
                        x1 = x1.max(px.x);
                        y1 = y1.max(px.y);
                    }
                }
            }
        }
        let (w, h) = (k.width as f64, k.height as f64);
        if !x0.is_finite() {
            return PixelRect { x0: 0, y0: 0, x1: 0, y1: 0 };
        }
        let m = 4.0;
        let cl = |v: f64, hi: f64| v.clamp(0.0, hi) as usize;
        PixelRect {
            x0: cl((x0 - m).floor(), w),
            y0: cl((y0 - m).floor(), h),
            x1: cl((x1 + m).ceil() + 1.0, w),
            y1: cl((y1 + m).ceil() + 1.0, h),
        }
    }

    fn rays(&self, cam: usize) -> &CornerRays {
        self.cams[cam].rays.get_or_init(|| CornerRays::new(&self.layout.intrinsics[cam]))
    }

    fn background(&self, cam: usize, t_ns: i64) -> Arc<Background> {
        let epoch = self.pose_key(cam, t_ns);
        let mut slot = self.cams[cam].background.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(bg) = slot.as_ref() {
            if bg.epoch == epoch {
                return bg.clone();
            }
        }
        let pose = self.camera_pose(cam, t_ns);
        let rays = self.rays(cam);
        let (w, h) = (rays.w, rays.h);
        let rot_cw = pose.rotation.inverse();
        let centre = pose.centre();
        let mut raw = vec![0.0f32; w * h];
        let trace = |d: &Vector3<f64>| self.trace_static(&centre, d);
        let sample = |d: &Vector3<f64>, _: usize, _: usize| self.trace_static(&centre, d).1;
        let all = PixelRect { x0: 0, y0: 0, x1: w, y1: h };
        let bg_size = self.params.background_tag_mm;
        let flat = |key: u32, x: f64, y: f64| -> f32 {
            let panel = &self.layout.panels[((key >> 16) & 0xff) as usize - 1];
            let tag = &panel.tags[((key >> 8) & 0xff) as usize - 1];
            Self::tag_shade(&tag.bitmap, x, y, bg_size)
        };
        render_rect(rays, &rot_cw, all, self.params.subsamples as usize, &trace, &sample, None, Some(&flat), &mut raw);
        let blurred = blur(&raw, w, h, &self.kernel);
        let bg = Arc::new(Background { epoch, raw, blurred });
        *slot = Some(bg.clone());
        bg
    }

    /// Renders camera `cam`'s image at `t_ns` (8-bit grey, the camera's size).
    ///
    /// The fixed scene is rendered once per camera pose and cached; each call re-renders
    /// only the beam's image region, blurs around it, then adds fresh noise (seeded by
    /// the rig's seed, the camera and `t_ns`, so the same call gives the same image).
    /// Motion blur and a hidden tag apply per the frame set nearest to `t_ns`.
    ///
    /// Panics if `cam >= camera_count()`.
    pub fn render(&self, cam: usize, t_ns: i64) -> GrayImage {
        let k = self.set_index_at(t_ns);
        let bg = self.background(cam, t_ns);
        let rays = self.rays(cam);
        let (w, h) = (rays.w, rays.h);
        let pose = self.camera_pose(cam, t_ns);
        let st = self.beam_state(t_ns, self.hidden_tag(cam, k));
        let rect = self.beam_rect(cam, &pose, &st);
        let mut img = bg.blurred.clone();
        if !rect.is_empty() {
            let r = self.kernel.len() / 2;
            let outer = rect.grow(2 * r, w, h);
            let (ow, oh) = (outer.width(), outer.height());
            // Unblurred composite over `outer`: background, then the beam region.
            let mut comp = vec![0.0f32; ow * oh];
            for (j, row) in comp.chunks_mut(ow).enumerate() {
                let y = outer.y0 + j;
                row.copy_from_slice(&bg.raw[y * w + outer.x0..y * w + outer.x1]);
            }
            let mut beam_px = vec![0.0f32; rect.width() * rect.height()];
            let centre = pose.centre();
            // Corners: the beam only (label 0 = not the beam: a pixel whose four corners all
            // miss keeps the cached background). Sub-samples that miss the beam take the
            // cached background pixel (its area mean: the background is uniform at the scale
            // of a pixel wherever the beam's outline crosses it).
            let corner = |d: &Vector3<f64>| self.trace_beam(&st, &centre, d).unwrap_or((0, 0.0, [0.0; 2]));
            let sample = |d: &Vector3<f64>, x: usize, y: usize| match self.trace_beam(&st, &centre, d) {
                Some(hit) => hit.1,
                None => bg.raw[y * w + x],
            };
            let not_beam = |l: u32| l & BEAM_BIT == 0;
            let n = self.params.subsamples as usize;
            let size = self.params.specimen_tag_mm;
            let flat = |key: u32, x: f64, y: f64| -> f32 {
                let s = &self.layout.specimen[((key >> 8) & 0xff) as usize - 1];
                Self::tag_shade(&s.bitmap, x, y, size)
            };
            let rot = pose.rotation.inverse();
            render_rect(rays, &rot, rect, n, &corner, &sample, Some((&not_beam, &bg.raw)), Some(&flat), &mut beam_px);
            for (j, row) in beam_px.chunks(rect.width()).enumerate() {
                let y = rect.y0 + j - outer.y0;
                let x = rect.x0 - outer.x0;
                comp[y * ow + x..y * ow + x + rect.width()].copy_from_slice(row);
            }
            let blurred = blur(&comp, ow, oh, &self.kernel);
            // Valid where the whole kernel lay inside `outer` or the image edge: rect grown by r.
            let valid = rect.grow(r, w, h);
            for y in valid.y0..valid.y1 {
                let src = &blurred[(y - outer.y0) * ow + valid.x0 - outer.x0..(y - outer.y0) * ow + valid.x1 - outer.x0];
                img[y * w + valid.x0..y * w + valid.x1].copy_from_slice(src);
            }
        }
        if self.has_motion_blur(cam, k) {
            let angle = (mix(self.params.seed, k as u64) % 360) as f64 * std::f64::consts::PI / 180.0;
            img = motion_blur(&img, w, h, self.params.motion_blur_px, angle);
        }
        let seed = mix(mix(self.params.seed, 0x4015e), mix(cam as u64, t_ns as u64));
        quantize(&img, w, h, self.params.noise_sigma, seed)
    }
}

/// The simulated rig described as the config sections it fills (see [`SimRig::sections`]).
#[derive(Debug, Clone, PartialEq)]
pub struct SimRigSections {
    /// `[world]`.
    pub world: WorldConfig,
    /// `[sync]`: a tolerance fit for the rig's frame rate and jitter.
    pub sync: SyncConfig,
    /// The rig's cameras (`source = "sim"`).
    pub cameras: Vec<CameraConfig>,
    /// `[background]`.
    pub background: BackgroundConfig,
    /// `[specimen]`.
    pub specimen: SpecimenConfig,
    /// `[[gauge]]` (a real test's).
    pub gauges: Vec<GaugeConfig>,
}
