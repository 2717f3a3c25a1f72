//! A reported value with its uncertainty, rounded as the GUM says.

use serde::{Deserialize, Serialize};

/// A reported value with its 1-σ uncertainty (`{"value", "sigma", "unit"}` in `report.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Quantity {
    /// The value.
    pub value: f64,
    /// Its 1-σ uncertainty.
    pub sigma: f64,
    /// Its unit.
    pub unit: String,
}

impl Quantity {
    /// A value in `unit`.
    pub fn new(value: f64, sigma: f64, unit: &str) -> Self {
        Self { value, sigma, unit: unit.to_string() }
    }

    /// The power of ten of the last digit shown: that of σ's second significant digit (the
    /// GUM's rounding). σ is rounded there first, so a σ that carries into the next decade
    /// keeps two digits (0.0996 → 0.10, not 0.100; 99.7 → 100, shown to the tens). Without
    /// a σ, the fourth significant digit of the value (a zero value: tenths).
    fn last_digit_exp(&self) -> i32 {
        let s = self.sigma.abs();
        let e = if s > 0.0 && s.is_finite() {
            let e = s.log10().floor() as i32 - 1;
            if (s / 10f64.powi(e)).round() >= 100.0 {
                e + 1
            } else {
                e
            }
        } else {
            let v = self.value.abs();
            if v > 0.0 && v.is_finite() {
                v.log10().floor() as i32 - 3
            } else {
                -1
            }
        };
        e.clamp(-12, 300)
    }

    /// Decimals that show σ with two significant digits (the GUM's rounding; value and σ
    /// alike; 0 when σ's second digit is left of the point); without a σ, four significant
    /// digits of the value.
    pub fn decimals(&self) -> usize {
        (-self.last_digit_exp()).max(0) as usize
    }

    /// Value and σ rounded to two significant digits of σ (to tens, hundreds, … when σ is
    /// that large: 12345.6 ± 250 → 12350 ± 250).
    pub fn rounded(&self) -> Quantity {
        let e = self.last_digit_exp();
        let round = |x: f64| {
            if e < 0 {
                let k = 10f64.powi(-e);
                (x * k).round() / k
            } else {
                let k = 10f64.powi(e);
                (x / k).round() * k
            }
        };
        let v = round(self.value);
        Quantity { value: if v == 0.0 { 0.0 } else { v }, sigma: round(self.sigma), unit: self.unit.clone() }
    }

    /// `value ± σ unit` rounded as [`rounded`](Self::rounded).
    pub fn text(&self) -> String {
        let d = self.decimals();
        let r = self.rounded();
        format!("{:.d$} ± {:.d$} {}", r.value, r.sigma, r.unit)
    }
}

#[cfg(test)]
mod tests {
    use super::Quantity;

    /// `text()` and `rounded()` (what `report.json` holds) of `value ± sigma`.
    fn shown(value: f64, sigma: f64, unit: &str) -> (String, f64, f64) {
        let q = Quantity::new(value, sigma, unit);
        let r = q.rounded();
        (q.text(), r.value, r.sigma)
    }

    /// Two significant digits of σ, the value to the same decimal (GUM 7.2.6), on known
    /// inputs: the text exactly, and the JSON's numbers exactly those decimals.
    #[test]
    fn values_are_rounded_to_two_significant_digits_of_their_sigma() {
        // The f150: σ 0.000094 has its second digit at 1e-6.
        assert_eq!(shown(2.006889, 0.000094, "MPa"), ("2.006889 ± 0.000094 MPa".into(), 2.006889, 0.000094));
        // More digits than σ supports are dropped (half away from zero).
        assert_eq!(shown(2.00688949, 0.0000941, "MPa"), ("2.006889 ± 0.000094 MPa".into(), 2.006889, 0.000094));
        assert_eq!(shown(27.659_349, 0.000_912_3, "kN"), ("27.65935 ± 0.00091 kN".into(), 27.65935, 0.00091));
        assert_eq!(shown(61.45372, 0.05634, "%"), ("61.454 ± 0.056 %".into(), 61.454, 0.056));
        assert_eq!(shown(30.00004, 0.0481, "kN"), ("30.000 ± 0.048 kN".into(), 30.0, 0.048));
        assert_eq!(shown(51.0449, 0.27, "J"), ("51.04 ± 0.27 J".into(), 51.04, 0.27));
        assert_eq!(shown(51.0449, 1.234, "J"), ("51.0 ± 1.2 J".into(), 51.0, 1.2));
        assert_eq!(shown(0.29574, 0.00268, "mm"), ("0.2957 ± 0.0027 mm".into(), 0.2957, 0.0027));
        // A σ whose first digit is 1 keeps two digits too (0.0123 → 0.012, not 0.01).
        assert_eq!(shown(6.22712, 0.0123, "MPa"), ("6.227 ± 0.012 MPa".into(), 6.227, 0.012));
        // Negative values; a value that rounds to zero is 0, not -0.
        assert_eq!(shown(-0.01234, 0.0031, "mm"), ("-0.0123 ± 0.0031 mm".into(), -0.0123, 0.0031));
        let (t, v, _) = shown(-0.00004, 0.0031, "mm");
        assert_eq!(t, "0.0000 ± 0.0031 mm");
        assert!(v == 0.0 && v.is_sign_positive());
        // σ ≥ 10: no decimals; σ ≥ 100: the value to σ's second digit (tens).
        assert_eq!(shown(1234.56, 25.3, "kN"), ("1235 ± 25 kN".into(), 1235.0, 25.0));
        assert_eq!(shown(12345.6, 253.0, "J"), ("12350 ± 250 J".into(), 12350.0, 250.0));
        // Without σ: four significant digits of the value.
        assert_eq!(shown(12.34567, 0.0, "kN"), ("12.35 ± 0.00 kN".into(), 12.35, 0.0));
    }

    /// A σ that rounds up into the next decade keeps two significant digits: 0.0996 is shown
    /// as 0.10 (not 0.100, three digits), 9.96 as 10, 0.996 as 1.0.
    #[test]
    fn a_sigma_rounding_into_the_next_decade_keeps_two_digits() {
        assert_eq!(shown(3.24159, 0.0996, "mm"), ("3.24 ± 0.10 mm".into(), 3.24, 0.1));
        assert_eq!(shown(3.24159, 0.0994, "mm"), ("3.242 ± 0.099 mm".into(), 3.242, 0.099));
        assert_eq!(shown(40.2, 0.996, "kN"), ("40.2 ± 1.0 kN".into(), 40.2, 1.0));
        assert_eq!(shown(40.26, 9.96, "kN"), ("40 ± 10 kN".into(), 40.0, 10.0));
        for (v, s) in [(3.24159, 0.0996), (1.0, 0.00999), (250.0, 99.7), (7.5, 0.995), (7.5, 0.105), (7.5, 0.0949)] {
            let q = Quantity::new(v, s, "");
            let m = q.rounded().sigma / 10f64.powi(q.last_digit_exp());
            assert!((m - m.round()).abs() < 1e-6 && (10.0..=99.0).contains(&m.round()), "{v} ± {s}: σ shown as {}: {m}", q.text());
        }
    }
}
