//! What a report holds: the standard's entries, the curves, the QC, the inputs; and what it
//! needs of the rig.

use std::path::PathBuf;

use tagdeflect_core::gauge::GaugeConfig;
use tagdeflect_core::rig::{SpecimenConfig, TagRole, WorldConfig};

use crate::config::{BeamConfig, LabInfo, ReportConfig};
use crate::curve::Curve;
use crate::quantity::Quantity;
use crate::standard::Standard;
use crate::{qc, validity};

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

/// What the report needs of the rig: the world's up direction (deflection is along it) and
/// the specimen — its tags' roles and `[specimen.beam]`.
#[derive(Debug, Clone, PartialEq)]
pub struct TestRig {
    /// `[world]`.
    pub world: WorldConfig,
    /// `[specimen]`.
    pub specimen: SpecimenConfig,
    /// `[[gauge]]`.
    pub gauges: Vec<GaugeConfig>,
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
    /// How far the UTM's samples were shifted onto the cameras' clock (the feed's
    /// `clock_offset_ms`, UTM − camera, ns): `curve`'s times are the samples' minus this. 0
    /// without a UTM stream (the feed's loads are the UTM's at each line's time, unshifted) or
    /// without a clock check. The daemon stamps the UTM's samples and the test's events alike,
    /// so an event at `t_ns` lies on `curve` at `t_ns − utm_shift_ns` (docs/report.md, "The
    /// marks' loads").
    pub utm_shift_ns: i64,
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
    /// The test's record when the feed is a test folder's (`test.json`: events, notes,
    /// method, specimen row, crack entry).
    pub test: Option<tagdeflect_core::lab_test::TestRecord>,
    /// The test's control outputs (`control.json` of a test run under control; `Err`: the
    /// file could not be read), printed as the "Control output" section.
    pub control: Option<Result<tagdeflect_core::control_summary::ControlSummary, String>>,
    /// Where each dimension came from (`test.json` or `config`; empty outside a test folder).
    pub dimension_sources: crate::test_folder::DimensionSources,
}
