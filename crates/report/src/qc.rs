//! The QC section: how complete and how healthy the feed behind a report is.

use serde::Serialize;
use serde_json::Value;
use std::collections::BTreeMap;

use crate::curve::Curve;
use crate::feed_columns::UtmState;
use crate::feed_reader::Feed;
use crate::report::TestRig;
use crate::tag_stats::TagStats;
use tagdeflect_core::rig::TagRole;

/// A time interval with the UTM link down.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Outage {
    /// First line with `utm = "down"`, ns.
    pub from_t_ns: i64,
    /// First line after it with the link up again (or the last line), ns.
    pub to_t_ns: i64,
    /// Its length, s.
    pub duration_s: f64,
}

/// One camera's events over the feed.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CameraEvents {
    /// Camera name.
    pub camera: String,
    /// Lines in which it was found moved and re-posed.
    pub bumps: usize,
    /// Lines without a frame from it.
    pub lines_without_frame: usize,
    /// Lines in which it had no pose.
    pub lines_unposed: usize,
}

/// A drift or stale-pose field seen in the feed.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FieldSummary {
    /// The field (`camera.<name>.<field>` for per-camera fields).
    pub field: String,
    /// Lines where it is present and non-zero / true.
    pub lines: usize,
    /// Largest absolute numeric value, when numeric.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub max_abs: Option<f64>,
}

/// Coverage of one specimen tag.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TagCoverage {
    /// Tag id.
    pub id: u32,
    /// Its role in the config.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub role: Option<&'static str>,
    /// Lines that solved it.
    pub lines: usize,
    /// Fraction of all lines, %.
    pub coverage_pct: f64,
    /// Mean number of cameras that saw it.
    pub mean_views: f64,
    /// Median σ of its position along world.up, mm.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub median_sigma_up_mm: Option<f64>,
}

/// The QC section of a report (`report.json` `qc`).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Qc {
    /// Feed lines read.
    pub lines: usize,
    /// Time of the first line, ns.
    pub first_t_ns: i64,
    /// Time of the last line, ns.
    pub last_t_ns: i64,
    /// Duration of the feed, s.
    pub duration_s: f64,
    /// Frame sets without a line: gaps in `seq`.
    pub frame_sets_without_line: u64,
    /// Gaps in time: consecutive lines further apart than 3 median frame periods (and than
    /// 0.5 s), whatever `seq` says.
    pub time_gaps: Vec<Outage>,
    /// Lines without a load.
    pub lines_without_load: usize,
    /// Lines with a load but without the curve's `x` (net deflection or CMOD).
    pub lines_with_load_without_x: usize,
    /// Points of the curve (lines with both).
    pub curve_points: usize,
    /// Frame sets dropped by the live pipeline (the last `dropped_sets`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub dropped_sets: Option<u64>,
    /// Lines with the UTM link down.
    pub utm_down_lines: usize,
    /// UTM outages.
    pub utm_outages: Vec<Outage>,
    /// Per camera: bumps, missing frames, missing poses.
    pub cameras: Vec<CameraEvents>,
    /// Drift and stale-pose fields present in the feed.
    pub drift_and_stale: Vec<FieldSummary>,
    /// The clock offset between camera and UTM time, as the feed's last line reports it.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub clock_offset: Option<Value>,
    /// Coverage per specimen tag.
    pub tags: Vec<TagCoverage>,
    /// Scatter of `x` about a local line (robust), mm.
    pub x_scatter_mm: f64,
    /// Median σ of `x` as the feed gives it, mm.
    pub x_feed_sigma_median_mm: f64,
    /// Scatter of the load about a local line (robust), kN.
    pub load_noise_kn: f64,
    /// Everything worth a look, in words.
    pub warnings: Vec<String>,
}

