//! Reading a feed for the report: the lines as [`FeedLine`]s, the type the measurement
//! writes, which reads tolerantly (unknown fields ignored, extensions and what other writers
//! leave out optional; see [`tagdeflect_core::feed`]).

use std::io::Read;
use std::path::{Path, PathBuf};

use tagdeflect_core::feed::FeedLine;

use crate::ReportError;

/// A whole feed file.
#[derive(Debug, Clone)]
pub struct Feed {
    /// Where it was read from.
    pub path: PathBuf,
    /// The lines in time order.
    pub lines: Vec<FeedLine>,
    /// Warnings from reading (a truncated last line).
    pub warnings: Vec<String>,
}

impl Feed {
    /// Reads a feed (JSON Lines). A truncated last line (no newline, cut JSON — what a
    /// writer killed mid-line leaves) is skipped with a warning, as the recording reader
    /// does; any other bad line is an error naming the file and line.
    pub fn read(path: &Path) -> Result<Feed, ReportError> {
        let mut text = String::new();
        std::fs::File::open(path)
            .and_then(|mut f| f.read_to_string(&mut text))
            .map_err(|e| ReportError::Io { path: path.to_path_buf(), message: format!("cannot read the feed: {e}") })?;
        Self::parse(&text, path)
    }

    /// Parses feed text; `path` names the file in errors.
    fn parse(text: &str, path: &Path) -> Result<Feed, ReportError> {
        let ends_with_newline = text.ends_with('\n');
        let raw: Vec<&str> = text.lines().collect();
        let mut lines = Vec::with_capacity(raw.len());
        let mut warnings = Vec::new();
        for (i, line) in raw.iter().enumerate() {
            if line.trim().is_empty() {
                continue;
            }
            match serde_json::from_str::<FeedLine>(line) {
                Ok(r) => lines.push(r),
                Err(e) => {
                    if i + 1 == raw.len() && !ends_with_newline && e.is_eof() {
                        let msg = format!("{}:{}: truncated last line skipped", path.display(), i + 1);
                        tracing::warn!("{msg}");
                        warnings.push(msg);
                    } else {
                        return Err(ReportError::BadLine { path: path.to_path_buf(), line: i + 1, message: e.to_string() });
                    }
                }
            }
        }
        if lines.is_empty() {
            return Err(ReportError::BadLine { path: path.to_path_buf(), line: raw.len().max(1), message: "the feed has no lines".into() });
        }
        lines.sort_by_key(|l| l.t_ns);
        Ok(Feed { path: path.to_path_buf(), lines, warnings })
    }

    /// Gauge names in order of first appearance.
    pub(crate) fn gauge_names(&self) -> Vec<String> {
        let mut names: Vec<String> = Vec::new();
        for l in &self.lines {
            for k in l.gauges.keys() {
                if !names.contains(k) {
                    names.push(k.clone());
                }
            }
        }
        names
    }

    /// The unit of a gauge (from its first reading that names one).
    pub(crate) fn gauge_unit(&self, name: &str) -> Option<String> {
        self.lines.iter().find_map(|l| l.gauges.get(name).filter(|g| !g.unit.is_empty()).map(|g| g.unit.clone()))
    }

    /// Tag ids seen, sorted.
    pub(crate) fn tag_ids(&self) -> Vec<u32> {
        let mut ids: Vec<u32> = self.lines.iter().flat_map(|l| l.tags.iter().map(|t| t.id)).collect();
        ids.sort_unstable();
        ids.dedup();
        ids
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_lines_other_writers_leave_short_and_skips_a_truncated_last_one() {
        let text = concat!(
            r#"{"seq":1,"t_ns":20,"load_kN":1.5,"gauges":{"cmod":{"value":0.1}},"cameras":[{"name":"left"}],"drift_px":3}"#,
            "\n",
            r#"{"seq":0,"t_ns":10,"tags":[{"id":4,"pos_mm":[0,0,0],"disp_mm":[0,0,-1]}],"gauges":{"cmod":{"value":0.0,"sigma":0.002,"unit":"mm"}}}"#,
            "\n",
            r#"{"seq":2,"t_ns":30,"tags":[{"id""#,
        );
        let feed = Feed::parse(text, Path::new("f.jsonl")).unwrap();
        assert_eq!(feed.lines.iter().map(|l| l.seq).collect::<Vec<_>>(), vec![0, 1], "in time order, the cut line skipped");
        assert_eq!(feed.warnings, vec!["f.jsonl:3: truncated last line skipped".to_string()]);
        assert_eq!(feed.gauge_names(), vec!["cmod".to_string()]);
        assert_eq!(feed.gauge_unit("cmod").as_deref(), Some("mm"), "from the first line that names one");
        assert_eq!(feed.lines[1].gauges["cmod"].known_sigma(), None);
        assert!(feed.lines[1].cameras[0].frame && feed.lines[1].cameras[0].posed);
        assert_eq!(feed.tag_ids(), vec![4]);
        let e = Feed::parse("{\"seq\":0,\"t_ns\":\"soon\"}\n", Path::new("f.jsonl")).unwrap_err();
        assert!(e.to_string().starts_with("f.jsonl:1: not a feed line"), "{e}");
    }
}
