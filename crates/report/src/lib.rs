//! The test report (SPEC "Report"): standard quantities of a flexural test from a feed,
//! with their uncertainties, a QC section, the curve as CSV and plots.
//!
//! `tagdeflect report FEED --config FILE --standard astm-c1609|astm-c1856|en-14651 --out DIR`
//! writes `report.html` (self-contained, plots inline as SVG), `report.json`, `curve.csv`
//! and every plot as PNG and SVG; `tagdeflect export FEED --csv OUT` writes the CSV alone.
//! With `[report]` in the config, `run` writes a report of the run at its end.
//!
//! The steps: [`Feed`] reads the feed (`feed_reader`); [`build`] picks the curve and computes
//! the report (`build`): [`Curve`] holds load against net deflection (ASTM) or CMOD (EN) in
//! time order with σ and does the numerics (smoothing, crossings, area, first peak);
//! [`c1609`] and [`en14651`] compute each standard's quantities; [`qc`] summarises the feed's
//! health; [`write`] writes the outputs (`output`: `report.json`, with [`csv_out`], `plots`
//! and `html`).
//!
//! This file holds the types the steps share: [`Standard`], [`Quantity`], [`Entry`],
//! [`TestRig`], [`Report`] and [`ReportError`].

mod build;
pub mod c1609;
pub mod config;
pub mod csv_out;
mod curve;
pub mod en14651;
mod feed_reader;
mod html;
mod output;
mod plots;
pub mod qc;
pub mod series;
mod utm_stream;
pub mod validity;
pub mod verify;

pub use build::{build, choose_cmod_gauge};
pub use config::{BeamConfig, LabInfo, ReportConfig, Response};
pub use curve::{Curve, CurveError};
pub use feed_reader::{Feed, Limits, ReadOptions};
pub use output::{write, write_atomic};
pub use utm_stream::UtmStream;

use serde::{Deserialize, Serialize};
use std::path::PathBuf;

use tagdeflect_core::rig::TagRole;
use tagdeflect_core::rig::{SpecimenConfig, WorldConfig};

/// The standard a report follows.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
pub enum Standard {
    /// ASTM C1609/C1609M: fibre-reinforced concrete, third-point loading, net deflection.
    #[serde(rename = "astm-c1609")]
    #[cfg_attr(feature = "clap", value(name = "astm-c1609"))]
    AstmC1609,
    /// ASTM C1856/C1856M (UHPC): the flexural test of C1609 on the specimens C1856 calls
    /// for; the quantities are C1609's, the geometry is taken from the config.
    #[serde(rename = "astm-c1856")]
    #[cfg_attr(feature = "clap", value(name = "astm-c1856"))]
    AstmC1856,
    /// EN 14651: notched beam, three-point loading, CMOD.
    #[serde(rename = "en-14651")]
    #[cfg_attr(feature = "clap", value(name = "en-14651"))]
    En14651,
}

impl Standard {
    /// The name as on the command line and in `report.json`.
    pub fn id(self) -> &'static str {
        match self {
            Standard::AstmC1609 => "astm-c1609",
            Standard::AstmC1856 => "astm-c1856",
            Standard::En14651 => "en-14651",
        }
    }

    /// The standard's title.
    pub fn title(self) -> &'static str {
        match self {
            Standard::AstmC1609 => {
                "ASTM C1609/C1609M — Flexural Performance of Fiber-Reinforced Concrete (Using Beam With Third-Point Loading)"
            }
            Standard::AstmC1856 => {
                "ASTM C1856/C1856M — Fabricating and Testing Specimens of Ultra-High Performance Concrete (flexure per ASTM C1609)"
            }
            Standard::En14651 => {
                "EN 14651 — Test method for metallic fibre concrete: flexural tensile strength (limit of proportionality, residual)"
            }
        }
    }
}

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

