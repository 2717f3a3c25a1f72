//! What a calibration means: the text report, the coverage map, the uncertainty of a
//! measurement at a given distance, and the OpenCV FileStorage file.

use std::fmt::Write as _;
use std::path::Path;

use nalgebra::{Point2, SMatrix, Vector2, Vector3};

use super::solve::{Calibration, PARAM_NAMES};
use tagdeflect_core::camera::CameraIntrinsics;

/// Cells of the coverage grid across the image (the rows follow the aspect ratio).
const COVERAGE_COLS: usize = 8;

/// Where the target's points fell in the image.
#[derive(Debug, Clone, PartialEq)]
pub struct Coverage {
    /// Grid columns.
    pub cols: usize,
    /// Grid rows.
    pub rows: usize,
    /// Points per cell, row-major from the top-left.
    pub counts: Vec<usize>,
    /// Fraction of cells holding at least one point.
    pub covered_fraction: f64,
    /// Image corners (top-left, top-right, bottom-left, bottom-right) with no point in their cell.
    pub empty_corners: Vec<&'static str>,
    /// Border cells (outer ring of the grid) without a point.
    pub empty_border_cells: usize,
    /// Border cells in all.
    pub border_cells: usize,
}

impl Coverage {
    /// Counts the points of all views in a grid over a `width` × `height` image.
    pub fn new(width: u32, height: u32, points: &[Point2<f64>]) -> Coverage {
        let cols = COVERAGE_COLS;
        let rows = ((cols as f64 * height as f64 / width.max(1) as f64).round() as usize).max(3);
        let mut counts = vec![0usize; cols * rows];
        for p in points {
            let c = ((p.x + 0.5) / width as f64 * cols as f64).floor();
            let r = ((p.y + 0.5) / height as f64 * rows as f64).floor();
            if c >= 0.0 && r >= 0.0 && (c as usize) < cols && (r as usize) < rows {
                counts[r as usize * cols + c as usize] += 1;
            }
        }
        let corner_cells =
            [("top-left", 0), ("top-right", cols - 1), ("bottom-left", (rows - 1) * cols), ("bottom-right", rows * cols - 1)];
        let empty_corners = corner_cells.iter().filter(|(_, i)| counts[*i] == 0).map(|(n, _)| *n).collect();
        let border: Vec<usize> =
            (0..rows * cols).filter(|i| i / cols == 0 || i / cols == rows - 1 || i % cols == 0 || i % cols == cols - 1).collect();
        let empty_border_cells = border.iter().filter(|&&i| counts[i] == 0).count();
        let covered = counts.iter().filter(|&&c| c > 0).count();
        Coverage {
            cols,
            rows,
            counts,
            covered_fraction: covered as f64 / (cols * rows) as f64,
            empty_corners,
            empty_border_cells,
            border_cells: border.len(),
        }
    }

    /// The warning to print, if the image's corners or borders were not covered.
    pub fn warning(&self) -> Option<String> {
        if self.empty_corners.is_empty() && self.empty_border_cells * 4 <= self.border_cells {
            return None;
        }
        let mut w = String::from("coverage: ");
        if !self.empty_corners.is_empty() {
            let _ = write!(w, "no target points in the {} corner(s) of the image; ", self.empty_corners.join(", "));
        }
        let _ = write!(
            w,
            "{} of {} border cells empty. Distortion is largest there: add views with the target near the edges and corners.",
            self.empty_border_cells, self.border_cells
        );
        Some(w)
    }

