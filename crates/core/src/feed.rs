//! The deflection feed (SPEC "Deflection feed"): one JSON line per solved frame set.
//!
//! Extensions beyond SPEC (all optional for readers): per tag `sigma_mm`, `disp_sigma_mm`
//! and `reproj_px`; per line `reproj_px` (RMS over all specimen corners), `cameras` (per-camera health),
//! `utm` ("ok" / "down" when a UTM is configured), `dropped_sets` (frame sets dropped by
//! the live pipeline so far), `latency_ms` (frame capture → line written, live only),
//! `mqtt_dropped` (lines dropped by the MQTT publisher's buffer so far, with `[output.mqtt]`),
//! `recording` / `recorder_dropped` (recorder state and frames it dropped, live runs that
//! record); per camera `drift_deg` / `drift_mm` (estimated slow drift since the pose was
//! fixed), `stale_pose` / `pose_age_sets` (pose held unchecked) and `dropped_frames` (live).
//!
//! **Read tolerantly.** The same types read a feed back (the report, the archive): unknown
//! fields are ignored, every extension may be absent, and so may what a feed written
//! by another version or by hand may leave out — a line's `tags` (none solved), a tag's
//! `views` (0), a camera's `frame` and `posed` (`true`) and its tag counts (0), a gauge's
//! `sigma` (unknown: NaN, see [`GaugeReading::known_sigma`]) and `unit` (empty).

use serde::{Deserialize, Serialize};

/// One solved specimen tag in a feed line.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FeedTag {
    /// Specimen tag id.
    pub id: u32,
    /// Centre of the black square, world frame, mm.
    pub pos_mm: [f64; 3],
    /// `pos_mm` minus the tag's position in the first frame set that solved it.
    pub disp_mm: [f64; 3],
    /// Cameras that saw it (and were used); 0 when a feed does not say.
    #[serde(default)]
    pub views: usize,
    /// 1-σ uncertainty of `pos_mm` along world x, y, z.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sigma_mm: Option<[f64; 3]>,
    /// 1-σ uncertainty of `disp_mm` along world x, y, z: without what the tag's zero and
    /// this set share (the held camera poses' errors, the corners' bias that stays;
    /// docs/accuracy.md, "The displacement's σ").
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub disp_sigma_mm: Option<[f64; 3]>,
    /// RMS reprojection error of the tag's corners, px.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reproj_px: Option<f64>,
}

/// Health of one camera in one frame set.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct CameraHealth {
    /// Camera name.
    pub name: String,
    /// True when the camera contributed a frame to this set (read as `true` when absent).
    #[serde(default = "yes")]
    pub frame: bool,
    /// Background tags seen.
    #[serde(default)]
    pub background_tags: usize,
    /// Specimen tags seen.
    #[serde(default)]
    pub specimen_tags: usize,
    /// RMS reprojection error of the background corners with the pose in use, px.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pose_reproj_px: Option<f64>,
    /// The camera has a pose (from background tags or the config; read as `true` when absent).
    #[serde(default = "yes")]
    pub posed: bool,
    /// The camera was found moved (bumped) and re-posed in this frame set.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub bumped: bool,
    /// Estimated slow drift of the camera since its pose was last fixed (first posing or
    /// re-posing after a bump): rotation, degrees (see `solve::drift`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub drift_deg: Option<f64>,
    /// Estimated shift of the camera centre since its pose was last fixed, mm.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub drift_mm: Option<f64>,
    /// The pose in use was not checked against background tags in this frame set (too few
    /// seen): it is held from an earlier set.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub stale_pose: bool,
    /// Frame sets since the pose was last checked against background tags (with `stale_pose`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pose_age_sets: Option<u64>,
    /// This camera's frames dropped so far in a live run (capture queue full, incomplete
    /// buffers, arrived too late for their frame set).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dropped_frames: Option<u64>,
    /// How late this camera's frames steadily arrive in a live run (arrival on the process
    /// clock minus `t_ns`, the 90th percentile of its last 32 frames), ms: what a frame set
    /// learns to wait for it. Absent while learned and once the camera has gone silent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub arrival_delay_ms: Option<f64>,
}

