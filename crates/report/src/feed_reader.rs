//! Reading a feed for the report: each line parsed as a [`FeedLine`], the type the measurement
//! writes, which reads tolerantly (unknown fields ignored, extensions and what other writers
//! leave out optional; see [`tagdeflect_core::feed`]), checked, and held as columns
//! ([`crate::feed_columns`]) and sums ([`crate::feed_summary`]), never as lines.
//!
//! Tolerant of what is missing, strict about what is wrong: a feed is one run in time order
//! (SPEC), so `seq` must increase and `t_ns` with it; a `seq` that goes back or repeats (two
//! runs appended to one file, a file concatenated twice, a repeated line) is an error naming
//! the line, or, with [`ReadOptions::allow_restarts`], the start of a new run, reported on
//! its own. Every value must be finite and within physical ranges ([`Limits`]): a load of
//! 3e38 kN is a broken line, not a test.
//!
//! One exception, the restart of a daemon in the middle of a lab test: a line
//! that carries a [`RESUME_EVENT`] starts a new *segment* of the same run. The resumed daemon
//! numbers its frame sets from 0 again, so `seq` may go back (or repeat) there; the lines on
//! both sides are read as one test, since the test's zero was restored and its displacements
//! go on from it. `t_ns` must still increase across the resume (else the line is refused), the
//! hole is a gap in time as any other (QC's time gaps and validity's `max_gap_s` count it) and
//! a warning of the feed names the line and the hole. A `seq` going back without a `resume`
//! event on its line (or with one, after a line of another test) stays an error naming the
//! line (two runs appended to one feed).

use std::path::{Path, PathBuf};

use std::sync::{Arc, Mutex};

use serde::{Deserialize, Serialize};
use tagdeflect_core::feed::FeedLine;

use crate::error::ReportError;
use crate::feed_columns::Columns;
use crate::feed_summary::LineSummary;
use crate::report::TestRig;
use crate::tag_stats::TagStats;

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

/// A whole feed file (or one run of it): its lines as columns, never as lines (see
/// [`crate::feed_columns`]).
#[derive(Debug, Clone)]
pub struct Feed {
    /// Where it was read from.
    pub path: PathBuf,
    /// The lines in time order, one entry per line in each column.
    pub columns: Columns,
    /// 1-based file line of each line (for messages).
    pub line_numbers: Vec<usize>,
    /// Warnings from reading (a truncated last line).
    pub warnings: Vec<String>,
    /// `(index from 1, runs in the file)` when the file held several runs.
    pub run: Option<(usize, usize)>,
    /// What the lines said that is kept only in sum: the cameras' health, the gauges' units,
    /// the tags seen, ... (see [`crate::feed_summary`]).
    pub summary: LineSummary,
    /// Where the lines are read again (the tags, which are not held).
    pub(crate) source: Source,
    /// The tags' figures gathered as the lines were read, for the rig they were gathered for
    /// ([`Feed::read_runs_for`]); taken by the report that uses them.
    tag_stats: TagSlot,
}

/// The tags' figures of a feed read for a rig, until a report takes them.
type TagSlot = Arc<Mutex<Option<Box<(TestRig, TagStats)>>>>;

/// Where a feed's lines are read again from: the file (from the byte where the run's first
/// line starts) or the text it was parsed from.
#[derive(Debug, Clone)]
pub(crate) enum Source {
    /// The file `Feed::path`, the run's first line at this byte.
    File { offset: u64 },
    /// Parsed text, the run's first line at this byte.
    Text { text: Arc<str>, offset: usize },
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
    /// line, never whole, and each line is held as its entries in [`Feed::columns`] (a long
    /// test's feed is gigabytes of text; ~100 B a line are held).
    pub fn read_runs(path: &Path, opts: &ReadOptions) -> Result<Vec<Feed>, ReportError> {
        Self::read_runs_for(path, opts, None)
    }