    /// Writes the coverage map as PNG: the grid over the image (scaled so its longest side is
    /// at most 640 px), empty cells red, covered cells green by count, every point a dot,
    /// each view's points in their own colour.
    pub(crate) fn write_png(&self, path: &Path, width: u32, height: u32, views: &[Vec<Point2<f64>>]) -> std::io::Result<()> {
        let scale = (640.0 / width.max(height) as f64).min(1.0);
        let (w, h) = (((width as f64) * scale).round().max(1.0) as usize, ((height as f64) * scale).round().max(1.0) as usize);
        let mut rgb = vec![0u8; w * h * 3];
        let maxc = self.counts.iter().copied().max().unwrap_or(1).max(1) as f64;
        for y in 0..h {
            for x in 0..w {
                let c = (x * self.cols / w).min(self.cols - 1);
                let r = (y * self.rows / h).min(self.rows - 1);
                let n = self.counts[r * self.cols + c];
                let px = if n == 0 { [120u8, 30, 30] } else { [25, (60.0 + 120.0 * (n as f64 / maxc).sqrt()) as u8, 40] };
                let line = (x * self.cols) % w < self.cols || (y * self.rows) % h < self.rows;
                let px = if line { [90, 90, 90] } else { px };
                rgb[(y * w + x) * 3..(y * w + x) * 3 + 3].copy_from_slice(&px);
            }
        }
        for (i, pts) in views.iter().enumerate() {
            // Distinct hues per view, bright on the dark cells.
            let hue = (i as f64 * 0.618_034) % 1.0;
            let col = hsv(hue, 0.45, 1.0);
            for p in pts {
                let (cx, cy) = (((p.x + 0.5) * scale) as i64, ((p.y + 0.5) * scale) as i64);
                for dy in -1..=1 {
                    for dx in -1..=1 {
                        let (x, y) = (cx + dx, cy + dy);
                        if x >= 0 && y >= 0 && (x as usize) < w && (y as usize) < h {
                            let o = (y as usize * w + x as usize) * 3;
                            rgb[o..o + 3].copy_from_slice(&col);
                        }
                    }
                }
            }
        }
        let file = std::fs::File::create(path)?;
        let mut enc = png::Encoder::new(std::io::BufWriter::new(file), w as u32, h as u32);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        let mut writer = enc.write_header().map_err(std::io::Error::other)?;
        writer.write_image_data(&rgb).map_err(std::io::Error::other)?;
        writer.finish().map_err(std::io::Error::other)?;
        Ok(())
    }
}

fn hsv(h: f64, s: f64, v: f64) -> [u8; 3] {
    let i = (h * 6.0).floor();
    let f = h * 6.0 - i;
    let (p, q, t) = (v * (1.0 - s), v * (1.0 - f * s), v * (1.0 - (1.0 - f) * s));
    let (r, g, b) = match i as i64 % 6 {
        0 => (v, t, p),
        1 => (q, v, p),
        2 => (p, v, t),
        3 => (p, q, v),
        4 => (t, p, v),
        _ => (v, p, q),
    };
    [(r * 255.0) as u8, (g * 255.0) as u8, (b * 255.0) as u8]
}

/// What the intrinsics' uncertainty means for a point seen at one place in the image.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PointUncertainty {
    /// Where in the image ("centre", "edge", "corner").
    pub place: &'static str,
    /// The pixel.
    pub pixel: Point2<f64>,
    /// 1-σ of the point's position across the line of sight at the given distance, mm
    /// (√ of the trace of its 2×2 covariance): the error of an absolute position from this
    /// camera alone at a known distance.
    pub lateral_mm: f64,
    /// 1-σ error of a displacement of `displacement_mm` across the line of sight measured there
    /// (what a deflection measurement sees: constant offsets cancel, scale and distortion errors
    /// do not), mm.
    pub displacement_error_mm: f64,
}

/// The uncertainty report at distance `z_mm` for a displacement of `displacement_mm`:
/// centre, middle of the right edge and top-left corner of the image (10 % inside).
///
/// First-order propagation of the intrinsics covariance: the back-projection `x_n(u; θ)` of a
/// pixel `u` moves by `(∂x_n/∂θ) δθ = −(∂u/∂x_n)⁻¹ (∂u/∂θ) δθ`, scaled by the distance.
pub fn uncertainty_at(k: &CameraIntrinsics, cov: &SMatrix<f64, 9, 9>, z_mm: f64, displacement_mm: f64) -> Vec<PointUncertainty> {
    let (w, h) = (k.width.max(1) as f64, k.height.max(1) as f64);
    let places = [
        ("centre", Point2::new(k.cx, k.cy)),
        ("edge", Point2::new(0.9 * (w - 1.0), k.cy)),
        ("corner", Point2::new(0.1 * (w - 1.0), 0.1 * (h - 1.0))),
    ];
    places
        .iter()
        .map(|&(place, pixel)| {
            let xn = k.undistort(&pixel);
            let j_xn = back_projection_jacobian(k, &xn);
            let c = j_xn * cov * j_xn.transpose();
            let lateral_mm = z_mm * c.trace().max(0.0).sqrt();
            // A vertical displacement at that point: the difference of two back-projections.
            let p1 = Vector3::new(xn.x * z_mm, xn.y * z_mm, z_mm);
            let p2 = p1 + Vector3::new(0.0, displacement_mm, 0.0);
            let displacement_error_mm = match k.project(&p2) {
                Some(u2) => {
                    let xn2 = k.undistort(&u2);
                    let j2 = back_projection_jacobian(k, &xn2);
                    let g = (j2 - j_xn) * z_mm;
                    (g * cov * g.transpose()).trace().max(0.0).sqrt()
                }
                None => f64::NAN,
            };
            PointUncertainty { place, pixel, lateral_mm, displacement_error_mm }
        })
        .collect()
}

