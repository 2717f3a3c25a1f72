//! Checkerboard corners: found and labelled by `calib-targets-chessboard`, trimmed to the
//! board, refined to sub-pixel by the gradient orthogonality condition (module docs of
//! [`crate::target`]).

use nalgebra::{Point2, Vector3};

use super::detector::{BoardSeen, TargetNotFound};
use crate::solve::View;
use tagdeflect_core::frame::GrayImage;

/// Checkerboard corners: ChESS + grid labelling (`calib-targets-chessboard`), trimmed to
/// the board's size, refined by [`refine_saddle`].
pub(super) fn detect_checkerboard(
    image: &GrayImage,
    name: &str,
    cols: u32,
    rows: u32,
    square_mm: f64,
) -> Result<(View, BoardSeen), TargetNotFound> {
    use calib_targets_chessboard as ct;
    let view = ct::GrayImageView { width: image.width as usize, height: image.height as usize, data: &image.data };
    let corners = ct::detect_corners(&view, &ct::default_chess_config());
    let detector = ct::ChessboardDetector::new(ct::ChessboardParams::default()).map_err(TargetNotFound::ChessboardDetector)?;
    let det = detector.detect(&corners).ok_or(TargetNotFound::NoCheckerboard { junctions: corners.len() })?;
    let mut pts: Vec<(i32, i32, Point2<f64>)> =
        det.corners.iter().map(|c| (c.grid.u, c.grid.v, Point2::new(c.position.x as f64, c.position.y as f64))).collect();
    // The labelling may be the board transposed (cols along v): pick the orientation whose
    // extent fits, trimming sparse outer lines when the grid is larger than the board.
    let extent = |p: &[(i32, i32, Point2<f64>)]| {
        let (umin, umax) = p.iter().fold((i32::MAX, i32::MIN), |a, q| (a.0.min(q.0), a.1.max(q.0)));
        let (vmin, vmax) = p.iter().fold((i32::MAX, i32::MIN), |a, q| (a.0.min(q.1), a.1.max(q.1)));
        (umin, umax, vmin, vmax)
    };
    let on = |p: &(i32, i32, Point2<f64>), (is_u, k): (bool, i32)| if is_u { p.0 == k } else { p.1 == k };
    let labelled = {
        let (umin, umax, vmin, vmax) = extent(&pts);
        ((umax - umin + 1) as u32, (vmax - vmin + 1) as u32)
    };
    // The dense grid: outer lines holding less than half of a full line's corners trimmed
    // (stray X-junctions next to the board; a line cut by the image's edge) — what the view
    // shows of the board whatever the target declares.
    let dense = {
        let mut q = pts.clone();
        loop {
            let (umin, umax, vmin, vmax) = extent(&q);
            let (eu, ev) = (umax - umin + 1, vmax - vmin + 1);
            let lines = [((true, umin), ev), ((true, umax), ev), ((false, vmin), eu), ((false, vmax), eu)];
            let (line, frac) = lines
                .iter()
                .map(|&(l, len)| (l, q.iter().filter(|p| on(p, l)).count() as f64 / len as f64))
                .min_by(|a, b| a.1.total_cmp(&b.1))
                .expect("four lines");
            if frac >= 0.5 || eu <= 2 || ev <= 2 {
                break (eu, ev);
            }
            q.retain(|p| !on(p, line));
        }
    };
    let (cu, cv) = {
        let (eu, ev) = dense;
        // Transposed when that fits better.
        if (eu > ev) == (cols >= rows) {
            (cols as i32, rows as i32)
        } else {
            (rows as i32, cols as i32)
        }
    };
    // Outer lines: (is a u line, index). Drop the sparsest until the grid fits the board.
    loop {
        let (umin, umax, vmin, vmax) = extent(&pts);
        if umax - umin < cu && vmax - vmin < cv {
            break;
        }
        let mut lines: Vec<(bool, i32)> = Vec::new();
        if umax - umin >= cu {
            lines.extend([(true, umin), (true, umax)]);
        }
        if vmax - vmin >= cv {
            lines.extend([(false, vmin), (false, vmax)]);
        }
        let drop = lines.into_iter().min_by_key(|&l| pts.iter().filter(|p| on(p, l)).count()).expect("a line to drop");
        pts.retain(|p| !on(p, drop));
    }
    let min_points = ((cols * rows) as usize / 3).max(6);
    if pts.len() < min_points {
        return Err(TargetNotFound::TooFewCorners { found: pts.len(), need: min_points });
    }
    let (umin, _, vmin, _) = extent(&pts);
    let spacing = det.cell_size.map(|c| c as f64).unwrap_or(20.0);
    let half = (0.4 * spacing).round().clamp(2.0, 11.0) as i32;
    let mut object = Vec::with_capacity(pts.len());
    let mut pixels = Vec::with_capacity(pts.len());
    for (u, v, p) in pts {
        object.push(Vector3::new((u - umin) as f64 * square_mm, (v - vmin) as f64 * square_mm, 0.0));
        pixels.push(refine_saddle(image, p, half).unwrap_or(p));
    }
    // In the declared orientation: (cols, rows) when cols ≥ rows matched u, else swapped.
    let orient = |(a, b): (u32, u32)| if cu as u32 == cols { (a, b) } else { (b, a) };
    let seen = BoardSeen { grid: Some(orient((dense.0 as u32, dense.1 as u32))), labelled: Some(orient(labelled)), ..BoardSeen::default() };
    Ok((View { name: name.to_string(), object, image: pixels }, seen))
}

