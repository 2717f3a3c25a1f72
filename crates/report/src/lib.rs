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
//! The types the steps share: [`Standard`] (`standard`), [`Quantity`] (`quantity`), [`Entry`],
//! [`TestRig`] and [`Report`] (`report`), [`ReportError`] (`error`).

mod build;
pub mod c1609;
pub mod config;
mod control_section;
pub mod csv_out;
mod curve;
pub mod en14651;
mod error;
mod event_loads;
pub mod feed_columns;
mod feed_reader;
pub mod feed_summary;
mod html;
mod load_spikes;
mod lop;
pub mod method_statement;
mod output;
mod plot_points;
mod plots;
pub mod qc;
mod quantity;
mod report;
pub mod series;
pub mod series_stats;
mod standard;
mod tag_stats;
pub mod test_folder;
mod utm_stream;
pub mod validity;
pub mod verify;

pub use build::{build, choose_cmod_gauge, CurveChoiceError};
pub use config::{BeamConfig, LabInfo, ReportConfig, Response};
pub use curve::{Curve, CurveError};
pub use error::ReportError;
pub use feed_reader::{Feed, Limits, ReadOptions};
pub use output::{print_pdf, sha256_file, sha256_prefix, write, write_atomic, PdfError};
pub use quantity::Quantity;
pub use report::{Entry, Report, TestRig};
pub use standard::Standard;
pub use utm_stream::UtmStream;