    /// [`Feed::read_runs`], gathering as the lines are read what the report takes from their
    /// tags for `rig` (its up direction, its tags' roles): the report of the feed with that rig
    /// needs no second read of the file for its numbers (`curve.csv` still reads it again:
    /// its header names every tag of the feed before the first row).
    pub fn read_runs_for(path: &Path, opts: &ReadOptions, rig: Option<&TestRig>) -> Result<Vec<Feed>, ReportError> {
        use std::io::BufRead;
        let io = |e: std::io::Error| ReportError::Io { path: path.to_path_buf(), message: format!("cannot read the feed: {e}") };
        // A rotated run's current file: its rotated files first, in order (`[output.feed_rotation]`).
        let mut reader = tagdeflect_core::feed_rotation::open_feed_set(path).map_err(io)?;
        let mut runs = Runs::new(path, opts, None);
        runs.rig = rig;
        let mut buf = Vec::new();
        let (mut no, mut offset) = (0, 0);
        loop {
            buf.clear();
            let n = reader.read_until(b'\n', &mut buf).map_err(io)?;
            if n == 0 {
                break;
            }
            runs.offset = offset;
            offset += n;
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
        let shared: Arc<str> = Arc::from(text);
        let mut runs = Runs::new(path, opts, Some(shared.clone()));
        let mut lines = shared.lines().peekable();
        let mut no = 0;
        while let Some(line) = lines.next() {
            runs.offset = line.as_ptr() as usize - shared.as_ptr() as usize;
            no += 1;
            runs.line(no, line, lines.peek().is_none() && !ends_with_newline)?;
        }
        runs.finish(no)
    }

    /// A feed of `lines` (in memory, as parsed from their JSON text): for tests.
    pub fn from_lines(path: &Path, lines: &[FeedLine]) -> Result<Feed, ReportError> {
        let text: String = lines.iter().map(|l| serde_json::to_string(l).expect("a feed line serialises") + "\n").collect();
        Ok(Self::parse(&text, path, &ReadOptions::default())?.remove(0))
    }

    fn empty(path: &Path) -> Feed {
        Feed {
            path: path.to_path_buf(),
            columns: Columns::default(),
            line_numbers: Vec::new(),
            warnings: Vec::new(),
            run: None,
            summary: LineSummary::default(),
            source: Source::File { offset: 0 },
            tag_stats: TagSlot::default(),
        }
    }

    /// The tags' figures gathered for `rig` as the feed was read, taken (a second call, or
    /// another rig, gets `None`: read them again).
    pub(crate) fn take_tag_stats(&self, rig: &TestRig) -> Option<TagStats> {
        let mut slot = self.tag_stats.lock().unwrap_or_else(|e| e.into_inner());
        match slot.take() {
            Some(b) if b.0 == *rig => Some(b.1),
            other => {
                *slot = other;
                None
            }
        }
    }

    /// Lines held.
    pub fn len(&self) -> usize {
        self.columns.len()
    }

    /// True when no line is held (a feed read has at least one).
    pub fn is_empty(&self) -> bool {
        self.columns.is_empty()
    }

    /// Gauge names in order of first appearance.
    pub(crate) fn gauge_names(&self) -> Vec<String> {
        self.columns.gauges.iter().map(|g| g.name.clone()).collect()
    }

    /// The unit of a gauge (from its first reading that names one).
    pub(crate) fn gauge_unit(&self, name: &str) -> Option<String> {
        self.summary.gauge_units.get(name).cloned()
    }

    /// Tag ids seen, sorted.
    pub(crate) fn tag_ids(&self) -> Vec<u32> {
        self.summary.tag_lines.keys().copied().collect()
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
    /// The text parsed (`None`: the file is read).
    text: Option<Arc<str>>,
    /// The byte where the line being read starts.
    offset: usize,
    /// The test of the last line held.
    prev_test: Option<String>,
    /// The rig to gather the tags' figures for, and the current run's so far.
    rig: Option<&'a TestRig>,
    tags: TagStats,
}

impl<'a> Runs<'a> {
    fn new(path: &'a Path, opts: &'a ReadOptions, text: Option<Arc<str>>) -> Self {
        Runs {
            path,
            opts,
            runs: Vec::new(),
            cur: Feed::empty(path),
            warnings: Vec::new(),
            text,
            offset: 0,
            prev_test: None,
            rig: None,
            tags: TagStats::default(),
        }
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
        if self.cur.is_empty() {
            self.cur.source = match &self.text {
                Some(text) => Source::Text { text: text.clone(), offset: self.offset },
                None => Source::File { offset: self.offset as u64 },
            };
        }
        if let Some(rig) = self.rig {
            self.tags.fold(&l.tags, rig);
        }
        self.cur.summary.fold(&mut l);
        self.cur.columns.push(&l);
        self.cur.line_numbers.push(no);
        self.prev_test = l.test.map(|t| t.id);
        Ok(())
    }

    /// Checks line `no` against the line before it: a resumed test's new segment (a warning), a
    /// new run (`allow_restarts`) or an error naming the line.
    fn follow(&mut self, no: usize, l: &FeedLine) -> Result<(), ReportError> {
        let (mut warning, mut new_run) = (None, false);
        let c = &self.cur.columns;
        if let (Some(&prev_seq), Some(&prev_t_ns), Some(&prev_no)) = (c.seq.last(), c.t_ns.last(), self.cur.line_numbers.last()) {
            let prev = Prev { seq: prev_seq, t_ns: prev_t_ns };
            // A resumed test: a new segment of this run, not a new run (module doc).
            let same_test = match (&l.test, &self.prev_test) {
                (Some(a), Some(b)) => &a.id == b,
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
            let run = std::mem::replace(&mut self.cur, next);
            self.end_run(run);
        }
        Ok(())
    }

    /// Keeps a run read whole, with its tags' figures when gathered.
    fn end_run(&mut self, run: Feed) {
        let mut tags = std::mem::take(&mut self.tags);
        if let Some(rig) = self.rig {
            tags.finish();
            *run.tag_stats.lock().unwrap_or_else(|e| e.into_inner()) = Some(Box::new((rig.clone(), tags)));
        }
        self.runs.push(run);
    }

    fn finish(mut self, lines: usize) -> Result<Vec<Feed>, ReportError> {
        if !self.cur.is_empty() {
            let cur = std::mem::replace(&mut self.cur, Feed::empty(self.path));
            self.end_run(cur);
        }
        if self.runs.is_empty() {
            return Err(self.bad(lines.max(1), "the feed has no lines".into()));
        }
        let n = self.runs.len();
        for (k, r) in self.runs.iter_mut().enumerate() {
            r.warnings.extend(self.warnings.iter().cloned());
            r.columns.shrink_to_fit();
            r.line_numbers.shrink_to_fit();
            if n > 1 {
                r.run = Some((k + 1, n));
            }
        }
        Ok(self.runs)
    }
}

/// The line before the one being read.
struct Prev {
    seq: u64,
    t_ns: i64,
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
mod tests;
