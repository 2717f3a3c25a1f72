//! The static layout of the simulated rig: cameras, background panels with their tags,
//! specimen tag positions on the beam face, and surface textures.

use nalgebra::{Rotation3, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::params::{camera_places, SIM_CAMERA_NAMES};
use tagdeflect_core::camera::{CameraIntrinsics, Pose};
use tagdeflect_core::rig::TagRole;
use tagdeflect_core::tags::{TagBitmap, TagFamily};
use tagdeflect_detect::tag_bitmap;

use super::SimParams;

/// A smooth, mild surface texture: two octaves of value noise (random grey values on a
/// square lattice, interpolated bilinearly), in grey levels around zero.
#[derive(Debug, Clone)]
pub(crate) struct Texture {
    seed: u64,
    amp: f64,
    /// Lattice pitches of the two octaves, mm.
    pitch: (f64, f64),
}

#[inline]
fn lattice(seed: u64, i: i64, j: i64) -> f64 {
    let mut z = seed ^ (i as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15) ^ (j as u64).wrapping_mul(0xc2b2_ae3d_27d4_eb4f);
    z = (z ^ (z >> 31)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 29)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^= z >> 32;
    (z & 0xffff) as f64 / 65535.0 * 2.0 - 1.0
}

#[inline]
fn value_noise(seed: u64, u: f64, v: f64) -> f64 {
    // Floor without a libm call: truncate, then step down for negative fractions.
    let (mut i, mut j) = (u as i64, v as i64);
    if (i as f64) > u {
        i -= 1;
    }
    if (j as f64) > v {
        j -= 1;
    }
    let (fu, fv) = (i as f64, j as f64);
    let (tu, tv) = (u - fu, v - fv);
    let a = lattice(seed, i, j) * (1.0 - tu) + lattice(seed, i + 1, j) * tu;
    let b = lattice(seed, i, j + 1) * (1.0 - tu) + lattice(seed, i + 1, j + 1) * tu;
    a * (1.0 - tv) + b * tv
}

impl Texture {
    /// A texture of amplitude about `amp` grey levels with features from `lmin` to `lmax` mm.
    pub fn new(rng: &mut ChaCha8Rng, amp: f64, lmin: f64, lmax: f64) -> Self {
        Self { seed: rng.gen(), amp, pitch: (lmin, lmax) }
    }

    /// The texture at surface coordinates `(u, v)`, mm.
    #[inline]
    pub fn at(&self, u: f64, v: f64) -> f32 {
        let fine = value_noise(self.seed, u / self.pitch.0, v / self.pitch.0);
        let coarse = value_noise(self.seed ^ 0xabcd, u / self.pitch.1, v / self.pitch.1);
        (self.amp * (0.35 * fine + 0.65 * coarse)) as f32
    }
}

/// A [`Texture`] sampled on a 1 mm grid over a rectangle, read back bilinearly (for the
/// beam's surfaces, which are traced every frame).
#[derive(Debug, Clone)]
pub(crate) struct TextureTable {
    u0: f64,
    v0: f64,
    nu: usize,
    nv: usize,
    data: Vec<f32>,
}

impl TextureTable {
    /// Samples `tex` over `u0..u1` × `v0..v1` (mm) with a margin of 10 mm.
    pub fn new(tex: &Texture, (u0, u1): (f64, f64), (v0, v1): (f64, f64)) -> Self {
        let (u0, v0) = (u0 - 10.0, v0 - 10.0);
        let nu = (u1 - u0 + 10.0).ceil() as usize + 2;
        let nv = (v1 - v0 + 10.0).ceil() as usize + 2;
        let data = (0..nv).flat_map(|j| (0..nu).map(move |i| (i, j))).map(|(i, j)| tex.at(u0 + i as f64, v0 + j as f64)).collect();
        Self { u0, v0, nu, nv, data }
    }

    /// The texture at `(u, v)`, mm (clamped to the table).
    #[inline]
    pub fn at(&self, u: f64, v: f64) -> f32 {
        let fu = (u - self.u0).clamp(0.0, (self.nu - 2) as f64);
        let fv = (v - self.v0).clamp(0.0, (self.nv - 2) as f64);
        let (i, j) = (fu as usize, fv as usize);
        let (tu, tv) = ((fu - i as f64) as f32, (fv - j as f64) as f32);
        let k = j * self.nu + i;
        let a = self.data[k] * (1.0 - tu) + self.data[k + 1] * tu;
        let b = self.data[k + self.nu] * (1.0 - tu) + self.data[k + self.nu + 1] * tu;
        a * (1.0 - tv) + b * tv
    }
}

/// Grey levels of the scene's materials.
pub(crate) mod shade {
    /// Printed black.
    pub const BLACK: f32 = 28.0;
    /// Paper white.
    pub const WHITE: f32 = 228.0;
    /// The beam's front face (light grey concrete).
    pub const FACE: f32 = 168.0;
    /// The beam's top face (lit from above).
    pub const TOP: f32 = 196.0;
    /// The beam's end faces.
    pub const END: f32 = 138.0;
    /// The card hiding a tag.
    pub const CARD: f32 = 118.0;
    /// The frame behind the beam.
    pub const BACK: f32 = 96.0;
    /// The bench in front.
    pub const BENCH: f32 = 132.0;
    /// Beyond everything.
    pub const FAR: f32 = 58.0;
}

/// Background tags of the simulated rig (tag25h9 ids `0..BACKGROUND_TAGS`): five on the
/// frame's top row, two beside the beam, four on the bench.
pub(crate) const BACKGROUND_TAGS: u32 = 11;

/// A tag printed on a panel, upright in the panel's `(u, v)` axes.
#[derive(Debug, Clone)]
pub(crate) struct PanelTag {
    /// Centre of the black square in panel coordinates, mm.
    pub centre: (f64, f64),
    /// Its bitmap.
    pub bitmap: TagBitmap,
}

/// A flat rectangular panel of the fixed scene (frame behind the beam, bench in front).
#[derive(Debug, Clone)]
pub(crate) struct Panel {
    /// Centre of the panel.
    pub origin: Vector3<f64>,
    /// In-plane axis, tags' "right".
    pub u: Vector3<f64>,
    /// In-plane axis, tags' "up".
    pub v: Vector3<f64>,
    /// Normal `u × v` (towards the cameras).
    pub n: Vector3<f64>,
    /// Half extents along u and v, mm.
    pub half: (f64, f64),
    /// Base grey level.
    pub base: f32,
    /// Surface texture.
    pub texture: Texture,
    /// Tags on the panel.
    pub tags: Vec<PanelTag>,
}

impl Panel {
    /// World corners of tag `k`'s black square in SPEC order.
    pub fn tag_corners(&self, k: usize, size: f64) -> [Vector3<f64>; 4] {
        let t = &self.tags[k];
        let c = self.origin + self.u * t.centre.0 + self.v * t.centre.1;
        let h = 0.5 * size;
        [c - self.u * h - self.v * h, c + self.u * h - self.v * h, c + self.u * h + self.v * h, c - self.u * h + self.v * h]
    }
}

/// Where a specimen tag sits on the beam's front face at rest.
#[derive(Debug, Clone)]
pub(crate) struct SpecimenPlacement {
    /// Tag id (tag36h11).
    pub id: u32,
    /// Position along the beam from midspan, mm.
    pub x: f64,
    /// Height above the neutral axis, mm.
    pub zeta: f64,
    /// Role for the net deflection.
    pub role: Option<TagRole>,
    /// Its bitmap.
    pub bitmap: TagBitmap,
}

/// Fixed layout of the rig built from [`SimParams`].
#[derive(Debug, Clone)]
pub(crate) struct Layout {
    /// Camera names.
    pub names: Vec<String>,
    /// Camera intrinsics.
    pub intrinsics: Vec<CameraIntrinsics>,
    /// Camera poses at rest.
    pub poses: Vec<Pose>,
    /// Pose of the bumped camera after the bump.
    pub bumped: Option<(usize, Pose)>,
    /// Background panels (their tags are the world reference).
    pub panels: Vec<Panel>,
    /// Ids of the background tags, per panel.
    pub background_ids: Vec<Vec<u32>>,
    /// Specimen tags.
    pub specimen: Vec<SpecimenPlacement>,
    /// Texture of the beam face (material coordinates `x`, `zeta`).
    pub face_texture: TextureTable,
    /// Texture of the beam top (material `x`, world `y`).
    pub top_texture: TextureTable,
}

/// Tag places of the notched three-point test: the midspan tag near the top (above the
/// crack tip: a tag must not straddle the crack), the supports, two tags just above the
/// bottom face straddling the notch (ids 3 and 4: the crack mouth opening), the supports'
/// top row, the quarter points.
pub(crate) fn notched_slots(p: &SimParams) -> Vec<(f64, f64)> {
    let (half_span, hh) = (0.5 * p.span_mm, 0.5 * p.beam_height_mm);
    let printed = p.specimen_tag_mm * 10.0 / 8.0;
    let top = hh - 0.5 * printed - 3.0;
    let bottom = -hh + 0.5 * printed + 2.0;
    let across = 0.5 * p.notch_width_mm + 2.0 + 0.5 * printed;
    vec![
        (0.0, top),
        (-half_span, 0.0),
        (half_span, 0.0),
        (-across, bottom),
        (across, bottom),
        (-half_span, bh_third(p)),
        (half_span, bh_third(p)),
        (-0.5 * half_span, 0.0),
        (0.5 * half_span, 0.0),
    ]
}

fn bh_third(p: &SimParams) -> f64 {
    p.beam_height_mm / 3.0
}

/// A camera at `centre` looking at `target` with world `z` up, rolled by `roll` rad.
pub(crate) fn look_at(centre: Vector3<f64>, target: Vector3<f64>, roll: f64) -> Pose {
    let f = (target - centre).normalize();
    let r = f.cross(&Vector3::z()).normalize();
    let d = f.cross(&r);
    let m = nalgebra::Matrix3::from_rows(&[r.transpose(), d.transpose(), f.transpose()]);
    let rot = Rotation3::from_axis_angle(&Vector3::z_axis(), roll) * Rotation3::from_matrix_unchecked(m);
    Pose { rotation: rot, translation: -(rot * centre) }
}

impl Layout {
    /// Builds the layout; `params` must be valid.
    pub fn new(p: &SimParams) -> Layout {
        let mut rng = ChaCha8Rng::seed_from_u64(p.seed ^ 0x5eed_1a70_u64);
        let (bl, bh, bw) = (p.beam_length_mm, p.beam_height_mm, p.beam_width_mm);
        let zc = 0.5 * bh;

        // Cameras: ~1 m in front, slightly above, each from its own angle.
        // One place per name of `SIM_CAMERA_NAMES`: centre, target, roll.
        let all = [
            (Vector3::new(-0.78 * bl, -1000.0, zc + 260.0), Vector3::new(-0.06 * bl, bw, zc + 20.0), 0.012),
            (Vector3::new(0.02 * bl, -1080.0, zc + 340.0), Vector3::new(0.0, bw, zc + 25.0), -0.008),
            (Vector3::new(0.8 * bl, -990.0, zc + 190.0), Vector3::new(0.06 * bl, bw, zc + 20.0), 0.005),
        ];
        let chosen = camera_places(p.cameras as usize);
        // The same view at any size: the focal length follows the width of a 4:3 frame
        // (wider frames see more to the sides).
        let f = 1.2 * (p.width as f64).min(p.height as f64 * 4.0 / 3.0);
        let mut names = Vec::new();
        let mut intrinsics = Vec::new();
        let mut poses = Vec::new();
        for (i, &k) in chosen.iter().enumerate() {
            let (c, t, roll) = all[k];
            names.push(SIM_CAMERA_NAMES[k].to_string());
            let k1 = if p.strong_distortion_camera == Some(i as u32) { p.strong_k1 } else { p.k1 };
            intrinsics.push(CameraIntrinsics {
                width: p.width,
                height: p.height,
                fx: f * (1.0 + 0.003 * i as f64),
                fy: f * (1.0 + 0.003 * i as f64) * 0.9995,
                cx: 0.5 * (p.width as f64 - 1.0) + 3.5 - 2.0 * i as f64,
                cy: 0.5 * (p.height as f64 - 1.0) - 2.5 + 1.5 * i as f64,
                dist: [k1, -0.5 * k1, 0.0004, -0.0003, 0.0],
            });
            poses.push(look_at(c, t, roll));
        }
        let bumped = p.bump_camera.map(|c| {
            let c = c as usize;
            let pose = poses[c];
            let axis = nalgebra::Unit::new_normalize(Vector3::new(0.4, 1.0, 0.3));
            let dr = Rotation3::from_axis_angle(&axis, p.bump_rot_deg.to_radians());
            let dt = Vector3::new(0.6, -0.3, 0.74).normalize() * p.bump_trans_mm;
            // Turn about the camera centre, then move the centre by dt (world).
            let centre = pose.centre() + dt;
            let rot = dr * pose.rotation;
            (c, Pose { rotation: rot, translation: -(rot * centre) })
        });

        // Background: a frame behind the beam (vertical, facing the cameras) and a bench in
        // front of it (horizontal, below the beam's bottom).
        let s = p.background_tag_mm;
        let bg = |id: u32| tag_bitmap(TagFamily::Tag25h9, id).expect("tag25h9 ids 0..35");
        let back_y = bw + 250.0;
        let top_row_z = bh + 130.0 + 0.8 * s;
        let mut back_tags = Vec::new();
        let mut ids = Vec::new();
        let mut next = 0u32;
        for &fx in &[-0.8, -0.4, 0.0, 0.4, 0.8] {
            back_tags.push(PanelTag { centre: (fx * 0.5 * bl + 0.3 * s, top_row_z - 50.0 + 8.0 * fx), bitmap: bg(next) });
            ids.push(next);
            next += 1;
        }
        for &sx in &[-1.0, 1.0] {
            // Beside the beam, high enough that its top face never hides them.
            back_tags.push(PanelTag { centre: (sx * (0.5 * bl + 0.95 * s + 40.0) - 50.0, bh + 60.0 - 50.0), bitmap: bg(next) });
            ids.push(next);
            next += 1;
        }
        let back = Panel {
            origin: Vector3::new(0.0, back_y, 50.0),
            u: Vector3::x(),
            v: Vector3::z(),
            n: -Vector3::y(),
            half: (1400.0, 900.0),
            base: shade::BACK,
            texture: Texture::new(&mut rng, 7.0, 30.0, 160.0),
            tags: back_tags,
        };
        let mut bench_tags = Vec::new();
        let mut bench_ids = Vec::new();
        for &fx in &[-0.6, -0.2, 0.2, 0.6] {
            bench_tags.push(PanelTag { centre: (fx * 0.5 * bl * 1.25, 0.0 + 30.0 * fx), bitmap: bg(next) });
            bench_ids.push(next);
            next += 1;
        }
        let bench = Panel {
            origin: Vector3::new(0.0, -60.0 - 0.9 * s, -70.0),
            u: Vector3::x(),
            v: Vector3::y(),
            n: Vector3::z(),
            half: (900.0, 0.9 * s + 45.0),
            base: shade::BENCH,
            texture: Texture::new(&mut rng, 6.0, 20.0, 120.0),
            tags: bench_tags,
        };

        // Specimen tags: columns over the supports and at midspan (then the load points),
        // rows middle, top, bottom.
        let half_span = 0.5 * p.span_mm;
        let row_off = bh / 3.0;
        let mut slots = Vec::new();
        if p.test == super::SimTest::ThreePointNotched {
            slots = notched_slots(p);
        } else {
            for zeta in [0.0, row_off, -row_off] {
                for x in [0.0, -half_span, half_span] {
                    slots.push((x, zeta));
                }
            }
            for zeta in [0.0, row_off, -row_off] {
                for x in [-0.5 * p.load_span_mm, 0.5 * p.load_span_mm] {
                    slots.push((x, zeta));
                }
            }
        }
        let specimen = slots
            .into_iter()
            .take(p.specimen_tags as usize)
            .enumerate()
            .map(|(i, (x, zeta))| {
                let role = if x == 0.0 {
                    Some(TagRole::Midspan)
                } else if (x.abs() - half_span).abs() < 1e-9 {
                    Some(TagRole::Support)
                } else {
                    None
                };
                SpecimenPlacement {
                    id: i as u32,
                    x,
                    zeta,
                    role,
                    bitmap: tag_bitmap(TagFamily::Tag36h11, i as u32).expect("tag36h11 ids 0..587"),
                }
            })
            .collect();

        let face_texture = TextureTable::new(&Texture::new(&mut rng, 9.0, 8.0, 60.0), (-0.5 * bl, 0.5 * bl), (-0.5 * bh, 0.5 * bh));
        let top_texture = TextureTable::new(&Texture::new(&mut rng, 6.0, 10.0, 60.0), (-0.5 * bl, 0.5 * bl), (0.0, bw));
        Layout {
            names,
            intrinsics,
            poses,
            bumped,
            panels: vec![back, bench],
            background_ids: {
                debug_assert_eq!(next, BACKGROUND_TAGS);
                vec![ids, bench_ids]
            },
            specimen,
            face_texture,
            top_texture,
        }
    }
}
