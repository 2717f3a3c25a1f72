//! The plan's image geometry: rectangles, the sweep's tiles, the masked copy of a tile
//! searched by the sweep, and the merging of overlapping windows.

use nalgebra::{Point2, Vector2};

use crate::{Detection, Rect};
use tagdeflect_core::frame::GrayImage;

pub(super) fn x1(r: &Rect) -> u32 {
    r.x + r.width
}
pub(super) fn y1(r: &Rect) -> u32 {
    r.y + r.height
}
pub(super) fn overlaps(a: &Rect, b: &Rect) -> bool {
    a.x < x1(b) && b.x < x1(a) && a.y < y1(b) && b.y < y1(a)
}
pub(super) fn union(a: &Rect, b: &Rect) -> Rect {
    let (x, y) = (a.x.min(b.x), a.y.min(b.y));
    Rect { x, y, width: x1(a).max(x1(b)) - x, height: y1(a).max(y1(b)) - y }
}

/// The sweep's tiles of a `width` × `height` frame: a grid whose cells are about three
/// times `overlap` wide, each grown by `overlap` (so any tag smaller than the overlap lies
/// wholly inside some tile), in row-major order.
pub fn sweep_tiles(width: u32, height: u32, overlap: f64) -> Vec<Rect> {
    let overlap = overlap.max(8.0);
    let cell = 3.0 * overlap;
    let nx = ((width as f64 / cell).ceil() as u32).max(1);
    let ny = ((height as f64 / cell).ceil() as u32).max(1);
    let (cw, ch) = (width as f64 / nx as f64, height as f64 / ny as f64);
    let mut out = Vec::with_capacity((nx * ny) as usize);
    for j in 0..ny {
        for i in 0..nx {
            let (x0, y0) = (i as f64 * cw - overlap / 2.0, j as f64 * ch - overlap / 2.0);
            if let Some(r) = clip(width, height, x0, y0, x0 + cw + overlap, y0 + ch + overlap) {
                out.push(r);
            }
        }
    }
    out
}

pub(super) fn clip(width: u32, height: u32, x0: f64, y0: f64, x1: f64, y1: f64) -> Option<Rect> {
    if !(x0.is_finite() && y0.is_finite() && x1.is_finite() && y1.is_finite()) {
        return None;
    }
    let cx0 = x0.floor().max(0.0) as u32;
    let cy0 = y0.floor().max(0.0) as u32;
    let cx1 = (x1.ceil().max(0.0) as u32).min(width);
    let cy1 = (y1.ceil().max(0.0) as u32).min(height);
    (cx1 > cx0 + 8 && cy1 > cy0 + 8).then_some(Rect { x: cx0, y: cy0, width: cx1 - cx0, height: cy1 - cy0 })
}

pub(super) fn bounds(c: &[Point2<f64>; 4]) -> (Vector2<f64>, Vector2<f64>) {
    let mut lo = Vector2::new(f64::MAX, f64::MAX);
    let mut hi = Vector2::new(f64::MIN, f64::MIN);
    for p in c {
        lo = lo.inf(&p.coords);
        hi = hi.sup(&p.coords);
    }
    (lo, hi)
}

pub(super) fn centre(c: &[Point2<f64>; 4]) -> Vector2<f64> {
    (c[0].coords + c[1].coords + c[2].coords + c[3].coords) / 4.0
}
/// Copies `tile` of `image` into `out` (resized to the tile) with the printed area of every
/// tag in `known` — its black square, the white ring and one more cell — filled with the
/// mean grey just outside it. A sweep searches this copy: tags already found are flat
/// patches there, which the contrast filter skips, so the sweep spends its time only on
/// the rest of the tile (a tag's own bits are otherwise most of what a filtered search
/// still fits quads to). Tags never overlap, so no new tag is hidden.
pub fn masked_tile(image: &GrayImage, tile: Rect, known: &[Detection], out: &mut GrayImage) {
    let (tw, th) = (tile.width as usize, tile.height as usize);
    out.width = tile.width;
    out.height = tile.height;
    out.data.resize(tw * th, 0);
    let stride = image.width as usize;
    for row in 0..th {
        let start = (tile.y as usize + row) * stride + tile.x as usize;
        out.data[row * tw..(row + 1) * tw].copy_from_slice(&image.data[start..start + tw]);
    }
    let (ox, oy) = (tile.x as f64, tile.y as f64);
    for d in known {
        let nb = d.family.width_at_border() as f64;
        let c = centre(&d.corners);
        let grow = (nb + 4.0) / nb;
        let poly = d.corners.map(|p| c + (p.coords - c) * grow);
        let (lo, hi) = (
            poly.iter().fold(Vector2::new(f64::MAX, f64::MAX), |a, p| a.inf(p)),
            poly.iter().fold(Vector2::new(f64::MIN, f64::MIN), |a, p| a.sup(p)),
        );
        if hi.x < ox || hi.y < oy || lo.x >= ox + tw as f64 || lo.y >= oy + th as f64 {
            continue;
        }
        // Mean grey along the grown outline (in the frame, clamped to it).
        let mut sum = 0.0;
        let n = 64;
        for k in 0..n {
            let (i, f) = (k * 4 / n, (k % (n / 4)) as f64 / (n / 4) as f64);
            let p = poly[i] + (poly[(i + 1) % 4] - poly[i]) * f;
            sum += image.sample(p.x, p.y);
        }
        let fill = (sum / n as f64).round().clamp(0.0, 255.0) as u8;
        // Orientation-free convex test: the point is on the same side of all four edges.
        let inside = |x: f64, y: f64| {
            let mut sign = 0.0;
            for i in 0..4 {
                let (a, b) = (poly[i], poly[(i + 1) % 4]);
                let cross = (b.x - a.x) * (y - a.y) - (b.y - a.y) * (x - a.x);
                if cross * sign < 0.0 {
                    return false;
                }
                if cross != 0.0 {
                    sign = cross;
                }
            }
            true
        };
        let y0 = (lo.y.floor() - oy).max(0.0) as usize;
        let y1 = ((hi.y.ceil() - oy).max(0.0) as usize).min(th.saturating_sub(1));
        let x0 = (lo.x.floor() - ox).max(0.0) as usize;
        let x1 = ((hi.x.ceil() - ox).max(0.0) as usize).min(tw.saturating_sub(1));
        for y in y0..=y1 {
            for x in x0..=x1 {
                if inside(x as f64 + ox, y as f64 + oy) {
                    out.data[y * tw + x] = fill;
                }
            }
        }
    }
}

/// Merges overlapping rectangles where the merged one costs no more pixels than the two
/// apart (overlapping windows are otherwise searched as they are: each tag lies wholly
/// inside its own window, and detections found twice are de-duplicated).
pub fn merge_rects(mut rects: Vec<Rect>) -> Vec<Rect> {
    let area = |r: &Rect| r.width as u64 * r.height as u64;
    loop {
        let mut merged = false;
        'outer: for i in 0..rects.len() {
            for j in (i + 1)..rects.len() {
                if overlaps(&rects[i], &rects[j]) {
                    let u = union(&rects[i], &rects[j]);
                    if area(&u) <= area(&rects[i]) + area(&rects[j]) {
                        rects[i] = u;
                        rects.swap_remove(j);
                        merged = true;
                        break 'outer;
                    }
                }
            }
        }
        if !merged {
            return rects;
        }
    }
}