/// `∂x_n/∂θ` (2 × 9) of the back-projection at normalised point `xn`.
fn back_projection_jacobian(k: &CameraIntrinsics, xn: &Vector2<f64>) -> SMatrix<f64, 2, 9> {
    let p = Vector3::new(xn.x, xn.y, 1.0);
    let ju = k.project_intrinsics_jacobian(&p).expect("z = 1");
    let jd = k.distort_jacobian(*xn);
    let jpx = nalgebra::Matrix2::new(k.fx, 0.0, 0.0, k.fy) * jd;
    match jpx.try_inverse() {
        Some(inv) => -(inv * ju),
        None => SMatrix::<f64, 2, 9>::repeat(f64::NAN),
    }
}

fn fs_number(v: f64) -> String {
    if v == 0.0 {
        return "0.".into();
    }
    let s = format!("{v:.16e}");
    match s.split_once('e') {
        Some((m, e)) if !e.starts_with('-') => format!("{m}e+{:0>2}", e),
        Some((m, e)) => format!("{m}e-{:0>2}", &e[1..]),
        None => s,
    }
}

fn fs_matrix(out: &mut String, key: &str, rows: usize, cols: usize, data: &[f64]) {
    let _ = writeln!(out, "{key}: !!opencv-matrix\n   rows: {rows}\n   cols: {cols}\n   dt: d");
    let items: Vec<String> = data.iter().map(|v| fs_number(*v)).collect();
    let _ = write!(out, "   data: [");
    for (i, it) in items.iter().enumerate() {
        if i > 0 {
            out.push(',');
            if i % 3 == 0 {
                out.push_str("\n       ");
            }
        }
        out.push(' ');
        out.push_str(it);
    }
    out.push_str(" ]\n");
}

/// The calibration as an OpenCV FileStorage YAML (what `cv::FileStorage` writes and
/// `calibration = "..."` reads): `image_width`, `image_height`, `camera_matrix`,
/// `distortion_coefficients` (k1 k2 p1 p2 k3), `avg_reprojection_error`,
/// `per_view_reprojection_errors`, plus `intrinsics_sigma` (1-σ of fx fy cx cy k1 k2 p1 p2 k3)
/// and the target and flags as comments.
pub fn opencv_yaml(c: &Calibration, target: &str, flags: &str, view_names: &[String]) -> String {
    let k = &c.intrinsics;
    let mut out = String::from("%YAML:1.0\n---\n");
    let _ = writeln!(out, "# tagdeflect calibrate: {target}; {flags}");
    let _ = writeln!(out, "calibration_time: \"{}\"", chrono::Utc::now().format("%Y-%m-%dT%H:%M:%SZ"));
    let _ = writeln!(out, "nframes: {}", c.poses.len());
    let _ = writeln!(out, "image_width: {}", k.width);
    let _ = writeln!(out, "image_height: {}", k.height);
    fs_matrix(&mut out, "camera_matrix", 3, 3, &[k.fx, 0.0, k.cx, 0.0, k.fy, k.cy, 0.0, 0.0, 1.0]);
    fs_matrix(&mut out, "distortion_coefficients", 5, 1, &k.dist);
    let _ = writeln!(out, "# 1-sigma of {}", PARAM_NAMES.join(" "));
    fs_matrix(&mut out, "intrinsics_sigma", 9, 1, &c.sigmas());
    let _ = writeln!(out, "avg_reprojection_error: {}", fs_number(c.rms_px));
    let _ = writeln!(out, "# views: {}", view_names.join(" "));
    fs_matrix(&mut out, "per_view_reprojection_errors", c.view_rms_px.len(), 1, &c.view_rms_px);
    out
}
