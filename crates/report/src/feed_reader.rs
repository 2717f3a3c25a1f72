//! Reading a feed for the report: the lines as [`FeedLine`]s, the type the measurement
//! writes, which reads tolerantly (unknown fields ignored, extensions and what other writers
//! leave out optional; see [`tagdeflect_core::feed`]).
//!
//! Tolerant of what is missing, strict about what is wrong: a feed is one run in time order
//! (SPEC), so `seq` must increase and `t_ns` with it; a `seq` that goes back or repeats (two
//! runs appended to one file, a file concatenated twice, a repeated line) is an error naming
//! the line, or, with [`ReadOptions::allow_restarts`], the start of a new run, reported on
//! its own. Every value must be finite and within physical ranges ([`Limits`]): a load of
//! 3e38 kN is a broken line, not a test.
//!
//! One exception, the restart of a daemon in the middle of a lab test (issue 24 item 3): a line
//! that carries a [`RESUME_EVENT`] starts a new *segment* of the same run. The resumed daemon
//! numbers its frame sets from 0 again, so `seq` may go back (or repeat) there; the lines on
//! both sides are read as one test, since the test's zero was restored and its displacements
//! go on from it. `t_ns` must still increase across the resume (else the line is refused), the
//! hole is a gap in time as any other (QC's time gaps and validity's `max_gap_s` count it) and
//! a warning of the feed names the line and the hole. A `seq` going back without a `resume`
//! event on its line (or with one, after a line of another test) stays an error naming the
//! line (two runs appended to one feed, issue 24 item 8).

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use tagdeflect_core::feed::FeedLine;

use crate::error::ReportError;
use crate::feed_summary::LineSummary;

/// Physical ranges of a feed's values (`[report] max_load_kn`, `max_length_mm`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Limits {
    /// Largest |load| a line may carry, kN.
    pub max_load_kn: f64,
    /// Largest |length| (positions, displacements, stroke, deflection, gauges in mm, σ), mm.
    pub max_length_mm: f64,
}

impl Default for Limits {
    fn default() -> Self {
        Limits { max_load_kn: DEFAULT_MAX_LOAD_KN, max_length_mm: DEFAULT_MAX_LENGTH_MM }
    }
}

/// Default largest load: beyond the largest flexural testing machines.
pub const DEFAULT_MAX_LOAD_KN: f64 = 10_000.0;
/// Default largest length: a 10 m world around the rig.
pub const DEFAULT_MAX_LENGTH_MM: f64 = 10_000.0;
/// Largest |value| of a gauge in another unit (µε, mrad, 1/km).
const MAX_OTHER_GAUGE: f64 = 1e9;
/// Latest time a feed may carry: 2200-01-01 (the i64 nanosecond clock ends in 2262).
const MAX_T_NS: i64 = 7_258_118_400_000_000_000;

/// The kind of the feed event a daemon puts on its first line after resuming a lab test it
/// was running when it stopped (`tagdeflect_sinks::lab_test`, `TESTS/.running.json`): the
/// line starts a new segment of the same test, where `seq` may restart (see the module doc).
pub(crate) const RESUME_EVENT: &str = "resume";

/// True when `line` carries a [`RESUME_EVENT`]: its `seq` may go back from the line before it.
pub(crate) fn resumes(line: &FeedLine) -> bool {
    line.events.iter().any(|e| e.kind == RESUME_EVENT)
}

/// How a feed is read.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct ReadOptions {
    /// Physical ranges.
    pub limits: Limits,
    /// A `seq` going back or repeating starts a new run instead of being an error.
    pub allow_restarts: bool,
}

/// A whole feed file (or one run of it).
#[derive(Debug, Clone)]
pub struct Feed {
    /// Where it was read from.
    pub path: PathBuf,
    /// The lines in time order.
    pub lines: Vec<FeedLine>,
    /// 1-based file line of each line (for messages).
    pub line_numbers: Vec<usize>,
    /// Warnings from reading (a truncated last line).
    pub warnings: Vec<String>,
    /// `(index from 1, runs in the file)` when the file held several runs.
    pub run: Option<(usize, usize)>,
    /// What the lines said that is kept only in sum: the cameras' health, the gauges' units
    /// (the held lines carry no `cameras` and no unit equal to their gauge's first; see
    /// [`crate::feed_summary`]).
    pub summary: LineSummary,
}

