//! Rendering of the simulated rig's camera images ([`SimRig::render`]): the fixed scene
//! rendered once per camera pose and cached, the beam's image region re-rendered per
//! frame, the optics' blur, motion blur, the exposure and shot noise ([`crate::sensor`]), the
//! camera's processing, read noise, the sensor's bit depth, 8-bit storage and JPEG (on
//! [`crate::render`]).

use std::sync::{Arc, Mutex, OnceLock};

use nalgebra::Vector3;

use tagdeflect_core::frame::GrayImage;

use super::render::{formation, motion_blur, quantize_bits, render_rect, CornerRays, PixelRect};
use super::rig::mix;
use super::trace::BEAM_BIT;
use super::SimRig;

/// The static image of one camera pose (no beam): its sub-box integrals ([`Optics`]) and
/// the pixel image through the optics.
///
/// [`Optics`]: crate::render::Optics
struct Background {
    /// The pose's cache key (see `pose_key`).
    epoch: u64,
    /// Sub-box integrals, `w·scale × h·scale`.
    raw: Vec<f32>,
    /// Pixels, `w × h`.
    blurred: Vec<f32>,
}

/// Per-camera render state: rays (computed once) and the cached background.
pub(crate) struct CameraRenderCache {
    rays: OnceLock<CornerRays>,
    background: Mutex<Option<Arc<Background>>>,
}

impl CameraRenderCache {
    /// No rays and no background yet.
    pub(crate) fn new() -> Self {
        CameraRenderCache { rays: OnceLock::new(), background: Mutex::new(None) }
    }
}

impl SimRig {
    /// The rays through the corners of camera `cam`'s sub-boxes.
    fn rays(&self, cam: usize) -> &CornerRays {
        self.cams[cam].rays.get_or_init(|| CornerRays::sub_boxes(&self.layout.intrinsics[cam], self.optics.scale()))
    }

    /// Sub-box sub-samples per axis ([`crate::render::Optics::sub_box_samples`]).
    fn sub_box_samples(&self) -> usize {
        self.optics.sub_box_samples(self.params.subsamples as usize)
    }

    fn background(&self, cam: usize, t_ns: i64) -> Arc<Background> {
        let hidden = self.hidden_background_tag(cam, self.set_index_at(t_ns));
        let epoch = self.pose_key(cam, t_ns) | (hidden.is_some() as u64) << 48;
        let mut slot = self.cams[cam].background.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(bg) = slot.as_ref() {
            if bg.epoch == epoch {
                return bg.clone();
            }
        }
        let pose = self.camera_pose(cam, t_ns);
        let rays = self.rays(cam);
        let (wf, hf) = (rays.w, rays.h);
        let rot_cw = pose.rotation.inverse();
        let centre = pose.centre();
        let mut raw = vec![0.0f32; wf * hf];
        let trace = |d: &Vector3<f64>| self.trace_static(&centre, d, hidden);
        let sample = |d: &Vector3<f64>, _: usize, _: usize| self.trace_static(&centre, d, hidden).1;
        let all = PixelRect { x0: 0, y0: 0, x1: wf, y1: hf };
        let bg_size = self.params.background_tag_mm;
        let flat = |key: u32, x: f64, y: f64| -> f32 {
            let panel = &self.layout.panels[((key >> 16) & 0xff) as usize - 1];
            let tag = &panel.tags[((key >> 8) & 0xff) as usize - 1];
            Self::tag_shade(&tag.bitmap, x, y, bg_size)
        };
        render_rect(rays, &rot_cw, all, self.sub_box_samples(), &trace, &sample, None, Some(&flat), &mut raw);
        let blurred = self.optics.apply(&raw, wf, hf);
        let bg = Arc::new(Background { epoch, raw, blurred });
        *slot = Some(bg.clone());
        bg
    }

    /// The camera's processing of the integrated pixels (`bayer`, `post_blur_px`,
    /// `sharpen`, in that order; see [`crate::render::formation`]).
    fn after_pixels(&self, img: Vec<f32>, w: usize, h: usize) -> Vec<f32> {
        after_pixels_of(&self.params, img, w, h)
    }

