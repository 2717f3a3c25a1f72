//! The statistics of a series as the standards use them: mean, standard deviation and
//! coefficient of variation over the valid specimens; EN 14651's characteristic values
//! (5 % fractile, EN 1990 Annex D) and the fib Model Code 2010 class of the material.

use crate::report::Report;

/// Statistics of one quantity over the specimens used.
#[derive(Debug, Clone, PartialEq)]
pub struct Stat {
    /// `report.json` key.
    pub key: &'static str,
    /// Unit.
    pub unit: String,
    /// Specimens with a value.
    pub n: usize,
    /// Mean.
    pub mean: f64,
    /// Sample standard deviation (n − 1).
    pub sd: f64,
    /// Coefficient of variation, %.
    pub cov_pct: f64,
}

/// The statistics per quantity of `reports` (the specimens used), the quantities and their
/// order `order`'s (the series' first report: its method's results), each with its `n` — 0
/// and no mean when no specimen is used.
pub fn stats(order: Option<&Report>, reports: &[&Report]) -> Vec<Stat> {
    let Some(first) = order else { return Vec::new() };
    first
        .entries
        .iter()
        .map(|e| {
            let vals: Vec<f64> = reports
                .iter()
                .filter_map(|r| r.entries.iter().find(|x| x.key == e.key).and_then(|x| x.result.as_ref().ok()).map(|q| q.value))
                .collect();
            let (mean, sd) = mean_sd(&vals);
            let unit = reports
                .iter()
                .filter_map(|r| r.entries.iter().find(|x| x.key == e.key).and_then(|x| x.result.as_ref().ok()))
                .chain(e.result.as_ref().ok())
                .map(|q| q.unit.clone())
                .next()
                .unwrap_or_default();
            Stat { key: e.key, unit, n: vals.len(), mean, sd, cov_pct: 100.0 * sd / mean.abs() }
        })
        .collect()
}

/// Mean and sample standard deviation (NaN when there are too few values).
pub fn mean_sd(v: &[f64]) -> (f64, f64) {
    let n = v.len();
    let mean = if n > 0 { v.iter().sum::<f64>() / n as f64 } else { f64::NAN };
    let sd = if n > 1 { (v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1) as f64).sqrt() } else { f64::NAN };
    (mean, sd)
}

/// EN 1990:2002 Annex D, Table D1: k_n for the 5 % characteristic value, V_X unknown, by n.
pub const KN_TABLE_D1: [(usize, f64); 9] =
    [(3, 3.37), (4, 2.63), (5, 2.33), (6, 2.18), (8, 2.00), (10, 1.92), (20, 1.76), (30, 1.73), (usize::MAX, 1.64)];

/// k_n of EN 1990 Annex D, Table D1 (5 % fractile, variance unknown) for `n` specimens: the
/// table's value at `n`, between its columns the value of the next smaller n tabulated (the
/// larger, safe-side factor); `None` below 3 (the table gives none).
pub fn k_n(n: usize) -> Option<f64> {
    KN_TABLE_D1.iter().rev().find(|(m, _)| *m <= n).map(|(_, k)| *k)
}

/// A characteristic value f_k = f_m − k_n·s (EN 1990 Annex D, D7.2, Eq. D.1 with V_X unknown).
#[derive(Debug, Clone, PartialEq)]
pub struct Characteristic {
    /// The key of the mean it comes from (`fR1`, ...).
    pub key: &'static str,
    /// Specimens used.
    pub n: usize,
    /// k_n, when n ≥ 3.
    pub k_n: Option<f64>,
    /// The value, MPa; `None` (not determined) when n < 3.
    pub value: Option<f64>,
}

/// The characteristic values of the statistics of `keys`.
pub fn characteristic(stats: &[Stat], keys: &[&'static str]) -> Vec<Characteristic> {
    keys.iter()
        .filter_map(|k| stats.iter().find(|s| s.key == *k))
        .map(|s| {
            let k = k_n(s.n);
            Characteristic { key: s.key, n: s.n, k_n: k, value: k.filter(|_| s.sd.is_finite()).map(|k| s.mean - k * s.sd) }
        })
        .collect()
}

/// The strength classes of fib Model Code 2010 §5.6.3 (f_R1k, MPa).
pub const FIB_STRENGTHS_MPA: [f64; 10] = [1.0, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0];

/// The fib Model Code 2010 class (§5.6.3) of a fibre concrete from its characteristic
/// residual strengths: the strength class is the largest of [`FIB_STRENGTHS_MPA`] not above
/// f_R1k, the letter from f_R3k/f_R1k: a 0.5–0.7, b 0.7–0.9, c 0.9–1.1, d 1.1–1.3, e ≥ 1.3
/// (each interval closed below). `None` when f_R1k < 1.0 MPa or the ratio is below 0.5.
pub fn fib_class(fr1k: f64, fr3k: f64) -> Option<String> {
    let strength = FIB_STRENGTHS_MPA.iter().rev().find(|s| **s <= fr1k)?;
    let ratio = fr3k / fr1k;
    let letter = [(1.3, 'e'), (1.1, 'd'), (0.9, 'c'), (0.7, 'b'), (0.5, 'a')].iter().find(|(lo, _)| ratio >= *lo)?.1;
    Some(format!("{strength}{letter}"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn k_n_is_en_1990_table_d1_for_an_unknown_variance() {
        assert_eq!(k_n(2), None);
        assert_eq!(k_n(3), Some(3.37));
        assert_eq!(k_n(4), Some(2.63));
        assert_eq!(k_n(6), Some(2.18));
        assert_eq!(k_n(7), Some(2.18), "between columns: the smaller n's, larger factor");
        assert_eq!(k_n(1000), Some(1.73));
    }

    #[test]
    fn the_fib_class_at_its_boundaries() {
        assert_eq!(fib_class(2.0, 1.8).as_deref(), Some("2c"), "f_R1k on a class value, ratio 0.9 is c");
        assert_eq!(fib_class(1.99, 1.8).as_deref(), Some("1.5c"), "just below 2.0: class 1.5 (ratio 0.905: c)");
        assert_eq!(fib_class(2.0, 1.79).as_deref(), Some("2b"), "ratio 0.895: b");
        assert_eq!(fib_class(4.5, 4.5 * 0.69).as_deref(), Some("4a"));
        assert_eq!(fib_class(4.5, 4.5 * 1.3).as_deref(), Some("4e"));
        assert_eq!(fib_class(0.9, 0.9), None, "below the lowest class");
        assert_eq!(fib_class(3.0, 1.2), None, "ratio 0.4 below a");
    }

    #[test]
    fn characteristic_values_in_closed_form() {
        let s = |n, mean, sd| Stat { key: "fR1", unit: "MPa".into(), n, mean, sd, cov_pct: 0.0 };
        let c = characteristic(&[s(3, 4.0, 0.5)], &["fR1"]);
        assert_eq!(c[0].value, Some(4.0 - 3.37 * 0.5));
        let c = characteristic(&[s(2, 4.0, 0.5)], &["fR1"]);
        assert_eq!(c[0].value, None, "n < 3: not determined");
    }
}