impl Feed {
    /// Reads a feed (JSON Lines) that must hold one run. A truncated last line (no newline,
    /// cut JSON — what a writer killed mid-line leaves) is skipped with a warning, as the
    /// recording reader does; any other bad line is an error naming the file and line.
    pub fn read(path: &Path) -> Result<Feed, ReportError> {
        let mut runs = Self::read_runs(path, &ReadOptions::default())?;
        Ok(runs.remove(0))
    }

    /// Reads a feed into its runs (one unless `allow_restarts`); a rotated feed's current file
    /// is read after its rotated files (line numbers in messages count across them). The file is read line by
    /// line, never whole: only the parsed lines are held (a long test's feed is gigabytes of
    /// text).
    pub fn read_runs(path: &Path, opts: &ReadOptions) -> Result<Vec<Feed>, ReportError> {
        use std::io::BufRead;
        let io = |e: std::io::Error| ReportError::Io { path: path.to_path_buf(), message: format!("cannot read the feed: {e}") };
        // A rotated run's current file: its rotated files first, in order (`[output.feed_rotation]`).
        let mut reader = tagdeflect_core::feed_rotation::open_feed_set(path).map_err(io)?;
        let mut runs = Runs::new(path, opts);
        let mut buf = Vec::new();
        let mut no = 0;
        loop {
            buf.clear();
            if reader.read_until(b'\n', &mut buf).map_err(io)? == 0 {
                break;
            }
            no += 1;
            let unterminated = buf.last() != Some(&b'\n');
            let text = std::str::from_utf8(&buf).map_err(|_| ReportError::BadLine {
                path: path.to_path_buf(),
                line: no,
                message: "not a feed line: not UTF-8 text".into(),
            })?;
            let text = text.strip_suffix('\n').map_or(text, |t| t.strip_suffix('\r').unwrap_or(t));
            runs.line(no, text, unterminated)?;
        }
        runs.finish(no)
    }

    /// Parses feed text; `path` names the file in errors.
    pub fn parse(text: &str, path: &Path, opts: &ReadOptions) -> Result<Vec<Feed>, ReportError> {
        let ends_with_newline = text.ends_with('\n');
        let mut runs = Runs::new(path, opts);
        let mut lines = text.lines().peekable();
        let mut no = 0;
        while let Some(line) = lines.next() {
            no += 1;
            runs.line(no, line, lines.peek().is_none() && !ends_with_newline)?;
        }
        runs.finish(no)
    }

    fn empty(path: &Path) -> Feed {
        Feed {
            path: path.to_path_buf(),
            lines: Vec::new(),
            line_numbers: Vec::new(),
            warnings: Vec::new(),
            run: None,
            summary: LineSummary::default(),
        }
    }

    /// Gauge names in order of first appearance.
    pub(crate) fn gauge_names(&self) -> Vec<String> {
        let mut names: Vec<String> = Vec::new();
        let mut seen = std::collections::HashSet::new();
        for l in &self.lines {
            for k in l.gauges.keys() {
                if seen.insert(k.as_str()) {
                    names.push(k.clone());
                }
            }
        }
        names
    }

    /// The unit of a gauge (from its first reading that names one).
    pub(crate) fn gauge_unit(&self, name: &str) -> Option<String> {
        self.summary.gauge_units.get(name).cloned()
    }

    /// Tag ids seen, sorted.
    pub(crate) fn tag_ids(&self) -> Vec<u32> {
        let mut ids: Vec<u32> = self.lines.iter().flat_map(|l| l.tags.iter().map(|t| t.id)).collect();
        ids.sort_unstable();
        ids.dedup();
        ids
    }

    /// A name for messages: the file, and the run when the file holds several.
    pub fn label(&self) -> String {
        match self.run {
            Some((k, n)) => format!(
                "{} (run {k} of {n}, lines {}–{})",
                self.path.display(),
                self.line_numbers[0],
                self.line_numbers.last().unwrap_or(&0)
            ),
            None => self.path.display().to_string(),
        }
    }
}

/// The runs of a feed being read, line by line (see [`Feed::read_runs`]).
struct Runs<'a> {
    path: &'a Path,
    opts: &'a ReadOptions,
    runs: Vec<Feed>,
    cur: Feed,
    /// The file's warnings (a truncated last line).
    warnings: Vec<String>,
}