impl Qc {
    /// The QC of a feed and the curve made from it.
    pub(crate) fn of(feed: &Feed, config: &TestRig, tag_stats: TagStats, curve: &Curve, x_name: &str, opts: &crate::ReportConfig) -> Qc {
        let cols = &feed.columns;
        let n = cols.len();
        let t = &cols.t_ns;
        let first_t_ns = t[0];
        let last_t_ns = t[n - 1];
        // The reader guarantees t_ns increasing (and seq too, but at a lab test's `resume` line).
        let frame_sets_without_line: u64 = cols.seq.windows(2).map(|w| w[1].saturating_sub(w[0]).saturating_sub(1)).sum();
        let mut steps: Vec<f64> = t.windows(2).map(|w| (w[1] - w[0]) as f64 * 1e-9).collect();
        let period = if steps.is_empty() { 0.0 } else { super::curve::median(&mut steps) };
        drop(steps);
        let gap_s = (3.0 * period).max(0.5).min(opts.max_gap_s);
        let time_gaps: Vec<Outage> = t
            .windows(2)
            .filter(|w| (w[1] - w[0]) as f64 * 1e-9 > gap_s)
            .map(|w| Outage { from_t_ns: w[0], to_t_ns: w[1], duration_s: (w[1] - w[0]) as f64 * 1e-9 })
            .collect();
        let lines_without_load = cols.load_kn.iter().filter(|p| p.is_nan()).count();
        let lines_with_load_without_x = (n - lines_without_load).saturating_sub(curve.len());
        let dropped_sets = feed.summary.dropped_sets;

        let mut utm_outages = Vec::new();
        let mut down_from: Option<i64> = None;
        let mut utm_down_lines = 0;
        for (state, &t_ns) in cols.utm.iter().zip(t) {
            match state {
                UtmState::Down => {
                    utm_down_lines += 1;
                    down_from.get_or_insert(t_ns);
                }
                UtmState::Up => {
                    if let Some(f) = down_from.take() {
                        utm_outages.push(Outage { from_t_ns: f, to_t_ns: t_ns, duration_s: (t_ns - f) as f64 * 1e-9 });
                    }
                }
                UtmState::Absent => {}
            }
        }
        if let Some(f) = down_from {
            utm_outages.push(Outage { from_t_ns: f, to_t_ns: last_t_ns, duration_s: (last_t_ns - f) as f64 * 1e-9 });
        }

        // The cameras' health was counted as the lines were read (crate::feed_summary).
        let cams: BTreeMap<String, CameraEvents> = feed
            .summary
            .cameras
            .iter()
            .map(|(name, t)| {
                let e = CameraEvents {
                    camera: name.clone(),
                    bumps: t.bumps,
                    lines_without_frame: t.lines_without_frame,
                    lines_unposed: t.lines_unposed,
                };
                (name.clone(), e)
            })
            .collect();
        let fields = feed.summary.camera_fields.clone();
        let clock_offset = feed.summary.clock_offset_ms.map(|c| serde_json::json!({ "field": "clock_offset_ms", "value": c }));
        let drift_and_stale: Vec<FieldSummary> =
            fields.into_iter().map(|(field, (lines, max_abs))| FieldSummary { field, lines, max_abs }).collect();

        // Each tag's lines, views and σ along world.up, read again from the feed (crate::tag_stats).
        let mut tags = Vec::new();
        for (id, crate::tag_stats::TagLines { lines: count, views, sigma_up_mm: mut sig }) in tag_stats.tags {
            let role = config.role_of(id).map(|r| match r {
                TagRole::Support => "support",
                TagRole::Midspan => "midspan",
            });
            tags.push(TagCoverage {
                id,
                role,
                lines: count,
                coverage_pct: 100.0 * count as f64 / n as f64,
                mean_views: views as f64 / count.max(1) as f64,
                median_sigma_up_mm: (!sig.is_empty()).then(|| super::curve::median(&mut sig)),
            });
        }
        let mut feed_sigma = curve.sx.clone();
        let x_feed_sigma_median_mm = super::curve::median(&mut feed_sigma);

        let mut warnings = feed.warnings.clone();
        if frame_sets_without_line > 0 {
            warnings.push(format!("{frame_sets_without_line} frame set(s) have no feed line (gaps in seq)"));
        }
        if let Some(g) = time_gaps.iter().max_by(|a, b| a.duration_s.total_cmp(&b.duration_s)) {
            warnings.push(format!(
                "{} gap(s) in time longer than {gap_s:.1} s between feed lines (the longest {:.1} s, {:.1} s into the feed)",
                time_gaps.len(),
                g.duration_s,
                (g.from_t_ns - first_t_ns) as f64 * 1e-9
            ));
        }
        if lines_without_load > 0 {
            warnings.push(format!("{lines_without_load} line(s) without load"));
        }
        if lines_with_load_without_x > 0 {
            warnings.push(format!("{lines_with_load_without_x} line(s) with a load but without {x_name}"));
        }
        if let Some(d) = dropped_sets.filter(|d| *d > 0) {
            warnings.push(format!("{d} frame set(s) dropped by the live pipeline"));
        }
        if !utm_outages.is_empty() {
            let total: f64 = utm_outages.iter().map(|o| o.duration_s).sum();
            warnings.push(format!("UTM down {} time(s), {total:.1} s in all", utm_outages.len()));
        }
        for c in cams.values() {
            if c.bumps > 0 {
                warnings.push(format!("camera {} was bumped (re-posed) {} time(s)", c.camera, c.bumps));
            }
        }
        // Drift matters when what it moves the deflection by exceeds 2 σ of the deflection:
        // drift_mm as it is, drift_deg as the shift it makes at 1 m from the camera.
        let x_sigma_floor = 2.0 * x_feed_sigma_median_mm.max(curve.x_noise).max(1e-4);
        for f in &drift_and_stale {
            if f.lines == 0 {
                continue;
            }
            let effect_mm = match f.max_abs {
                Some(v) if f.field.ends_with("drift_deg") => v.to_radians() * 1000.0,
                Some(v) => v,
                None => f64::INFINITY, // a stale pose: always worth a look
            };
            if effect_mm > x_sigma_floor {
                let what = match f.max_abs {
                    Some(v) if f.field.ends_with("drift_deg") => format!("up to {v:.4}° (≈ {effect_mm:.3} mm at 1 m)"),
                    Some(v) => format!("up to {v:.3} mm"),
                    None => "present".to_string(),
                };
                warnings.push(format!(
                    "{} {what} in {} line(s): more than 2 σ of the {x_name} ({:.4} mm)",
                    f.field,
                    f.lines,
                    x_sigma_floor / 2.0
                ));
            }
        }
        for t in &tags {
            if t.role.is_some() && t.coverage_pct < 95.0 {
                warnings.push(format!("{} tag {} solved in only {:.1} % of the lines", t.role.unwrap_or(""), t.id, t.coverage_pct));
            }
        }
        // Against the first point's own σ (the zero reference's included).
        if curve.xs[0].abs() > 4.0 * curve.sxs[0] + 1e-4 {
            warnings.push(format!(
                "the curve starts at {x_name} = {:.3} mm (σ {:.4} mm), not 0: the test was not recorded from its start (areas and early points are incomplete)",
                curve.xs[0], curve.sxs[0]
            ));
        }
        if x_feed_sigma_median_mm > 0.0 && curve.x_noise > 3.0 * x_feed_sigma_median_mm {
            warnings.push(format!(
                "the scatter of {x_name} ({:.4} mm) is more than 3× the feed's σ ({:.4} mm): the σ reported may be too small",
                curve.x_noise, x_feed_sigma_median_mm
            ));
        }
        Qc {
            lines: n,
            first_t_ns,
            last_t_ns,
            duration_s: (last_t_ns - first_t_ns) as f64 * 1e-9,
            frame_sets_without_line,
            time_gaps,
            lines_without_load,
            lines_with_load_without_x,
            curve_points: curve.len(),
            dropped_sets,
            utm_down_lines,
            utm_outages,
            cameras: cams.into_values().collect(),
            drift_and_stale,
            clock_offset,
            tags,
            x_scatter_mm: curve.x_noise,
            x_feed_sigma_median_mm,
            load_noise_kn: curve.load_noise,
            warnings,
        }
    }
}
