//! Time series read from a feed, and the small statistics the figures use.

use tagdeflect_core::feed::FeedLine;

/// A time series: times (s from the feed's first line) and values (mm).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Series {
    /// Times, s.
    pub t_s: Vec<f64>,
    /// Values, mm.
    pub value_mm: Vec<f64>,
}

impl Series {
    /// The series of `value(line)` over the lines that have it; times from `t0_ns`.
    pub fn from_feed(lines: &[&FeedLine], t0_ns: i64, value: impl Fn(&FeedLine) -> Option<f64>) -> Series {
        let mut s = Series::default();
        for l in lines {
            if let Some(v) = value(l).filter(|v| v.is_finite()) {
                s.t_s.push((l.t_ns - t0_ns) as f64 * 1e-9);
                s.value_mm.push(v);
            }
        }
        s
    }

    /// Number of samples.
    pub fn len(&self) -> usize {
        self.value_mm.len()
    }

    /// True when it has no samples.
    pub fn is_empty(&self) -> bool {
        self.value_mm.is_empty()
    }

    /// The median interval between samples, s (`None` with fewer than two).
    pub fn interval_s(&self) -> Option<f64> {
        let d: Vec<f64> = self.t_s.windows(2).map(|w| w[1] - w[0]).collect();
        tagdeflect_core::stats::median(&d)
    }
}

/// The downward displacement of a line's tags (mean over the tags solved), mm: `−disp · up`.
pub fn down_displacement(line: &FeedLine, up: [f64; 3]) -> Option<f64> {
    let v: Vec<f64> = line.tags.iter().map(|t| -dot(t.disp_mm, up)).collect();
    mean(&v)
}

/// The downward displacement of tag `id` in a line, mm.
pub fn tag_down_displacement(line: &FeedLine, id: u32, up: [f64; 3]) -> Option<f64> {
    line.tags.iter().find(|t| t.id == id).map(|t| -dot(t.disp_mm, up))
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// Mean, `None` when empty.
pub fn mean(v: &[f64]) -> Option<f64> {
    (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
}

/// Sample standard deviation (n − 1), `None` with fewer than two values.
pub fn sd(v: &[f64]) -> Option<f64> {
    let m = mean(v)?;
    (v.len() >= 2).then(|| (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (v.len() - 1) as f64).sqrt())
}

/// Least-squares line `y = a + b x`: `(a, b)`; `None` with fewer than two distinct x.
pub fn line_fit(x: &[f64], y: &[f64]) -> Option<(f64, f64)> {
    let (mx, my) = (mean(x)?, mean(y)?);
    let sxx: f64 = x.iter().map(|v| (v - mx).powi(2)).sum();
    if sxx <= 0.0 {
        return None;
    }
    let sxy: f64 = x.iter().zip(y).map(|(a, b)| (a - mx) * (b - my)).sum();
    let b = sxy / sxx;
    Some((my - b * mx, b))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn statistics_by_hand() {
        assert_eq!(mean(&[1.0, 2.0, 3.0]), Some(2.0));
        assert_eq!(sd(&[1.0, 3.0]), Some(2f64.sqrt()));
        assert_eq!(sd(&[1.0]), None);
        let (a, b) = line_fit(&[0.0, 1.0, 2.0], &[1.0, 3.0, 5.0]).unwrap();
        assert!((a - 1.0).abs() < 1e-12 && (b - 2.0).abs() < 1e-12);
        let s = Series { t_s: vec![0.0, 0.1, 0.2, 0.4], value_mm: vec![0.0; 4] };
        assert!((s.interval_s().unwrap() - 0.1).abs() < 1e-12);
    }
}
