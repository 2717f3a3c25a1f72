//! Rendering of the simulated rig's camera images ([`SimRig::render`]): the fixed scene
//! rendered once per camera pose and cached, the beam's image region re-rendered per
//! frame, optical and motion blur, noise and 8-bit rounding (on [`crate::render`]).

use std::sync::{Arc, Mutex, OnceLock};

use nalgebra::Vector3;

use tagdeflect_core::frame::GrayImage;

use super::render::{blur, motion_blur, quantize, render_rect, CornerRays, PixelRect};
use super::rig::mix;
use super::trace::BEAM_BIT;
use super::SimRig;

/// The static image of one camera pose (no beam), before and after optical blur.
struct Background {
    /// The pose's cache key (see `pose_key`).
    epoch: u64,
    raw: Vec<f32>,
    blurred: Vec<f32>,
}

/// Per-camera render state: rays (computed once) and the cached background.
pub(crate) struct CameraState {
    rays: OnceLock<CornerRays>,
    background: Mutex<Option<Arc<Background>>>,
}

impl CameraState {
    /// No rays and no background yet.
    pub(crate) fn new() -> Self {
        CameraState { rays: OnceLock::new(), background: Mutex::new(None) }
    }
}

impl SimRig {
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
