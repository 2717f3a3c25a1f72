//! The scene tracer of the simulated rig: what a ray from a camera centre hits — the fixed
//! scene (panels with background tags) or the deformed beam at one instant (front face with
//! the specimen tags, top, end faces) — and the pixels the beam covers.

use nalgebra::Vector3;

use tagdeflect_core::camera::Pose;

use super::law::{BeamMotion, DeformedShape};
use super::render::{Hit, PixelRect};
use super::scene::shade;
use super::SimRig;

/// Region labels of the beam's surfaces (see [`Hit`]): the beam bit, then the face.
pub(crate) const BEAM_BIT: u32 = 1 << 31;
const FRONT: u32 = BEAM_BIT | (1 << 24);
const TOP: u32 = BEAM_BIT | (2 << 24);
const END: u32 = BEAM_BIT | (3 << 24);
const CARD_CELL: u32 = 0xff;

/// The deformed beam at one instant, ready for tracing.
pub(crate) struct BeamState {
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

impl SimRig {
    /// The deformed beam at `t_ns`, with specimen tag `hidden` (an id) covered by a card.
    pub(crate) fn beam_state(&self, t_ns: i64, hidden: Option<u32>) -> BeamState {
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
    pub(crate) fn tag_shade(bitmap: &tagdeflect_core::tags::TagBitmap, x: f64, y: f64, size: f64) -> f32 {
        match bitmap.cell_at(x, y, size) {
            Some((col, row)) if !bitmap.is_white(col, row) => shade::BLACK,
            _ => shade::WHITE,
        }
    }

    /// The fixed scene (panels with background tags), without the beam; background tag
    /// `hidden` (an id) covered by a grey card.
    pub(crate) fn trace_static(&self, c: &Vector3<f64>, d: &Vector3<f64>, hidden: Option<u32>) -> Hit {
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
                if hidden == Some(tag.bitmap.id) {
                    let half = 0.5 * tag.bitmap.printed_mm(size) + 3.0;
                    if tx.abs() <= half && ty.abs() <= half {
                        hit = (base.0 | ((k as u32 + 1) << 8) | CARD_CELL, shade::CARD, [tx, ty]);
                        break;
                    }
                    continue;
                }
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
    pub(crate) fn trace_beam(&self, st: &BeamState, c: &Vector3<f64>, d: &Vector3<f64>) -> Option<Hit> {
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
    pub(crate) fn beam_rect(&self, cam: usize, pose: &Pose, st: &BeamState) -> PixelRect {
        let p = &self.params;
        let k = &self.layout.intrinsics[cam];
        let lens = crate::lens::Lens::of(k);
        let (hl, hh, bw) = (0.5 * p.beam_length_mm, 0.5 * p.beam_height_mm, p.beam_width_mm);
        let (mut x0, mut y0, mut x1, mut y1) = (f64::INFINITY, f64::INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY);
        let n = 60;
        for i in 0..=n {
            let x = -hl + 2.0 * hl * i as f64 / n as f64;
            for zeta in [-hh, 0.0, hh] {
                let (dx, dz, _) = st.motion.displace(x, zeta);
                for y in [0.0, bw] {
                    let w = Vector3::new(x + dx, y, hh + zeta + dz);
                    if let Some(px) = lens.pixel(&pose.transform(&w)) {
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
}