/// One line of the feed.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct FeedLine {
    /// Frame-set number from 0.
    pub seq: u64,
    /// The frame set's time (mean of its frames), ns since the Unix epoch.
    pub t_ns: i64,
    /// UTM load interpolated at `t_ns`, kN.
    #[serde(rename = "load_kN", default, skip_serializing_if = "Option::is_none")]
    pub load_kn: Option<f64>,
    /// UTM stroke interpolated at `t_ns`, mm.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stroke_mm: Option<f64>,
    /// The specimen tags solved in this frame set (none when absent).
    #[serde(default)]
    pub tags: Vec<FeedTag>,
    /// Mean downward displacement of midspan tags minus that of support tags, mm.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub net_deflection_mm: Option<f64>,
    /// 1-σ uncertainty of `net_deflection_mm`, mm (present with it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub net_deflection_sigma_mm: Option<f64>,
    /// (extension) Rate of `net_deflection_mm`, mm/min (from the temporal estimate).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub net_deflection_rate_mm_per_min: Option<f64>,
    /// (extension) The frame set lacked a camera's frame, or saw a tag with fewer cameras
    /// than usual: its values lean on the temporal estimate's state (or, solved per set,
    /// are less certain).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub partial_set: bool,
    /// The line was smoothed with the frame sets after it (`replay --smooth`: a fixed-lag
    /// Rauch–Tung–Striebel smoother over the temporal estimate); absent in a live feed.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub smoothed: bool,
    /// RMS reprojection error over all solved specimen tags, px.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reproj_px: Option<f64>,
    /// Per-camera health.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub cameras: Vec<CameraHealth>,
    /// UTM link state when a UTM is configured: "ok" or "down".
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub utm: Option<String>,
    /// Frame sets dropped by the live pipeline so far (back-pressure).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dropped_sets: Option<u64>,
    /// Capture → feed latency of this set, ms (live only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub latency_ms: Option<f64>,
    /// Virtual gauges (`[[gauge]]`) whose tags were solved in this frame set, by name
    /// (a `distance` gauge adds `<name>.strain`); see `solve::gauges`.
    #[serde(default, skip_serializing_if = "std::collections::BTreeMap::is_empty")]
    pub gauges: std::collections::BTreeMap<String, GaugeReading>,
    /// Estimated offset of the UTM clock against the cameras' (UTM time − camera time for
    /// one instant), ms; every few lines once determined (see `solve::clock_offset`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub clock_offset_ms: Option<ValueSigma>,
    /// Feed lines dropped so far by the MQTT publisher's buffer (broker unreachable too
    /// long); present when `[output.mqtt]` is configured.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mqtt_dropped: Option<u64>,
    /// State of the recorder when the live run records: "ok", "failing" (write errors,
    /// retried) or "off" (stopped).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub recording: Option<String>,
    /// Frames the recorder did not record so far (queue full or writes failing).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub recorder_dropped: Option<u64>,
    /// The test running when the set was solved (SPEC "Tests"); its displacements and gauges
    /// then count from the test's zero.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub test: Option<TestRef>,
    /// What happened since the previous line (a test started, stopped, marked or zeroed).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub events: Vec<FeedEvent>,
}

/// The test a feed line belongs to.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct TestRef {
    /// The test's id (its folder's name).
    pub id: String,
    /// The specimen's id.
    pub specimen: String,
    /// True while the test's zero is still being taken (its first frame sets): the values
    /// count from the mean of the sets so far.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub zeroing: bool,
}

/// An event of a test: `start`, `stop`, `mark` or `zero`, with its time and an optional note.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct FeedEvent {
    /// `start`, `stop`, `mark`, `zero`, `resume`, `crack` or `preload`.
    pub kind: String,
    /// When it happened, ns since the Unix epoch.
    pub t_ns: i64,
    /// The operator's note (a mark's text), if any.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub note: Option<String>,
    /// Who did it (a user of `[output] users_file`, `shared-token`, or absent: the daemon
    /// itself, or a test written before users existed).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub user: Option<String>,
}

