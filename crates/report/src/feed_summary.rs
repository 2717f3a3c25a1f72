//! What a feed's lines say that the report needs only in sum, folded in as each line is read:
//! the cameras' health per line (counted per camera), each gauge's unit (kept once per
//! gauge), the tags seen, the largest `dropped_sets`, the last clock check and whether the
//! lines belong to a test. The numbers the report computes with per line are held as columns
//! ([`crate::feed_columns`]); a line of a three-camera, 9-tag, 4-gauge rig held for the report
//! takes ~100 B against 3.8 kB as parsed (the `report_memory` test of this crate;
//! docs/performance.md).

use std::collections::BTreeMap;

use serde::Serialize;
use tagdeflect_core::feed::FeedLine;

/// One camera's health counted over a feed's lines.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct CameraTally {
    /// Lines that flag the camera bumped.
    pub bumps: usize,
    /// Lines without a frame from it.
    pub lines_without_frame: usize,
    /// Lines where it had no pose.
    pub lines_unposed: usize,
}

/// What the report keeps of a feed's lines in sum (see the module doc).
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct LineSummary {
    /// Per camera (by name), its health over the lines.
    pub cameras: BTreeMap<String, CameraTally>,
    /// Per field `camera.NAME.drift_deg`, `.drift_mm`, `.stale_pose`: the lines where it is
    /// non-zero (present, for the flag) and its largest |value|.
    pub camera_fields: BTreeMap<String, (usize, Option<f64>)>,
    /// Per gauge, the unit of its first reading that names one.
    pub gauge_units: BTreeMap<String, String>,
    /// Per specimen tag seen, the lines that solved it.
    pub tag_lines: BTreeMap<u32, usize>,
    /// The largest `dropped_sets` of the lines.
    pub dropped_sets: Option<u64>,
    /// The clock check of the last line that carries one.
    pub clock_offset_ms: Option<tagdeflect_core::feed::ValueSigma>,
    /// True when a line belongs to a test (`test`).
    pub any_test: bool,
}

impl LineSummary {
    /// Counts `l`'s cameras and notes its gauges' units, tags, dropped sets, clock check and
    /// test, then drops from `l` what is kept here: its cameras, and every unit equal to its
    /// gauge's first.
    pub(crate) fn fold(&mut self, l: &mut FeedLine) {
        for t in &l.tags {
            *self.tag_lines.entry(t.id).or_default() += 1;
        }
        self.dropped_sets = self.dropped_sets.max(l.dropped_sets);
        if l.clock_offset_ms.is_some() {
            self.clock_offset_ms = l.clock_offset_ms;
        }
        self.any_test |= l.test.is_some();
        for c in &l.cameras {
            let e = self.cameras.entry(c.name.clone()).or_default();
            e.bumps += c.bumped as usize;
            e.lines_without_frame += (!c.frame) as usize;
            e.lines_unposed += (!c.posed) as usize;
            let field = |k: &str| format!("camera.{}.{k}", c.name);
            for (k, v) in [("drift_deg", c.drift_deg), ("drift_mm", c.drift_mm)] {
                if let Some(x) = v {
                    let e = self.camera_fields.entry(field(k)).or_insert((0, None));
                    e.0 += (x != 0.0) as usize;
                    e.1 = Some(e.1.unwrap_or(0.0).max(x.abs()));
                }
            }
            if c.stale_pose {
                self.camera_fields.entry(field("stale_pose")).or_insert((0, None)).0 += 1;
            }
        }
        l.cameras = Vec::new();
        for (name, g) in l.gauges.iter_mut() {
            if g.unit.is_empty() {
                continue;
            }
            if !self.gauge_units.contains_key(name) {
                self.gauge_units.insert(name.clone(), g.unit.clone());
            }
            if self.gauge_units[name] == g.unit {
                g.unit = String::new();
            }
        }
    }
}
