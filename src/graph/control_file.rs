//! A test run under control carries it into its folder (docs/control.md "A test under
//! control"): at the stop, before the report and the folder's hashes, `control.json`
//! ([`tagdeflect_core::control_summary::ControlSummary`]) gets each control output's figures
//! for the test — the signal, its scaling, the share of frame sets with the valid line high,
//! the longest invalid stretch and its cause, the exposure → write latency measured live — and
//! the temporal estimate's dynamics computed with the run's `[measure]` at the frame rate the
//! test saw. The report prints them as its "Control output" section.

use std::path::Path;
use std::sync::Arc;

use tagdeflect_core::control_summary::{ControlSummary, CONTROL_FILE};
use tagdeflect_sinks::lab_test::{LabTests, TestRecord};
use tagdeflect_sinks::signal_log::TestSummaries;

use crate::config::Config;

/// Frame rate assumed for the dynamics when the test's own cannot be told, sets/s.
const DEFAULT_FPS: f64 = 30.0;

/// Installs the hook that writes `control.json` into each stopped test's folder (nothing
/// without control outputs).
pub fn install(tests: &Arc<LabTests>, config: &Config, outputs: Vec<TestSummaries>) {
    if outputs.is_empty() {
        return;
    }
    let temporal = config.measure.temporal();
    tests.set_folder_files(Box::new(move |folder: &Path, record: &TestRecord| {
        let Some(summary) = summary(&record.id, &outputs, &temporal, record) else { return Ok(()) };
        let text = serde_json::to_string_pretty(&summary)? + "\n";
        let path = folder.join(CONTROL_FILE);
        write_synced(&path, text.as_bytes()).map_err(|e| format!("{}: cannot write the test's control figures: {e}", path.display()))?;
        Ok(())
    }));
}

/// The test's control figures, when an output served it.
fn summary(
    id: &str,
    outputs: &[TestSummaries],
    temporal: &tagdeflect_estimate::temporal::TemporalConfig,
    record: &TestRecord,
) -> Option<ControlSummary> {
    let outputs: Vec<_> = outputs.iter().filter_map(|f| f(id)).collect();
    if outputs.is_empty() {
        return None;
    }
    let fps = frame_rate(record).unwrap_or(DEFAULT_FPS);
    let dynamics = tagdeflect_estimate::temporal_response::dynamics(temporal, fps);
    Some(ControlSummary { test: id.to_string(), outputs, dynamics: Some(dynamics) })
}

/// The test's frame sets per second: its lines over its time.
fn frame_rate(record: &TestRecord) -> Option<f64> {
    let stopped = record.stopped_t_ns?;
    let s = (stopped - record.started_t_ns) as f64 * 1e-9;
    let fps = (record.lines.saturating_sub(1)) as f64 / s;
    (s > 0.0 && fps.is_finite() && fps >= 1.0).then_some(fps.min(240.0))
}

/// Writes `path` and syncs it (the folder is synced with `test.json`, written after it).
fn write_synced(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    use std::io::Write;
    let mut f = std::fs::File::create(path)?;
    f.write_all(bytes)?;
    f.sync_all()
}
