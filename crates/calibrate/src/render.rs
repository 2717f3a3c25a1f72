//! Renders calibration targets through a known camera, with the simulator's renderer
//! (`tagdeflect_render`: exact undistorted rays through every pixel corner, n-rooks area
//! integration of mixed pixels, optical blur, sensor noise, 8-bit rounding) — images with
//! ground truth for testing [`crate::calibrate_views`].
//!
//! The renderer is its own crate, below both the simulator and the calibration: the
//! calibration's test images need the renderer, not the simulated rig, so the calibration
//! does not depend on the simulator (which stands on the solver, the I/O and the Modbus
//! machine); the images are a test helper, public because the integration tests use them.

use nalgebra::Vector3;

use super::target::{tag_centre, TargetSpec};
use tagdeflect_core::camera::{CameraIntrinsics, Pose};
use tagdeflect_core::frame::GrayImage;
use tagdeflect_core::tags::{TagBitmap, TagFamily};
use tagdeflect_detect::tag_bitmap;
use tagdeflect_render::{blur, gaussian_kernel, quantize, render_rect, CornerRays, Hit, PixelRect};

/// How a target image is rendered.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RenderOptions {
    /// Sub-samples per axis in mixed pixels.
    pub supersample: usize,
    /// Optical blur σ, pixels.
    pub blur_px: f64,
    /// Sensor noise σ, grey levels.
    pub noise: f64,
    /// Grey level of black print.
    pub black: f32,
    /// Grey level of white paper.
    pub white: f32,
    /// Grey level behind the target.
    pub background: f32,
    /// Noise seed.
    pub seed: u64,
}

impl Default for RenderOptions {
    fn default() -> Self {
        Self { supersample: 8, blur_px: 0.7, noise: 1.5, black: 30.0, white: 220.0, background: 110.0, seed: 1 }
    }
}

/// Renders `spec` seen by camera `k` with the board at `pose` (board → camera, mm).
pub fn render_target(spec: &TargetSpec, k: &CameraIntrinsics, pose: &Pose, o: &RenderOptions) -> GrayImage {
    let rays = CornerRays::new(k);
    let (w, h) = (k.width as usize, k.height as usize);
    // Camera → board: directions and centre in the board frame.
    let inv = pose.inverse();
    let centre = inv.translation;
    let bitmaps: Vec<TagBitmap> = match spec {
        TargetSpec::TagBoard { family, cols, rows, first_id, .. } => {
            (0..cols * rows).map(|i| tag_bitmap(*family, first_id + i).expect("board ids validated")).collect()
        }
        TargetSpec::AprilGrid { cols, rows, .. } => {
            (0..cols * rows).map(|i| tag_bitmap(TagFamily::Tag36h11, i).expect("grid ids validated")).collect()
        }
        TargetSpec::Checkerboard { .. } => Vec::new(),
    };
    let (black, white, bg) = (o.black, o.white, o.background);
    let shade = |x: f64, y: f64| -> (u32, f32) {
        match *spec {
            TargetSpec::Checkerboard { cols, rows, square_mm } => {
                // Squares span one square beyond the outer inner corners; a white margin of
                // one more square around them (the paper).
                let (i, j) = ((x / square_mm).floor() as i64, (y / square_mm).floor() as i64);
                let (cols, rows) = (cols as i64, rows as i64);
                if i < -2 || j < -2 || i > cols || j > rows {
                    (2, bg)
                } else if i < -1 || j < -1 || i > cols - 1 || j > rows - 1 {
                    (1, white)
                } else if (i + j).rem_euclid(2) == 0 {
                    (0, black)
                } else {
                    (1, white)
                }
            }
            TargetSpec::TagBoard { cols, rows, size_mm, pitch_mm, .. } => {
                let c = (x / pitch_mm).round();
                let r = (-y / pitch_mm).round();
                let margin = pitch_mm;
                let inside_paper = x > -margin
                    && x < (cols as f64 - 1.0) * pitch_mm + margin
                    && -y > -margin
                    && -y < (rows as f64 - 1.0) * pitch_mm + margin;
                if !inside_paper {
                    return (2, bg);
                }
                if c < 0.0 || r < 0.0 || c >= cols as f64 || r >= rows as f64 {
                    return (1, white);
                }
                let (c, r) = (c as u32, r as u32);
                let t = tag_centre(c, r, pitch_mm);
                let bm = &bitmaps[(r * cols + c) as usize];
                match bm.cell_at(x - t.x, y - t.y, size_mm) {
                    Some((cc, rr)) if !bm.is_white(cc, rr) => (0, black),
                    _ => (1, white),
                }
            }
            TargetSpec::AprilGrid { cols, rows, tag_mm, spacing } => {
                // Kalibr's layout: tag (c, r) spans [c p, c p + tag] × [r p, r p + tag]; a black
                // square of the gap's size in every gap crossing, the outer ones included; white
                // paper one gap beyond them.
                let gap = spacing * tag_mm;
                let p = tag_mm + gap;
                let (cf, rf) = ((x / p).floor(), (y / p).floor());
                let (u, v) = (x - cf * p, y - rf * p);
                let (wide, high) = (cols as f64 * p - gap, rows as f64 * p - gap);
                if x < -2.0 * gap || y < -2.0 * gap || x > wide + 2.0 * gap || y > high + 2.0 * gap {
                    return (2, bg);
                }
                let in_gap_x = u >= tag_mm;
                let in_gap_y = v >= tag_mm;
                let inside = x >= -gap && y >= -gap && x <= wide + gap && y <= high + gap;
                if in_gap_x && in_gap_y {
                    return if inside { (0, black) } else { (1, white) };
                }
                if in_gap_x || in_gap_y || cf < 0.0 || rf < 0.0 || cf >= cols as f64 || rf >= rows as f64 {
                    return (1, white);
                }
                // Inside tag (cf, rf): 10 cells, the outer ring black, the inner 8 × 8 the tag's
                // bitmap (whose own outer ring is the white one, here black), rows from the top.
                let cell = tag_mm / 10.0;
                let (cc, rr) = ((u / cell).floor().clamp(0.0, 9.0) as u32, (9.0 - (v / cell).floor()).clamp(0.0, 9.0) as u32);
                let bm = &bitmaps[(rf as u32 * cols + cf as u32) as usize];
                if cc == 0 || rr == 0 || cc == 9 || rr == 9 || !bm.is_white(cc, rr) {
                    (0, black)
                } else {
                    (1, white)
                }
            }
        }
    };
    let hit = |d: &Vector3<f64>| -> Hit {
        if d.z.abs() < 1e-12 {
            return (2, bg, [0.0; 2]);
        }
        let s = -centre.z / d.z;
        if s <= 0.0 {
            return (2, bg, [0.0; 2]);
        }
        let p = centre + d * s;
        let (l, v) = shade(p.x, p.y);
        (l, v, [0.0; 2])
    };
    let sample = |d: &Vector3<f64>, _x: usize, _y: usize| hit(d).1;
    let mut img = vec![0.0f32; w * h];
    let rect = PixelRect { x0: 0, y0: 0, x1: w, y1: h };
    render_rect(&rays, &inv.rotation, rect, o.supersample, &hit, &sample, None, None, &mut img);
    let img = blur(&img, w, h, &gaussian_kernel(o.blur_px));
    quantize(&img, w, h, o.noise, o.seed)
}