/// One gauge's reading in a feed line.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GaugeReading {
    /// The value.
    pub value: f64,
    /// Its 1-σ uncertainty, propagated from the tags' covariance; NaN when a feed read back
    /// does not give it (absent or `null`; not written then), see [`GaugeReading::known_sigma`].
    #[serde(default = "unknown_sigma", deserialize_with = "sigma_or_unknown", skip_serializing_if = "is_unknown_sigma")]
    pub sigma: f64,
    /// Unit of both: `mm`, `µε`, `mrad`, `1/km`; empty when a feed read back does not give it.
    #[serde(default, deserialize_with = "unit_or_empty", skip_serializing_if = "String::is_empty")]
    pub unit: String,
}

impl GaugeReading {
    /// A reading rounded to the resolution of its unit (no false digits).
    pub fn new(value: f64, sigma: f64, unit: &str) -> GaugeReading {
        let step = match unit {
            "mm" | "mrad" => 1e-5,
            "1/km" => 1e-4,
            _ => 1e-3,
        };
        let r = |v: f64| (v / step).round() * step;
        GaugeReading { value: r(value), sigma: r(sigma).max(step), unit: unit.to_string() }
    }

    /// The σ, `None` when the feed did not give it.
    pub fn known_sigma(&self) -> Option<f64> {
        Some(self.sigma).filter(|s| !s.is_nan())
    }
}

/// Default of a camera's `frame` and `posed` read from a feed that does not give them.
fn yes() -> bool {
    true
}

/// A gauge's σ that a feed does not give.
fn unknown_sigma() -> f64 {
    f64::NAN
}

fn is_unknown_sigma(s: &f64) -> bool {
    s.is_nan()
}

/// A gauge's σ, `null` read as unknown.
fn sigma_or_unknown<'de, D: serde::Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
    Ok(Option::<f64>::deserialize(d)?.unwrap_or_else(unknown_sigma))
}

/// A gauge's unit, `null` read as none.
fn unit_or_empty<'de, D: serde::Deserializer<'de>>(d: D) -> Result<String, D::Error> {
    Ok(Option::<String>::deserialize(d)?.unwrap_or_default())
}

/// A value with its 1-σ uncertainty (unit in the field's name).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ValueSigma {
    /// The value.
    pub value: f64,
    /// Its 1-σ uncertainty.
    pub sigma: f64,
}

/// Rounds to 0.01 µm: the feed carries no false digits and lines stay short.
pub fn round_mm(v: f64) -> f64 {
    (v * 1e5).round() / 1e5
}

impl FeedLine {
    /// The line as compact JSON (no trailing newline).
    pub fn to_json(&self) -> String {
        serde_json::to_string(self).expect("feed line serialises")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_what_other_writers_leave_out_and_writes_it_back_the_same() {
        let text = r#"{"seq":3,"t_ns":7,"future_field":{"x":1},"cameras":[{"name":"left","bumped":true}],"gauges":{"a":{"value":0.5},"b":{"value":1.0,"sigma":null,"unit":null}}}"#;
        let l: FeedLine = serde_json::from_str(text).unwrap();
        assert!(l.tags.is_empty());
        let c = &l.cameras[0];
        assert!(c.frame && c.posed && c.bumped && c.background_tags == 0);
        for g in l.gauges.values() {
            assert!(g.sigma.is_nan() && g.known_sigma().is_none() && g.unit.is_empty());
        }
        let back: serde_json::Value = serde_json::from_str(&l.to_json()).unwrap();
        assert_eq!(back["gauges"]["a"], serde_json::json!({"value": 0.5}), "an unknown σ is not written");
        let tag: FeedTag = serde_json::from_str(r#"{"id":1,"pos_mm":[0,0,1],"disp_mm":[0,0,0]}"#).unwrap();
        assert_eq!(tag.views, 0);
        let g = GaugeReading::new(0.123456, 0.0, "mm");
        assert_eq!(g.known_sigma(), Some(1e-5));
    }
}
