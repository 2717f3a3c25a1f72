//! [`SimRig`]: the simulated rig built from [`SimParams`] — its construction, its cameras,
//! and the config sections that describe it ([`SimRigSections`]).
//!
//! The rig's other concerns are `impl SimRig` blocks of their own modules: frame timing
//! (`timing`), the course of the test and the UTM (`loading`), camera bump and drift
//! (`drift`), ground truth (`truth`), the scene tracer (`trace`) and rendering
//! (`render_rig`, on the renderer of [`crate::render`]).

use tagdeflect_core::beam::BeamConfig;
use tagdeflect_core::camera::{CameraIntrinsics, Pose};
use tagdeflect_core::camera_config::CameraConfig;
use tagdeflect_core::gauge::{GaugeConfig, GaugeKind};
use tagdeflect_core::rig::{BackgroundConfig, BackgroundTag, SpecimenConfig, SpecimenTag, TagRole, WorldConfig};
use tagdeflect_core::tags::TagFamily;
use tagdeflect_io::sync::SyncConfig;

use super::beam::FourPointBeam;
use super::law::{self, SimTest};
use super::render::{Astigmatism, Optics, OpticsSpec};
use super::render_rig::CameraRenderCache;
use super::scene::Layout;
use super::{SimError, SimParams};

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

/// The simulated rig: scene, beam mechanics, renderer and truth (see the [crate
/// docs](crate) for the world frame).
pub struct SimRig {
    // Shared with the rig's `impl` blocks in the sibling modules (timing, drift, truth, …).
    pub(crate) params: SimParams,
    pub(crate) beam: FourPointBeam,
    pub(crate) layout: Layout,
    pub(crate) cams: Vec<CameraRenderCache>,
    pub(crate) optics: Optics,
    /// A verification run's positions (`verify_steps`), mm; empty for a test.
    pub(crate) verify_steps_mm: Vec<f64>,
    /// A test loaded at rates (`rates`): `(mm/min, until mm)`; empty for the ramp.
    pub(crate) rate_phases: Vec<(f64, f64)>,
}

impl std::fmt::Debug for SimRig {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SimRig").field("params", &self.params).finish_non_exhaustive()
    }
}

/// Mixes a seed with a value (SplitMix64's finaliser): the seeds of the rig's random draws
/// (frame jitter and drops, motion blur, noise) from the rig's seed.
pub(crate) fn mix(a: u64, b: u64) -> u64 {
    let mut z = a ^ b.wrapping_mul(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// The optics before the pixels of `params` (Gaussian, defocus disk, astigmatism, fill
/// factor).
pub(crate) fn optics_spec(params: &SimParams) -> OpticsSpec {
    OpticsSpec {
        gaussian_sigma_px: params.blur_sigma,
        defocus_radius_px: params.defocus_radius_px,
        astigmatism: (params.astig_major_px > 0.0).then_some(Astigmatism {
            major_px: params.astig_major_px,
            minor_px: params.astig_minor_px,
            angle_deg: params.astig_angle_deg,
        }),
        fill_factor: params.fill_factor,
    }
}

impl SimRig {
    /// Builds the rig; fails when a parameter is out of range.
    pub fn new(params: &SimParams) -> Result<SimRig, SimError> {
        params.validate()?;
        let layout = Layout::new(params);
        let cams = layout.names.iter().map(|_| CameraRenderCache::new()).collect();
        Ok(SimRig {
            params: params.clone(),
            beam: FourPointBeam {
                span: params.span_mm,
                load_span: if params.test == SimTest::ThreePointNotched { 0.0 } else { params.load_span_mm },
            },
            layout,
            cams,
            optics: Optics::of(&optics_spec(params)),
            verify_steps_mm: params.verify_positions_mm()?,
            rate_phases: params.rate_phases()?,
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
    pub(crate) fn camera_count(&self) -> usize {
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
                    full_depth: false,
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
                    ..Default::default()
                }),
            },
            gauges: if self.real_test() {
                self.gauges()
            } else if p.verify_stage_half_width_mm > 0.0 {
                self.gauges().into_iter().filter(|g| g.name == "net").collect()
            } else {
                Vec::new()
            },
        }
    }

    /// True when the rig simulates more than the default elastic four-point test (a load
    /// law, the notched test or a UTM clock offset): its config then carries
    /// `[specimen.beam]` and gauges (the default rig's config is left as it was).
    pub(crate) fn real_test(&self) -> bool {
        let p = &self.params;
        p.test != SimTest::FourPoint || p.load_law != law::LoadLaw::Elastic || p.utm_clock_offset_ms != 0.0
    }

    /// The gauges of a real test's config: `net` (net deflection), `rot1` (rotation of the
    /// left support tag about world y, the beam's end slope), and `cmod` (opening of the
    /// notch mouth from the two tags across it; notched test) or `curv` (curvature through
    /// the supports and midspan; four-point).
    pub(crate) fn gauges(&self) -> Vec<GaugeConfig> {
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
