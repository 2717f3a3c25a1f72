//! What a feed read for the report holds of its lines: one column per quantity the report
//! computes with, never the lines themselves (a 9-hour test at 30 frame sets/s
//! is 972 000 lines, and its report must fit the unit's `MemoryMax=2G`).
//!
//! Held per line: the time, `seq`, the load, the net deflection, the UTM link's state and
//! each gauge's value and σ (a missing value is NaN: the reader has checked every value
//! finite), ~100 B a line for four gauges. What the report needs of a line only in sum (the
//! cameras' health, the gauges' units, the largest `dropped_sets`, the last clock check, the
//! tags seen, whether the lines belong to a test) is folded into [`crate::feed_summary`] as
//! the line is read. The tags (~1 kB of a line's text) are not held: what depends on the rig's
//! config (each tag's σ along `world.up`, the role tags' σ of the net deflection) is gathered
//! as the line is read when the reader is given the rig (`crate::tag_stats`; every route of
//! the report does), else read from the feed again. The per-line table (`curve.csv`, every
//! tag's displacement) is written by a second read, line by line ([`crate::Feed::for_each_line`]):
//! its header names every tag and gauge of the feed, known only once the last line is read,
//! and its rows hold every tag's three displacements (216 B a line for 9 tags), which held
//! would double what a line costs (docs/performance.md).

use tagdeflect_core::feed::{FeedLine, FeedTag};

use crate::error::ReportError;
use crate::feed_reader::Source;

/// The UTM link's state on a line (`utm`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum UtmState {
    /// No `utm` field (no UTM configured).
    Absent,
    /// `"down"`.
    Down,
    /// Any other state (`"ok"`).
    Up,
}

/// One gauge's readings, a value per line of the feed.
#[derive(Debug, Clone, PartialEq)]
pub struct GaugeColumn {
    /// The gauge's name (a key of the lines' `gauges`).
    pub name: String,
    /// Its value on each line; NaN where the line has no reading of it.
    pub value: Vec<f64>,
    /// Its σ on each line; NaN where the line does not give it (or has no reading).
    pub sigma: Vec<f64>,
}

/// The lines of a feed as columns, one entry per line (see the module doc).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Columns {
    /// `t_ns` of each line.
    pub t_ns: Vec<i64>,
    /// `seq` of each line.
    pub seq: Vec<u64>,
    /// `load_kN` of each line; NaN where absent.
    pub load_kn: Vec<f64>,
    /// `net_deflection_mm` of each line; NaN where absent.
    pub net_deflection_mm: Vec<f64>,
    /// The UTM link's state on each line.
    pub utm: Vec<UtmState>,
    /// The gauges, in order of first appearance (a line's own in name order).
    pub gauges: Vec<GaugeColumn>,
    /// Indices of the lines that carry a `resume` event (a resumed test's new segment).
    pub resumes: Vec<usize>,
}

impl Columns {
    /// Lines held.
    pub fn len(&self) -> usize {
        self.t_ns.len()
    }

    /// True when no line is held.
    pub fn is_empty(&self) -> bool {
        self.t_ns.is_empty()
    }

    /// `load_kN` of line `k`.
    pub fn load(&self, k: usize) -> Option<f64> {
        Some(self.load_kn[k]).filter(|p| !p.is_nan())
    }

    /// The column of gauge `name`.
    pub fn gauge(&self, name: &str) -> Option<&GaugeColumn> {
        self.gauges.iter().find(|g| g.name == name)
    }

    /// Appends line `l` (its values checked by the reader).
    pub(crate) fn push(&mut self, l: &FeedLine) {
        let k = self.len();
        self.t_ns.push(l.t_ns);
        self.seq.push(l.seq);
        self.load_kn.push(l.load_kn.unwrap_or(f64::NAN));
        self.net_deflection_mm.push(l.net_deflection_mm.unwrap_or(f64::NAN));
        self.utm.push(match l.utm.as_deref() {
            None => UtmState::Absent,
            Some("down") => UtmState::Down,
            Some(_) => UtmState::Up,
        });
        for name in l.gauges.keys() {
            if self.gauge(name).is_none() {
                self.gauges.push(GaugeColumn { name: name.clone(), value: vec![f64::NAN; k], sigma: vec![f64::NAN; k] });
            }
        }
        for c in &mut self.gauges {
            let (v, s) = l.gauges.get(&c.name).map_or((f64::NAN, f64::NAN), |g| (g.value, g.sigma));
            c.value.push(v);
            c.sigma.push(s);
        }
        if crate::feed_reader::resumes(l) {
            self.resumes.push(k);
        }
    }

    /// Gives back the lists' spare room (a long feed's columns grow by doubling).
    pub(crate) fn shrink_to_fit(&mut self) {
        self.t_ns.shrink_to_fit();
        self.seq.shrink_to_fit();
        self.load_kn.shrink_to_fit();
        self.net_deflection_mm.shrink_to_fit();
        self.utm.shrink_to_fit();
        for g in &mut self.gauges {
            g.value.shrink_to_fit();
            g.sigma.shrink_to_fit();
        }
        self.resumes.shrink_to_fit();
    }
}