/// One line of a standard's results.
#[derive(Debug, Clone, PartialEq)]
pub struct Entry {
    /// The `report.json` key (SPEC).
    pub key: &'static str,
    /// Symbol as the standard writes it (HTML).
    pub symbol: &'static str,
    /// What it is, in words.
    pub name: &'static str,
    /// The value, or why it could not be determined.
    pub result: Result<Quantity, String>,
    /// How it is determined (formula, method), in words.
    pub method: String,
    /// The clause of the standard the definition follows.
    pub clause: &'static str,
}

/// Errors of the report.
#[derive(Debug, thiserror::Error)]
pub enum ReportError {
    /// A feed (or UTM) line that cannot be read.
    #[error("{}:{line}: {message}", path.display())]
    BadLine {
        /// The feed file.
        path: PathBuf,
        /// 1-based line.
        line: usize,
        /// What is wrong.
        message: String,
    },
    /// A file that cannot be read or written.
    #[error("{}: {message}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// What failed.
        message: String,
    },
    /// The feed lacks what the standard needs.
    #[error("{}: {message}", path.display())]
    Data {
        /// The feed file.
        path: PathBuf,
        /// What is missing.
        message: String,
    },
    /// The config lacks what the report needs.
    #[error("{}: {message}", path.display())]
    Config {
        /// The config file.
        path: PathBuf,
        /// What is missing.
        message: String,
    },
    /// Drawing a plot failed.
    #[error("plot {name}: {message}")]
    Plot {
        /// The plot.
        name: String,
        /// What failed.
        message: String,
    },
}

/// What the report needs of the rig: the world's up direction (deflection is along it) and
/// the specimen — its tags' roles and `[specimen.beam]`.
#[derive(Debug, Clone, PartialEq)]
pub struct TestRig {
    /// `[world]`.
    pub world: WorldConfig,
    /// `[specimen]`.
    pub specimen: SpecimenConfig,
    /// `[[gauge]]`.
    pub gauges: Vec<tagdeflect_estimate::gauges::GaugeConfig>,
}

impl TestRig {
    /// Role of a specimen tag.
    pub(crate) fn role_of(&self, id: u32) -> Option<TagRole> {
        self.specimen.role_of(id)
    }
}

/// A computed report.
#[derive(Debug, Clone)]
pub struct Report {
    /// The standard.
    pub standard: Standard,
    /// The specimen's geometry (from the config).
    pub beam: BeamConfig,
    /// The standard's quantities in the standard's order.
    pub entries: Vec<Entry>,
    /// The curve the quantities come from (on the UTM's samples when there is a UTM stream).
    pub curve: Curve,
    /// The curve at the frame rate, as the feed gives it.
    pub feed_curve: Curve,
    /// Where the loads come from, in words.
    pub load_source: String,
    /// Is the feed a complete test of the standard.
    pub validity: validity::Validity,
    /// What identifies the test.
    pub lab: LabInfo,
    /// The UTM stream read, when one was.
    pub utm_path: Option<PathBuf>,
    /// Every input besides the feed and the UTM stream (config, calibration files): `(role, path)`.
    pub inputs: Vec<(String, PathBuf)>,
    /// What the curve's `x` is (e.g. `net deflection` or `CMOD (gauge cmod)`).
    pub x_name: String,
    /// Short name of `x` for axis labels and the CSV (e.g. `net deflection`).
    pub x_axis: String,
    /// Where `x` and its σ come from, in words.
    pub x_source: String,
    /// The QC section.
    pub qc: qc::Qc,
    /// Notes on the specimen and the standard (geometry, unchecked clauses).
    pub notes: Vec<String>,
    /// Where `beam` comes from (`report.json` `specimen.source`).
    pub beam_source: String,
    /// Where the feed was read.
    pub feed_path: PathBuf,
    /// `(index from 1, runs)` when the feed file held several runs.
    pub run: Option<(usize, usize)>,
    /// Report options used.
    pub options: ReportConfig,
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
