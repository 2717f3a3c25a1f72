//! Renders calibration targets through a known camera, with the simulator's renderer
//! (`tagdeflect_sim::render`: exact undistorted rays through every pixel corner, n-rooks area
//! integration of mixed pixels, optical blur, sensor noise, 8-bit rounding) — images with
//! ground truth for testing [`super::calibrate_views`].

use nalgebra::Vector3;

use super::target::{tag_centre, TargetSpec};
use tagdeflect_core::camera::{CameraIntrinsics, Pose};
use tagdeflect_core::frame::GrayImage;
use tagdeflect_core::tags::TagBitmap;
use tagdeflect_detect::tag_bitmap;
use tagdeflect_sim::render::{blur, gaussian_kernel, quantize, render_rect, CornerRays, Hit, PixelRect};

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
