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

    /// Decimals that show σ with two significant digits (the GUM's rounding; value and σ
    /// alike); without a σ, four significant digits of the value.
    pub fn decimals(&self) -> usize {
        let s = self.sigma.abs();
        if s > 0.0 && s.is_finite() {
            (1 - s.log10().floor() as i64).clamp(0, 12) as usize
        } else {
            let v = self.value.abs();
            if v > 0.0 && v.is_finite() {
                (3 - v.log10().floor() as i64).clamp(0, 12) as usize
            } else {
                1
            }
        }
    }

    /// Value and σ rounded to two significant digits of σ.
    pub fn rounded(&self) -> Quantity {
        let d = self.decimals() as i32;
        let k = 10f64.powi(d);
        let v = (self.value * k).round() / k;
        let s = (self.sigma * k).round() / k;
        Quantity { value: if v == 0.0 { 0.0 } else { v }, sigma: s, unit: self.unit.clone() }
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
