//! A rectangle of pixels (a detection window).

use nalgebra::Point2;

/// A rectangle of pixels: columns `x..x+width`, rows `y..y+height` (a detection window).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Rect {
    /// First column.
    pub x: u32,
    /// First row.
    pub y: u32,
    /// Number of columns.
    pub width: u32,
    /// Number of rows.
    pub height: u32,
}

impl Rect {
    /// The square window of half-size `half` pixels around `centre` (OpenCV pixels), clamped
    /// to an image of `width` × `height`; `None` when nothing of it lies in the image.
    pub fn around(centre: Point2<f64>, half: f64, width: u32, height: u32) -> Option<Rect> {
        if !(centre.x.is_finite() && centre.y.is_finite() && half.is_finite()) || half < 0.0 {
            return None;
        }
        let x0 = (centre.x - half).floor().max(0.0);
        let y0 = (centre.y - half).floor().max(0.0);
        let x1 = (centre.x + half).ceil().min(width as f64 - 1.0);
        let y1 = (centre.y + half).ceil().min(height as f64 - 1.0);
        if x1 < x0 || y1 < y0 {
            return None;
        }
        Some(Rect { x: x0 as u32, y: y0 as u32, width: (x1 - x0) as u32 + 1, height: (y1 - y0) as u32 + 1 })
    }

    /// The bounding window of some points (OpenCV pixels) grown by `margin`, clamped to the image.
    pub fn bounding(points: &[Point2<f64>], margin: f64, width: u32, height: u32) -> Option<Rect> {
        if points.is_empty() || points.iter().any(|p| !(p.x.is_finite() && p.y.is_finite())) || !margin.is_finite() {
            return None;
        }
        let (mut xmin, mut ymin, mut xmax, mut ymax) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
        for p in points {
            xmin = xmin.min(p.x);
            ymin = ymin.min(p.y);
            xmax = xmax.max(p.x);
            ymax = ymax.max(p.y);
        }
        let x0 = (xmin - margin).floor().max(0.0);
        let y0 = (ymin - margin).floor().max(0.0);
        let x1 = (xmax + margin).ceil().min(width as f64 - 1.0);
        let y1 = (ymax + margin).ceil().min(height as f64 - 1.0);
        if x1 < x0 || y1 < y0 {
            return None;
        }
        Some(Rect { x: x0 as u32, y: y0 as u32, width: (x1 - x0) as u32 + 1, height: (y1 - y0) as u32 + 1 })
    }

    /// The same rectangle with its origin moved down to a multiple of `align` (size grown to
    /// keep the far edges).
    pub fn aligned(self, align: u32) -> Rect {
        let align = align.max(1);
        let x = self.x - self.x % align;
        let y = self.y - self.y % align;
        Rect { x, y, width: self.width.saturating_add(self.x - x), height: self.height.saturating_add(self.y - y) }
    }

    /// The part inside an image of `width` × `height`; `None` when empty.
    pub fn clamp_to(self, width: u32, height: u32) -> Option<Rect> {
        if self.x >= width || self.y >= height || self.width == 0 || self.height == 0 {
            return None;
        }
        Some(Rect { x: self.x, y: self.y, width: self.width.min(width - self.x), height: self.height.min(height - self.y) })
    }

    /// True when the point (OpenCV pixels) lies inside the rectangle's pixels.
    pub fn contains(&self, p: &Point2<f64>) -> bool {
        p.x >= self.x as f64 - 0.5
            && p.y >= self.y as f64 - 0.5
            && p.x < self.x as f64 + self.width as f64 - 0.5
            && p.y < self.y as f64 + self.height as f64 - 0.5
    }

    /// Number of pixels.
    pub fn area(&self) -> u64 {
        self.width as u64 * self.height as u64
    }
}
