//! The points a plot draws, reduced to what its pixels can show. The plots get every line of
//! a feed (a million lines for a long test); drawn one by one they were the peak of the
//! report's memory while writing and most of its plotting time. Plotters maps every point to
//! a whole pixel before drawing, so:
//!
//! - a **line** keeps, of each run of consecutive points that fall in one pixel column, the
//!   first, the lowest, the highest and the last, in their order (M4): the segments inside
//!   one column cover the rows from its lowest to its highest point, and the run joins its
//!   neighbours at its first and last point — the same pixels, at most four points a column
//!   run;
//! - a **scatter** of equal markers keeps the first point of each pixel: a marker drawn
//!   again at the same pixel changes nothing.
//!
//! Only drawing reads these points: every number of the report comes from the full curve.

use std::collections::HashSet;

/// A backend pixel, as plotters maps a point to it before drawing.
pub(crate) type Pixel = (i32, i32);

/// The points of a polyline that draw its pixels: per run of consecutive points in one pixel
/// column (`pixel(p).0`), the first, the lowest, the highest and the last, in their order,
/// each once. Non-finite points are left out (plotters cannot place them).
pub(crate) fn line_points(points: impl IntoIterator<Item = (f64, f64)>, pixel: impl Fn(&(f64, f64)) -> Pixel) -> Vec<(f64, f64)> {
    let mut out = Vec::new();
    let mut run: Option<Run> = None;
    for (i, p) in points.into_iter().filter(|p| p.0.is_finite() && p.1.is_finite()).enumerate() {
        let px = pixel(&p);
        match run.as_mut() {
            Some(r) if r.column == px.0 => r.add(i, p, px.1),
            _ => {
                if let Some(r) = run.take() {
                    r.flush(&mut out);
                }
                run = Some(Run::new(i, p, px));
            }
        }
    }
    if let Some(r) = run {
        r.flush(&mut out);
    }
    out
}

/// The points of a scatter of equal markers that draw its pixels: the first of each pixel.
/// Non-finite points are left out. What is held besides the result is bounded by the
/// pixels, not by the points.
pub(crate) fn scatter_points(points: impl IntoIterator<Item = (f64, f64)>, pixel: impl Fn(&(f64, f64)) -> Pixel) -> Vec<(f64, f64)> {
    let mut seen: HashSet<Pixel> = HashSet::new();
    points.into_iter().filter(|p| p.0.is_finite() && p.1.is_finite() && seen.insert(pixel(p))).collect()
}

/// A run of consecutive points in one pixel column: `(index, point, row)` of its first,
/// lowest row, highest row and last point.
struct Run {
    column: i32,
    first: (usize, (f64, f64)),
    low: (usize, (f64, f64), i32),
    high: (usize, (f64, f64), i32),
    last: (usize, (f64, f64)),
}

impl Run {
    fn new(i: usize, p: (f64, f64), px: Pixel) -> Run {
        Run { column: px.0, first: (i, p), low: (i, p, px.1), high: (i, p, px.1), last: (i, p) }
    }

    fn add(&mut self, i: usize, p: (f64, f64), row: i32) {
        if row < self.low.2 {
            self.low = (i, p, row);
        }
        if row > self.high.2 {
            self.high = (i, p, row);
        }
        self.last = (i, p);
    }