    /// Renders camera `cam`'s image at `t_ns` (grey, the camera's size): digitised at the
    /// sensor's `bit_depth` (deeper than 8 bits: kept at full depth beside the 8-bit plane,
    /// so recordings store 16-bit PNGs), through JPEG when `jpeg_quality` is set (JPEG
    /// frames are 8-bit: the full depth is dropped).
    ///
    /// The fixed scene is rendered once per camera pose and cached; each call re-renders
    /// only the beam's image region, passes it and its surroundings through the optics
    /// ([`crate::render::Optics`]), then adds fresh noise (seeded by
    /// the rig's seed, the camera and `t_ns`, so the same call gives the same image).
    /// Motion blur and hidden tags apply per the frame set nearest to `t_ns`.
    ///
    /// Panics if `cam >= camera_count()`.
    pub fn render(&self, cam: usize, t_ns: i64) -> GrayImage {
        let k = self.set_index_at(t_ns);
        let bg = self.background(cam, t_ns);
        let rays = self.rays(cam);
        let s = self.optics.scale();
        let (wf, hf) = (rays.w, rays.h);
        let (w, h) = (wf / s, hf / s);
        let pose = self.camera_pose(cam, t_ns);
        let st = self.beam_state(t_ns, self.hidden_tag(cam, k));
        let rect = self.beam_rect(cam, &pose, &st);
        let mut img = bg.blurred.clone();
        if !rect.is_empty() {
            // Pixels: the beam's `rect`, what its light reaches (`valid`), and what light
            // reaches those from (`outer`).
            let r = self.optics.reach_px();
            let outer = rect.grow(2 * r, w, h);
            let valid = rect.grow(r, w, h);
            // Sub-box integrals over `outer`: the background's, then the beam's over `rect`.
            let (rect, outer_f) = (rect.scaled(s), outer.scaled(s));
            let (ow, oh) = (outer_f.width(), outer_f.height());
            let mut comp = vec![0.0f32; ow * oh];
            for (j, row) in comp.chunks_mut(ow).enumerate() {
                let y = outer_f.y0 + j;
                row.copy_from_slice(&bg.raw[y * wf + outer_f.x0..y * wf + outer_f.x1]);
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
                None => bg.raw[y * wf + x],
            };
            let not_beam = |l: u32| l & BEAM_BIT == 0;
            let n = self.sub_box_samples();
            let size = self.params.specimen_tag_mm;
            let flat = |key: u32, x: f64, y: f64| -> f32 {
                let s = &self.layout.specimen[((key >> 8) & 0xff) as usize - 1];
                Self::tag_shade(&s.bitmap, x, y, size)
            };
            let rot = pose.rotation.inverse();
            render_rect(rays, &rot, rect, n, &corner, &sample, Some((&not_beam, &bg.raw)), Some(&flat), &mut beam_px);
            for (j, row) in beam_px.chunks(rect.width()).enumerate() {
                let y = rect.y0 + j - outer_f.y0;
                let x = rect.x0 - outer_f.x0;
                comp[y * ow + x..y * ow + x + rect.width()].copy_from_slice(row);
            }
            // `outer`'s pixels; right wherever the point-spread function lay inside `outer`
            // or the image edge: over `valid`.
            let px = self.optics.apply(&comp, ow, oh);
            let pw = outer.width();
            for y in valid.y0..valid.y1 {
                let src = &px[(y - outer.y0) * pw + valid.x0 - outer.x0..(y - outer.y0) * pw + valid.x1 - outer.x0];
                img[y * w + valid.x0..y * w + valid.x1].copy_from_slice(src);
            }
        }
        if self.has_motion_blur(cam, k) {
            let angle = (mix(self.params.seed, k as u64) % 360) as f64 * std::f64::consts::PI / 180.0;
            img = motion_blur(&img, w, h, self.params.motion_blur_px, angle);
        }
        let seed = mix(mix(self.params.seed, 0x4015e), mix(cam as u64, t_ns as u64));
        crate::sensor::expose(&mut img, w, self.params.exposure, self.params.full_well_e, mix(seed, 0x5407));
        img = self.after_pixels(img, w, h);
        let stored = if self.params.bayer_raw {
            raw_bayer_converted(&img, w, h, self.params.noise_sigma, seed)
        } else {
            quantize_bits(&img, w, h, self.params.noise_sigma, seed, self.params.bit_depth)
        };
        match self.params.jpeg_quality {
            // Validated sizes (at most 8192 px a side) are within JPEG's 65535.
            Some(q) => formation::jpeg_round_trip(&stored, q).expect("an 8-bit grey image of a validated size encodes as JPEG"),
            None => stored,
        }
    }
}

/// The camera's processing after the pixels of `p` (`bayer`, `post_blur_px`, `sharpen`, in
/// that order): what [`SimRig::render`] applies, shared with [`crate::edge_patch`].
pub(crate) fn after_pixels_of(p: &crate::SimParams, mut img: Vec<f32>, w: usize, h: usize) -> Vec<f32> {
    if p.bayer {
        img = formation::bayer_demosaic_bilinear(&img, w, h);
    }
    if p.post_blur_px > 0.0 {
        img = formation::blur_after_pixels(&img, w, h, p.post_blur_px);
    }
    if p.sharpen > 0.0 {
        img = formation::convolve3x3(&img, w, h, &formation::sharpen_kernel(p.sharpen));
    }
    img
}

/// The grey scene `img` seen by an RGGB sensor delivering its raw 8-bit mosaic
/// ([`formation::bayer_mosaic`], read noise `noise_sigma` at each photosite), converted as the
/// product converts a V4L2 `RGGB` or GenICam `BayerRG8` frame.
fn raw_bayer_converted(img: &[f32], w: usize, h: usize, noise_sigma: f64, seed: u64) -> GrayImage {
    use tagdeflect_io::sources::convert::{to_gray8, BayerPattern, PixelLayout};
    let mosaic = formation::bayer_mosaic(img, w, &formation::RAW_BAYER_RESPONSES);
    let raw = quantize_bits(&mosaic, w, h, noise_sigma, seed, 8);
    to_gray8(PixelLayout::Bayer8(BayerPattern::Rggb), w as u32, h as u32, 0, &raw.data).expect("a rendered mosaic has width × height bytes")
}
