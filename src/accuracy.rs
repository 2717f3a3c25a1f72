//! Accuracy of a feed against a recording's ground truth (`truth.jsonl`): what the
//! accuracy tests assert and `bench` prints for synthetic recordings.
//!
//! Truth is interpolated linearly to each feed line's `t_ns`. A tag's true displacement
//! is its true centre minus its true centre at the time of the first feed line that
//! solved it — the same reference the feed uses — so the comparison is of displacements,
//! as an engineer uses them, not of absolute positions.

use nalgebra::Vector3;
use serde::Serialize;
use std::collections::HashMap;

use crate::config::{Config, TagRole};
use tagdeflect_core::feed::FeedLine;
use tagdeflect_io::recording::TruthLine;

/// Accuracy figures of a feed.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Accuracy {
    /// Feed lines compared.
    pub lines: usize,
    /// Tag solutions compared.
    pub tag_solutions: usize,
    /// Tag solutions expected (lines × configured specimen tags).
    pub tag_slots: usize,
    /// RMS of the 3D displacement error, mm.
    pub disp_rms_mm: f64,
    /// RMS of the vertical (along `world.up`) displacement error, mm.
    pub vertical_rms_mm: f64,
    /// Largest 3D displacement error, mm.
    pub disp_max_mm: f64,
    /// RMS of the net deflection error, mm (lines that carry it).
    pub net_rms_mm: Option<f64>,
    /// Lines that carry a net deflection.
    pub net_lines: usize,
    /// Fraction of per-axis position errors within 2σ (lines with `sigma_mm`), where the
    /// position error is taken relative to the tag's first solution (as displacement).
    pub within_2sigma: Option<f64>,
    /// RMS of the per-axis errors in units of their σ (1 when σ is right; below 1 when σ
    /// is inflated, above when it is too small): the two-sided check of σ.
    pub z_rms: Option<f64>,
    /// Fraction of per-axis displacement errors within 2σ of the feed's displacement σ
    /// (`disp_sigma_mm`, lines that carry it; not the tag's zero, whose displacement is 0).
    pub disp_within_2sigma: Option<f64>,
    /// RMS of the per-axis displacement errors in units of `disp_sigma_mm`.
    pub disp_z_rms: Option<f64>,
}

impl Accuracy {
    /// Fraction of (line, tag) slots that were solved.
    pub fn coverage(&self) -> f64 {
        if self.tag_slots == 0 {
            0.0
        } else {
            self.tag_solutions as f64 / self.tag_slots as f64
        }
    }
}

/// Truth centre of every tag at `t_ns`, interpolated between the two nearest truth lines
/// (held at the ends).
pub fn truth_at(truth: &[TruthLine], t_ns: i64) -> HashMap<u32, Vector3<f64>> {
    let i = truth.partition_point(|l| l.t_ns < t_ns);
    let (a, b) = match (i.checked_sub(1).and_then(|j| truth.get(j)), truth.get(i)) {
        (Some(a), Some(b)) => (a, b),
        (Some(a), None) => (a, a),
        (None, Some(b)) => (b, b),
        (None, None) => return HashMap::new(),
    };
    let w = if b.t_ns > a.t_ns { (t_ns - a.t_ns) as f64 / (b.t_ns - a.t_ns) as f64 } else { 0.0 };
    let bmap: HashMap<u32, Vector3<f64>> = b.tags.iter().map(|t| (t.id, Vector3::from(t.center_mm))).collect();
    a.tags.iter().filter_map(|t| bmap.get(&t.id).map(|pb| (t.id, Vector3::from(t.center_mm) * (1.0 - w) + pb * w))).collect()
}

/// Compares feed lines with ground truth.
pub fn evaluate(config: &Config, truth: &[TruthLine], feed: &[FeedLine]) -> Accuracy {
    evaluate_from(config, truth, feed, 0)
}