    /// Appends the run's kept points in their order, each once.
    fn flush(self, out: &mut Vec<(f64, f64)>) {
        let mut kept = [self.first, (self.low.0, self.low.1), (self.high.0, self.high.1), self.last];
        kept.sort_by_key(|k| k.0);
        let mut previous = None;
        for (i, p) in kept {
            if previous != Some(i) {
                out.push(p);
                previous = Some(i);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Pixels of a 900-column plot of `t` in 0..=1000 s and `y` in -10..=10 (row 0 at the top).
    fn pixel(p: &(f64, f64)) -> Pixel {
        ((p.0 / 1000.0 * 899.0).round() as i32, ((10.0 - p.1) / 20.0 * 599.0).round() as i32)
    }

    /// The lowest and highest row drawn in each column by consecutive points (the segments'
    /// ends), per column.
    fn column_extremes(points: &[(f64, f64)]) -> std::collections::BTreeMap<i32, (i32, i32)> {
        let mut m = std::collections::BTreeMap::new();
        for p in points {
            let (c, r) = pixel(p);
            let e = m.entry(c).or_insert((r, r));
            e.0 = e.0.min(r);
            e.1 = e.1.max(r);
        }
        m
    }

    /// 200 000 samples of a noisy slow wave with one single-sample spike up and one down:
    /// the drawn line keeps both spikes, each column's lowest and highest point, the first and
    /// the last point, and at most four points a column.
    #[test]
    fn a_decimated_line_keeps_every_extreme_and_a_one_sample_spike() {
        let n = 200_000;
        let series: Vec<(f64, f64)> = (0..n)
            .map(|i| {
                let t = i as f64 * 1000.0 / (n - 1) as f64;
                let noise = ((i * 7919) % 101) as f64 / 100.0 - 0.5;
                let spike = match i {
                    123_457 => 9.0,
                    54_321 => -9.5,
                    _ => 0.0,
                };
                (t, 3.0 * (t / 150.0).sin() + 0.3 * noise + spike)
            })
            .collect();
        let kept = line_points(series.iter().cloned(), pixel);
        assert!(kept.len() <= 4 * 900, "{} points kept of {n}", kept.len());
        assert!(kept.len() >= 2 * 900, "{} points kept: each column's lowest and highest are two", kept.len());
        assert!(kept.contains(&series[123_457]), "the spike up was dropped");
        assert!(kept.contains(&series[54_321]), "the spike down was dropped");
        assert_eq!(kept.first(), series.first());
        assert_eq!(kept.last(), series.last());
        assert_eq!(column_extremes(&kept), column_extremes(&series), "a column's extremes differ");
        // In time order, as drawn.
        assert!(kept.windows(2).all(|w| w[0].0 < w[1].0), "the kept points are out of order");
    }

    /// A load–deflection curve goes back in `x` (an unloading, a crack's jump): runs are cut
    /// where the column changes, so a column visited twice keeps both visits' extremes and
    /// the path between them.
    #[test]
    fn a_curve_that_comes_back_to_a_column_keeps_both_passes() {
        let mut pts: Vec<(f64, f64)> = (0..=1000).map(|i| (i as f64 * 0.5, 5.0)).collect();
        pts.extend((0..=1000).rev().map(|i| (i as f64 * 0.5, -5.0)));
        pts.push((250.0, 9.0));
        let kept = line_points(pts.iter().cloned(), pixel);
        assert_eq!(column_extremes(&kept), column_extremes(&pts));
        assert!(kept.contains(&(500.0, 5.0)) && kept.contains(&(500.0, -5.0)), "the turn is lost");
        assert_eq!(kept.last(), Some(&(250.0, 9.0)));
        // The way back starts after the way out ends: no point of the way back comes first.
        let back = kept.iter().position(|p| p.1 == -5.0).unwrap();
        assert!(kept[..back].iter().all(|p| p.1 == 5.0));
    }

    /// A scatter keeps one point per pixel (the first) and every pixel any point falls in.
    #[test]
    fn a_decimated_scatter_keeps_every_pixel_once() {
        let pts: Vec<(f64, f64)> = (0..100_000).map(|i| ((i % 1000) as f64, ((i * 31) % 17) as f64 - 8.0)).collect();
        let kept = scatter_points(pts.iter().cloned(), pixel);
        let all: HashSet<Pixel> = pts.iter().map(pixel).collect();
        let drawn: HashSet<Pixel> = kept.iter().map(pixel).collect();
        assert_eq!(drawn, all);
        assert_eq!(kept.len(), all.len(), "a pixel drawn twice");
        let nan = scatter_points([(f64::NAN, 1.0), (1.0, 1.0)], pixel);
        assert_eq!(nan, vec![(1.0, 1.0)]);
    }
}