/// Sub-pixel position of a checkerboard saddle near `start` (OpenCV pixels) from the gradient
/// orthogonality condition in a `(2 half + 1)²` window with Gaussian weights, iterated until
/// it moves less than 0.001 px. `None` when the window leaves the image, the structure
/// tensor is singular, or the corner wanders further than `half` from `start`.
fn refine_saddle(image: &GrayImage, start: Point2<f64>, half: i32) -> Option<Point2<f64>> {
    let (w, h) = (image.width as f64, image.height as f64);
    let hf = half as f64;
    let mut q = start;
    for _ in 0..40 {
        if q.x - hf - 1.0 < 0.0 || q.y - hf - 1.0 < 0.0 || q.x + hf + 1.0 > w - 1.0 || q.y + hf + 1.0 > h - 1.0 {
            return None;
        }
        let (mut a, mut b, mut c, mut bb1, mut bb2) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for j in -half..=half {
            for i in -half..=half {
                let (dx, dy) = (i as f64, j as f64);
                let (x, y) = (q.x + dx, q.y + dy);
                let gx = image.sample(x + 1.0, y) - image.sample(x - 1.0, y);
                let gy = image.sample(x, y + 1.0) - image.sample(x, y - 1.0);
                let m = (-(dx * dx + dy * dy) / (hf * hf)).exp();
                let (gxx, gxy, gyy) = (m * gx * gx, m * gx * gy, m * gy * gy);
                a += gxx;
                b += gxy;
                c += gyy;
                bb1 += gxx * dx + gxy * dy;
                bb2 += gxy * dx + gyy * dy;
            }
        }
        let det = a * c - b * b;
        if det.is_nan() || det.abs() <= 1e-9 * (a * c).abs().max(1e-300) {
            return None;
        }
        let step = nalgebra::Vector2::new(c * bb1 - b * bb2, a * bb2 - b * bb1) / det;
        q += step;
        if (q - start).norm() > hf {
            return None;
        }
        if step.norm() < 1e-3 {
            break;
        }
    }
    Some(q)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn saddle_refinement_finds_a_rendered_corner() {
        // An anti-aliased saddle at (20.3, 17.8) with a lens's blur (σ 0.8 px).
        use tagdeflect_render::{blur, gaussian_kernel};
        let (w, h) = (41u32, 37u32);
        let (x0, y0) = (20.3, 17.8);
        let mut area = vec![0.0f32; (w * h) as usize];
        for y in 0..h {
            for x in 0..w {
                // Exact area fractions of the pixel right of and below the corner.
                let fx = (x as f64 + 0.5 - x0).clamp(0.0, 1.0);
                let fy = (y as f64 + 0.5 - y0).clamp(0.0, 1.0);
                let bright = fx * fy + (1.0 - fx) * (1.0 - fy);
                area[(y * w + x) as usize] = (30.0 + 190.0 * bright) as f32;
            }
        }
        let blurred = blur(&area, w as usize, h as usize, &gaussian_kernel(0.8));
        let img = GrayImage { width: w, height: h, data: blurred.iter().map(|v| v.round() as u8).collect(), deep: None };
        // From where the ChESS detector leaves a corner (within half a pixel).
        for start in [Point2::new(20.0, 18.0), Point2::new(20.6, 17.4)] {
            let q = refine_saddle(&img, start, 6).unwrap();
            assert!((q.x - x0).abs() < 0.05 && (q.y - y0).abs() < 0.05, "{start} → {q}");
        }
    }
}