/// Like [`evaluate`], but counts only the lines with `seq >= from_seq` (displacements keep
/// their reference in the first line that solved each tag), e.g. the sets after a bump.
pub fn evaluate_from(config: &Config, truth: &[TruthLine], feed: &[FeedLine], from_seq: u64) -> Accuracy {
    let up = Vector3::from(config.world.up).normalize();
    let mut first_truth: HashMap<u32, Vector3<f64>> = HashMap::new();
    let counted = feed.iter().filter(|l| l.seq >= from_seq).count();
    let mut acc = Accuracy { lines: counted, tag_slots: counted * config.specimen.tags.len(), ..Accuracy::default() };
    let (mut sq, mut sq_v, mut n) = (0.0, 0.0, 0usize);
    let (mut net_sq, mut net_n) = (0.0, 0usize);
    let (mut in2, mut n_sigma, mut z_sq) = (0usize, 0usize, 0.0f64);
    let mut disp_z = ZScores::default();
    for line in feed {
        let tr = truth_at(truth, line.t_ns);
        let mut true_disp: HashMap<u32, Vector3<f64>> = HashMap::new();
        for tag in &line.tags {
            let Some(p) = tr.get(&tag.id) else { continue };
            let at_zero = !first_truth.contains_key(&tag.id);
            let p0 = *first_truth.entry(tag.id).or_insert(*p);
            let td = p - p0;
            true_disp.insert(tag.id, td);
            if line.seq < from_seq {
                continue;
            }
            let err = Vector3::from(tag.disp_mm) - td;
            sq += err.norm_squared();
            sq_v += err.dot(&up).powi(2);
            acc.disp_max_mm = acc.disp_max_mm.max(err.norm());
            n += 1;
            if let Some(s) = tag.sigma_mm {
                for k in 0..3 {
                    n_sigma += 1;
                    z_sq += (err[k] / s[k]).powi(2);
                    if err[k].abs() <= 2.0 * s[k] {
                        in2 += 1;
                    }
                }
            }
            // At its zero a displacement is 0 by definition: nothing for its σ to cover.
            if let (Some(s), false) = (tag.disp_sigma_mm, at_zero) {
                (0..3).for_each(|k| disp_z.add(err[k], s[k]));
            }
        }
        if line.seq < from_seq {
            continue;
        }
        if let Some(net) = line.net_deflection_mm {
            let mean = |role: TagRole| {
                let v: Vec<f64> = line
                    .tags
                    .iter()
                    .filter(|t| config.role_of(t.id) == Some(role))
                    .filter_map(|t| true_disp.get(&t.id))
                    .map(|d| -d.dot(&up))
                    .collect();
                (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
            };
            if let (Some(m), Some(s)) = (mean(TagRole::Midspan), mean(TagRole::Support)) {
                net_sq += (net - (m - s)).powi(2);
                net_n += 1;
            }
        }
    }
    acc.tag_solutions = n;
    if n > 0 {
        acc.disp_rms_mm = (sq / n as f64).sqrt();
        acc.vertical_rms_mm = (sq_v / n as f64).sqrt();
    }
    acc.net_lines = net_n;
    acc.net_rms_mm = (net_n > 0).then(|| (net_sq / net_n as f64).sqrt());
    acc.within_2sigma = (n_sigma > 0).then(|| in2 as f64 / n_sigma as f64);
    acc.z_rms = (n_sigma > 0).then(|| (z_sq / n_sigma as f64).sqrt());
    (acc.disp_within_2sigma, acc.disp_z_rms) = disp_z.figures();
    acc
}

/// Errors counted against their σ.
#[derive(Default)]
struct ZScores {
    within_2sigma: usize,
    count: usize,
    z_sq: f64,
}

impl ZScores {
    fn add(&mut self, err: f64, sigma: f64) {
        self.count += 1;
        self.z_sq += (err / sigma).powi(2);
        self.within_2sigma += usize::from(err.abs() <= 2.0 * sigma);
    }

    /// The share within 2σ and the RMS of error/σ.
    fn figures(&self) -> (Option<f64>, Option<f64>) {
        let n = self.count as f64;
        ((self.count > 0).then(|| self.within_2sigma as f64 / n), (self.count > 0).then(|| (self.z_sq / n).sqrt()))
    }
}

impl std::fmt::Display for Accuracy {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} lines, coverage {:.1} %, displacement RMS {:.4} mm (vertical {:.4} mm, max {:.4} mm), net deflection RMS {}, within 2σ {} (RMS error/σ {}), within 2σ of the displacement's σ {} (RMS error/σ {})",
            self.lines,
            100.0 * self.coverage(),
            self.disp_rms_mm,
            self.vertical_rms_mm,
            self.disp_max_mm,
            self.net_rms_mm.map_or("n/a".into(), |v| format!("{v:.4} mm")),
            self.within_2sigma.map_or("n/a".into(), |v| format!("{:.1} %", 100.0 * v)),
            self.z_rms.map_or("n/a".into(), |v| format!("{v:.2}")),
            self.disp_within_2sigma.map_or("n/a".into(), |v| format!("{:.1} %", 100.0 * v)),
            self.disp_z_rms.map_or("n/a".into(), |v| format!("{v:.2}")),
        )
    }
}