impl<'a> Runs<'a> {
    fn new(path: &'a Path, opts: &'a ReadOptions) -> Self {
        Runs { path, opts, runs: Vec::new(), cur: Feed::empty(path), warnings: Vec::new() }
    }

    fn bad(&self, line: usize, message: String) -> ReportError {
        ReportError::BadLine { path: self.path.to_path_buf(), line, message: format!("not a feed line: {message}") }
    }

    /// Line `no` of the file (without its newline); `unterminated` when no newline ended it.
    fn line(&mut self, no: usize, line: &str, unterminated: bool) -> Result<(), ReportError> {
        if line.trim().is_empty() {
            return Ok(());
        }
        let mut l = match serde_json::from_str::<FeedLine>(line) {
            Ok(l) => l,
            Err(e) => {
                if unterminated && e.is_eof() {
                    let msg = format!("{}:{no}: truncated last line skipped", self.path.display());
                    tracing::warn!("{msg}");
                    self.warnings.push(msg);
                    return Ok(());
                }
                return Err(self.bad(no, e.to_string()));
            }
        };
        check_values(&l, &self.opts.limits).map_err(|e| self.bad(no, e.to_string()))?;
        self.follow(no, &l)?;
        compact(&mut l, &mut self.cur.summary);
        self.cur.lines.push(l);
        self.cur.line_numbers.push(no);
        Ok(())
    }

    /// Checks line `no` against the line before it: a resumed test's new segment (a warning), a
    /// new run (`allow_restarts`) or an error naming the line.
    fn follow(&mut self, no: usize, l: &FeedLine) -> Result<(), ReportError> {
        let (mut warning, mut new_run) = (None, false);
        if let (Some(prev), Some(&prev_no)) = (self.cur.lines.last(), self.cur.line_numbers.last()) {
            // A resumed test: a new segment of this run, not a new run (module doc).
            let same_test = match (&l.test, &prev.test) {
                (Some(a), Some(b)) => a.id == b.id,
                _ => true,
            };
            let resumed = resumes(l) && same_test;
            if resumed {
                if l.t_ns <= prev.t_ns {
                    return Err(self.bad(
                        no,
                        format!(
                            "t_ns {} is not after t_ns {} of line {prev_no}: a resumed test's time must go on after the restart",
                            l.t_ns, prev.t_ns
                        ),
                    ));
                }
                let msg = format!(
                    "{}:{no}: the daemon restarted during the test (a `resume` event): no lines for {:.1} s after line {prev_no} \
                     (a gap in time), seq {} after seq {}; read as one test, which went on from its kept zero",
                    self.path.display(),
                    (l.t_ns - prev.t_ns) as f64 * 1e-9,
                    l.seq,
                    prev.seq
                );
                tracing::warn!("{msg}");
                warning = Some(msg);
            } else if l.seq <= prev.seq {
                if !self.opts.allow_restarts {
                    let what = if l.seq == prev.seq { "repeats" } else { "goes back from" };
                    return Err(self.bad(
                        no,
                        format!(
                            "seq {} {what} seq {} of line {prev_no}: a feed holds one run in order (two runs appended to one file, or a repeated line?); \
                             split the file, or give --allow-restarts to report each run on its own \
                             (a daemon that resumed a test after a restart marks the line with a `resume` event: this one has none)",
                            l.seq, prev.seq
                        ),
                    ));
                }
                new_run = true;
            } else if l.t_ns <= prev.t_ns {
                return Err(self.bad(
                    no,
                    format!("t_ns {} is not after t_ns {} of line {prev_no}: the feed's time must increase with seq", l.t_ns, prev.t_ns),
                ));
            }
        }
        if let Some(msg) = warning {
            self.cur.warnings.push(msg);
        }
        if new_run {
            let next = Feed::empty(self.path);
            self.runs.push(std::mem::replace(&mut self.cur, next));
        }
        Ok(())
    }

    fn finish(mut self, lines: usize) -> Result<Vec<Feed>, ReportError> {
        if !self.cur.lines.is_empty() {
            let cur = std::mem::replace(&mut self.cur, Feed::empty(self.path));
            self.runs.push(cur);
        }
        if self.runs.is_empty() {
            return Err(self.bad(lines.max(1), "the feed has no lines".into()));
        }
        let n = self.runs.len();
        for (k, r) in self.runs.iter_mut().enumerate() {
            r.warnings.extend(self.warnings.iter().cloned());
            r.lines.shrink_to_fit();
            r.line_numbers.shrink_to_fit();
            if n > 1 {
                r.run = Some((k + 1, n));
            }
        }
        Ok(self.runs)
    }
}