/// What a second read of a line gives (see [`crate::Feed::for_each_line`]): what the report
/// needs of a line but does not hold.
#[derive(Debug, Clone, Default, serde::Deserialize)]
pub struct LineTags {
    /// The line's `seq` (checked against the held one).
    pub seq: u64,
    /// The line's `t_ns` (checked against the held one).
    pub t_ns: i64,
    /// UTM stroke, mm.
    #[serde(default)]
    pub stroke_mm: Option<f64>,
    /// The specimen tags solved.
    #[serde(default)]
    pub tags: Vec<FeedTag>,
}

impl crate::Feed {
    /// Reads the held lines again, in order, from the file (or text) they were read from,
    /// and gives each with its index to `f`: what the report needs of a line but does not
    /// hold (the tags, the stroke). A line whose `seq` or `t_ns` is not the one read the first
    /// time, or a file that ends before the last, is an error naming the line: the feed changed
    /// since it was read.
    pub fn for_each_line(&self, mut f: impl FnMut(usize, &LineTags)) -> Result<(), ReportError> {
        let mut k = 0;
        let mut visit = |no: usize, text: &str| -> Result<bool, ReportError> {
            if self.line_numbers.get(k) != Some(&no) {
                return Ok(k < self.line_numbers.len());
            }
            let changed = |what: String| ReportError::BadLine {
                path: self.path.clone(),
                line: no,
                message: format!("the feed changed while its report was made: {what}"),
            };
            let l: LineTags = serde_json::from_str(text).map_err(|e| changed(e.to_string()))?;
            if l.seq != self.columns.seq[k] || l.t_ns != self.columns.t_ns[k] {
                return Err(changed(format!(
                    "seq {} at t_ns {} was seq {} at t_ns {}",
                    l.seq, l.t_ns, self.columns.seq[k], self.columns.t_ns[k]
                )));
            }
            f(k, &l);
            k += 1;
            Ok(k < self.line_numbers.len())
        };
        let first = self.line_numbers.first().copied().unwrap_or(1);
        match &self.source {
            Source::Text { text, offset } => {
                for (i, line) in text[*offset..].lines().enumerate() {
                    if !visit(first + i, line)? {
                        break;
                    }
                }
            }
            Source::File { offset } => {
                use std::io::{BufRead, Read};
                let io =
                    |e: std::io::Error| ReportError::Io { path: self.path.clone(), message: format!("cannot read the feed again: {e}") };
                // A rotated run's files are read again as one stream, as the first read did.
                let mut reader = tagdeflect_core::feed_rotation::open_feed_set(&self.path).map_err(io)?;
                std::io::copy(&mut (&mut reader).take(*offset), &mut std::io::sink()).map_err(io)?;
                let mut buf = Vec::new();
                for no in first.. {
                    buf.clear();
                    if reader.read_until(b'\n', &mut buf).map_err(io)? == 0 {
                        break;
                    }
                    let text = std::str::from_utf8(&buf).unwrap_or("");
                    let text = text.strip_suffix('\n').map_or(text, |t| t.strip_suffix('\r').unwrap_or(t));
                    if !visit(no, text)? {
                        break;
                    }
                }
            }
        }
        if k < self.line_numbers.len() {
            return Err(ReportError::BadLine {
                path: self.path.clone(),
                line: self.line_numbers[k],
                message: "the feed changed while its report was made: the line is gone".into(),
            });
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use crate::{Feed, ReadOptions};

    /// The tags read again are the file's; a file changed after the first read (a line's
    /// seq, or lines gone) is an error naming the line, never another feed's tags.
    #[test]
    fn the_lines_read_again_are_the_ones_held_or_an_error_naming_the_line() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("f.jsonl");
        let line = |seq: u64, z: f64| {
            format!(
                "{{\"seq\":{seq},\"t_ns\":{},\"load_kN\":1.0,\"stroke_mm\":{z},\"tags\":[{{\"id\":7,\"pos_mm\":[0,0,0],\"disp_mm\":[0,0,{z}]}}]}}\n",
                10 + seq
            )
        };
        let text = [line(0, 0.5), "\n".into(), line(1, 1.5), line(2, 2.5)].concat();
        std::fs::write(&path, &text).unwrap();
        let feed = Feed::read_runs(&path, &ReadOptions::default()).unwrap().remove(0);
        assert_eq!(feed.line_numbers, vec![1, 3, 4], "the blank line skipped");
        let mut got = Vec::new();
        feed.for_each_line(|k, l| got.push((k, l.seq, l.stroke_mm, l.tags[0].disp_mm[2]))).unwrap();
        assert_eq!(got, vec![(0, 0, Some(0.5), 0.5), (1, 1, Some(1.5), 1.5), (2, 2, Some(2.5), 2.5)]);

        std::fs::write(&path, [line(0, 0.5), "\n".into(), line(5, 1.5), line(2, 2.5)].concat()).unwrap();
        let e = feed.for_each_line(|_, _| {}).unwrap_err().to_string();
        assert!(e.contains("f.jsonl:3:") && e.contains("the feed changed while its report was made: seq 5"), "{e}");
        std::fs::write(&path, [line(0, 0.5), "\n".into(), line(1, 1.5)].concat()).unwrap();
        let e = feed.for_each_line(|_, _| {}).unwrap_err().to_string();
        assert!(e.contains("f.jsonl:4:") && e.contains("the line is gone"), "{e}");
    }
}