/// A parsed line held for the whole report: what is kept only in sum folded into `summary`
/// and dropped, its lists without spare capacity.
fn compact(l: &mut FeedLine, summary: &mut LineSummary) {
    summary.fold(l);
    l.tags.shrink_to_fit();
    l.events.shrink_to_fit();
}

/// A number for a message: scientific beyond ordinary magnitudes.
pub(crate) fn fmt_g(v: f64) -> String {
    if v != 0.0 && (v.abs() >= 1e7 || v.abs() < 1e-4) {
        format!("{v:e}")
    } else {
        v.to_string()
    }
}

use fmt_g as g;

/// A value of a feed line that is not finite or not within the limits; the message names
/// the field.
#[derive(Debug, thiserror::Error)]
enum ValueError {
    #[error("t_ns {t_ns} is not a time between 1970 and 2200 (ns since the Unix epoch)")]
    Time { t_ns: i64 },
    #[error("seq {seq} is beyond 2^53 (not a frame-set count)")]
    Seq { seq: u64 },
    #[error("{what} = {} mm is outside ±{max_mm} mm (max_length_mm)", g(*.value))]
    Length { what: String, value: f64, max_mm: f64 },
    #[error("{what} = {} is not a σ between 0 and {max_mm} mm", g(*.value))]
    Sigma { what: String, value: f64, max_mm: f64 },
    #[error("load_kN = {} is outside ±{max_kn} kN (max_load_kn)", g(*.value))]
    Load { value: f64, max_kn: f64 },
    #[error("gauge {name} = {} {unit} is not a finite reading within ±1e9", g(*.value))]
    Gauge { name: String, value: f64, unit: String },
    #[error("gauge {name} sigma = {sigma} is not a finite, non-negative σ")]
    GaugeSigma { name: String, sigma: f64 },
    #[error("clock_offset_ms = {value} ± {sigma} is not an offset within ±10^7 ms")]
    ClockOffset { value: f64, sigma: f64 },
    #[error("camera {camera} {field} = {value} is not finite")]
    CameraDrift { camera: String, field: &'static str, value: f64 },
}

/// Every value of a line finite and within the limits; the message names the field.
fn check_values(l: &FeedLine, lim: &Limits) -> Result<(), ValueError> {
    if !(0..=MAX_T_NS).contains(&l.t_ns) {
        return Err(ValueError::Time { t_ns: l.t_ns });
    }
    if l.seq > (1u64 << 53) {
        return Err(ValueError::Seq { seq: l.seq });
    }
    let max_mm = lim.max_length_mm;
    let len = |what: &str, v: f64| -> Result<(), ValueError> {
        if v.is_finite() && v.abs() <= max_mm {
            Ok(())
        } else {
            Err(ValueError::Length { what: what.to_string(), value: v, max_mm })
        }
    };
    let sig = |what: &str, v: f64| -> Result<(), ValueError> {
        if v.is_finite() && (0.0..=max_mm).contains(&v) {
            Ok(())
        } else {
            Err(ValueError::Sigma { what: what.to_string(), value: v, max_mm })
        }
    };
    if let Some(p) = l.load_kn {
        if !(p.is_finite() && p.abs() <= lim.max_load_kn) {
            return Err(ValueError::Load { value: p, max_kn: lim.max_load_kn });
        }
    }
    if let Some(s) = l.stroke_mm {
        len("stroke_mm", s)?;
    }
    if let Some(d) = l.net_deflection_mm {
        len("net_deflection_mm", d)?;
    }
    for t in &l.tags {
        for k in 0..3 {
            len(&format!("tag {} pos_mm", t.id), t.pos_mm[k])?;
            len(&format!("tag {} disp_mm", t.id), t.disp_mm[k])?;
            if let Some(s) = t.sigma_mm {
                sig(&format!("tag {} sigma_mm", t.id), s[k])?;
            }
        }
    }
    for (name, g) in &l.gauges {
        if g.unit == "mm" || g.unit.is_empty() {
            len(&format!("gauge {name}"), g.value)?;
        } else if !(g.value.is_finite() && g.value.abs() <= MAX_OTHER_GAUGE) {
            return Err(ValueError::Gauge { name: name.clone(), value: g.value, unit: g.unit.clone() });
        }
        if let Some(s) = g.known_sigma() {
            if !(s.is_finite() && s >= 0.0 && (g.unit != "mm" || s <= lim.max_length_mm)) {
                return Err(ValueError::GaugeSigma { name: name.clone(), sigma: s });
            }
        }
    }
    if let Some(c) = &l.clock_offset_ms {
        if !(c.value.is_finite() && c.value.abs() <= 1e7 && c.sigma.is_finite() && (0.0..=1e7).contains(&c.sigma)) {
            return Err(ValueError::ClockOffset { value: c.value, sigma: c.sigma });
        }
    }
    for c in &l.cameras {
        for (k, v) in [("drift_deg", c.drift_deg), ("drift_mm", c.drift_mm)] {
            if let Some(v) = v {
                if !(v.is_finite() && v.abs() <= 360.0 * 1e3) {
                    return Err(ValueError::CameraDrift { camera: c.name.clone(), field: k, value: v });
                }
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> Result<Vec<Feed>, ReportError> {
        Feed::parse(text, Path::new("f.jsonl"), &ReadOptions::default())
    }

    #[test]
    fn reads_lines_other_writers_leave_short_and_skips_a_truncated_last_one() {
        let text = concat!(
            r#"{"seq":0,"t_ns":10,"tags":[{"id":4,"pos_mm":[0,0,0],"disp_mm":[0,0,-1]}],"gauges":{"cmod":{"value":0.0,"sigma":0.002,"unit":"mm"}}}"#,
            "\n",
            r#"{"seq":1,"t_ns":20,"load_kN":1.5,"gauges":{"cmod":{"value":0.1}},"cameras":[{"name":"left"}],"drift_px":3}"#,
            "\n",
            r#"{"seq":2,"t_ns":30,"tags":[{"id""#,
        );
        let feed = parse(text).unwrap().remove(0);
        assert_eq!(feed.lines.iter().map(|l| l.seq).collect::<Vec<_>>(), vec![0, 1], "the cut line skipped");
        assert_eq!(feed.warnings, vec!["f.jsonl:3: truncated last line skipped".to_string()]);
        assert_eq!(feed.gauge_names(), vec!["cmod".to_string()]);
        assert_eq!(feed.gauge_unit("cmod").as_deref(), Some("mm"), "from the first line that names one");
        assert_eq!(feed.lines[1].gauges["cmod"].known_sigma(), None);
        assert_eq!(feed.summary.cameras["left"], crate::feed_summary::CameraTally::default(), "framed and posed by default");
        assert!(feed.lines.iter().all(|l| l.cameras.is_empty() && l.gauges.values().all(|g| g.unit.is_empty())), "kept in sum only");
        assert_eq!(feed.tag_ids(), vec![4]);
        let e = parse("{\"seq\":0,\"t_ns\":\"soon\"}\n").unwrap_err();
        assert!(e.to_string().starts_with("f.jsonl:1: not a feed line"), "{e}");
    }

    #[test]
    fn a_seq_going_back_or_repeating_is_an_error_or_a_new_run() {
        let l = |seq: u64, t: i64| format!("{{\"seq\":{seq},\"t_ns\":{t},\"load_kN\":1.0}}\n");
        let restart = [l(0, 10), l(1, 20), l(0, 30), l(1, 40), l(2, 50)].concat();
        let e = parse(&restart).unwrap_err().to_string();
        assert!(e.starts_with("f.jsonl:3: not a feed line: seq 0 goes back from seq 1 of line 2"), "{e}");
        let e = parse(&[l(0, 10), l(1, 20), l(1, 30)].concat()).unwrap_err().to_string();
        assert!(e.starts_with("f.jsonl:3:") && e.contains("seq 1 repeats seq 1"), "{e}");
        let e = parse(&[l(0, 10), l(1, 5)].concat()).unwrap_err().to_string();
        assert!(e.starts_with("f.jsonl:2:") && e.contains("t_ns 5 is not after"), "{e}");
        let runs = Feed::parse(&restart, Path::new("f.jsonl"), &ReadOptions { allow_restarts: true, ..Default::default() }).unwrap();
        assert_eq!(runs.len(), 2);
        assert_eq!((runs[0].lines.len(), runs[1].lines.len()), (2, 3));
        assert_eq!(runs[1].run, Some((2, 2)));
        assert_eq!(runs[1].line_numbers, vec![3, 4, 5]);
    }

    /// A lab test's feed across a restart of its daemon (issue 24 item 3): seq 75–79, then
    /// the resumed daemon's seq 0–9 after a 12 s hole, its first line with the `resume` event.
    fn resumed_test_feed(with_event: bool) -> String {
        const T0: i64 = 1_764_000_000_000_000_000;
        let test = r#""test":{"id":"20261202T013000Z-B12","specimen":"B12"}"#;
        let mut text = String::new();
        let mut line = |seq: u64, t_ns: i64, events: &str| {
            let x = (t_ns - T0) as f64 * 1e-9 * 0.01;
            text.push_str(&format!(
                "{{\"seq\":{seq},\"t_ns\":{t_ns},\"load_kN\":{:.3},\"net_deflection_mm\":{x:.6},{test}{events}}}\n",
                10.0 + 300.0 * x
            ));
        };
        for k in 0..5 {
            line(75 + k, T0 + k as i64 * 200_000_000, "");
        }
        let t1 = T0 + 800_000_000 + 12_000_000_000;
        for k in 0..10 {
            let ev = if k == 0 && with_event {
                format!(r#","events":[{{"kind":"{RESUME_EVENT}","t_ns":{}}}]"#, t1 - 50_000_000)
            } else {
                String::new()
            };
            line(k, t1 + k as i64 * 200_000_000, &ev);
        }
        text
    }

    /// With the `resume` event the seq restart is one test read across it, the hole named in
    /// the feed's warnings and counted as a gap by QC and validity; without it the same feed
    /// is refused, naming the line; a resume whose time goes back is refused too.
    #[test]
    fn a_resumed_test_is_one_test_across_its_seq_restart_and_its_hole_is_a_gap() {
        let text = resumed_test_feed(true);
        for allow_restarts in [false, true] {
            let runs = Feed::parse(&text, Path::new("f.jsonl"), &ReadOptions { allow_restarts, ..Default::default() }).unwrap();
            assert_eq!(runs.len(), 1, "one test, not two runs (allow_restarts {allow_restarts})");
            let feed = &runs[0];
            assert_eq!(feed.run, None);
            assert_eq!(feed.lines.iter().map(|l| l.seq).collect::<Vec<_>>(), [75, 76, 77, 78, 79, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9]);
            assert_eq!(feed.line_numbers, (1..=15).collect::<Vec<_>>());
            assert!(resumes(&feed.lines[5]) && !resumes(&feed.lines[4]));
            assert_eq!(feed.warnings.len(), 1, "{:?}", feed.warnings);
            let w = &feed.warnings[0];
            assert!(
                w.starts_with("f.jsonl:6: the daemon restarted during the test") && w.contains("no lines for 12.0 s after line 5"),
                "{w}"
            );
            assert!(w.contains("seq 0 after seq 79"), "{w}");
        }

        // The report reads it as one test: the hole is one gap in time for QC (with the
        // reader's warning) and for validity.
        let feed = Feed::parse(&text, Path::new("f.jsonl"), &ReadOptions::default()).unwrap().remove(0);
        let specimen: tagdeflect_core::rig::SpecimenConfig = serde_json::from_value(serde_json::json!({
            "family": "tag36h11", "size_mm": 30.0, "tag": [],
            "beam": {"width_mm": 150.0, "depth_mm": 150.0, "span_mm": 450.0},
        }))
        .unwrap();
        let rig = crate::TestRig { world: Default::default(), specimen, gauges: Vec::new() };
        let opts = crate::ReportConfig::new(crate::Standard::AstmC1609, "out".into());
        let rep = crate::build(&feed, None, &rig, Path::new("rig.toml"), &opts).unwrap();
        assert_eq!(rep.qc.time_gaps.len(), 1, "{:?}", rep.qc.time_gaps);
        assert!((rep.qc.time_gaps[0].duration_s - 12.0).abs() < 1e-6, "{:?}", rep.qc.time_gaps);
        assert!(rep.qc.warnings.iter().any(|w| w.contains("the daemon restarted during the test")), "{:?}", rep.qc.warnings);
        assert!(rep.qc.warnings.iter().any(|w| w.starts_with("1 gap(s) in time")), "{:?}", rep.qc.warnings);
        assert!(!rep.validity.valid && rep.validity.reasons.iter().any(|r| r.contains("gap(s)")), "{:?}", rep.validity.reasons);

        // The same feed without the event: two runs appended, refused naming the line.
        let e = parse(&resumed_test_feed(false)).unwrap_err().to_string();
        assert!(e.starts_with("f.jsonl:6: not a feed line: seq 0 goes back from seq 79 of line 5"), "{e}");
        assert!(e.contains("`resume` event"), "{e}");
        // A resume whose time goes back, or a resume after a line of another test, is refused.
        let back = text.replacen(
            &format!("\"t_ns\":{}", 1_764_000_000_000_000_000i64 + 800_000_000 + 12_000_000_000),
            "\"t_ns\":1764000000000000000",
            1,
        );
        let e = parse(&back).unwrap_err().to_string();
        assert!(e.starts_with("f.jsonl:6: not a feed line: t_ns 1764000000000000000 is not after"), "{e}");
        let mut other: Vec<String> = text.lines().map(String::from).collect();
        for l in &mut other[5..] {
            *l = l.replace("-B12\"", "-B13\"");
        }
        let e = parse(&(other.join("\n") + "\n")).unwrap_err().to_string();
        assert!(e.starts_with("f.jsonl:6: not a feed line: seq 0 goes back from seq 79 of line 5"), "{e}");
    }

    #[test]
    fn absurd_values_are_errors_naming_the_field() {
        let cases = [
            (r#"{"seq":0,"t_ns":10,"load_kN":1e308}"#, "load_kN = 1e308"),
            (r#"{"seq":0,"t_ns":10,"load_kN":-3e38}"#, "load_kN = -3"),
            (r#"{"seq":0,"t_ns":-9223372036854775808}"#, "t_ns -9223372036854775808"),
            (r#"{"seq":0,"t_ns":9223372036854775807}"#, "t_ns 9223372036854775807"),
            (r#"{"seq":18446744073709551615,"t_ns":10}"#, "seq 18446744073709551615"),
            (r#"{"seq":0,"t_ns":10,"net_deflection_mm":1e20}"#, "net_deflection_mm"),
            (r#"{"seq":0,"t_ns":10,"gauges":{"cmod":{"value":1e300,"unit":"mm"}}}"#, "gauge cmod"),
            (r#"{"seq":0,"t_ns":10,"tags":[{"id":3,"pos_mm":[0,0,1e99],"disp_mm":[0,0,0]}]}"#, "tag 3 pos_mm"),
        ];
        for (line, want) in cases {
            let e = parse(&format!("{line}\n")).unwrap_err().to_string();
            assert!(e.starts_with("f.jsonl:1: not a feed line") && e.contains(want), "{line}: {e}");
        }
    }

    /// Read line by line as parsed whole (a `\r\n`, a cut last line); a non-UTF-8 line named.
    #[test]
    fn a_feed_read_line_by_line_is_the_feed_parsed_whole() {
        let dir = tempfile::tempdir().unwrap();
        let text = [resumed_test_feed(true).replacen('\n', "\r\n", 2), "\n{\"seq\":99,\"t_ns\":9".into()].concat();
        let path = dir.path().join("f.jsonl");
        std::fs::write(&path, &text).unwrap();
        let (streamed, whole) =
            (Feed::read_runs(&path, &ReadOptions::default()).unwrap(), Feed::parse(&text, &path, &ReadOptions::default()).unwrap());
        assert_eq!((streamed.len(), streamed[0].lines.len()), (1, 15));
        assert_eq!(
            (&streamed[0].lines, &streamed[0].line_numbers, &streamed[0].warnings),
            (&whole[0].lines, &whole[0].line_numbers, &whole[0].warnings)
        );
        assert!(streamed[0].warnings.iter().any(|w| w.contains(":17: truncated last line skipped")), "{:?}", streamed[0].warnings);
        std::fs::write(&path, [&b"{\"seq\":0,\"t_ns\":1}\n\xff\n"[..], text.as_bytes()].concat()).unwrap();
        let e = Feed::read_runs(&path, &ReadOptions::default()).unwrap_err().to_string();
        assert!(e.contains("f.jsonl:2: not a feed line: not UTF-8"), "{e}");
    }
}
