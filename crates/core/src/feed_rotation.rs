//! Rotation of the run's feed file (`[output] feed`, `[output.feed_rotation]`).
//!
//! The current file keeps its configured name (`feed.jsonl`); when it would grow past
//! `max_mb`, or when the UTC day changed since its first line (`daily`), it is renamed to
//! `<stem>.<NNNNNN>.<UTC time of the cut>.<ext>` — `feed.000003.2026-12-06T19-40-00Z.jsonl` —
//! and a new current file is started. `NNNNNN` counts the rotated files from 1 (it goes on
//! across restarts: one above the largest found), so the run's files in order are the rotated
//! ones by number, then the current one: [`feed_files`] lists them and is the one place that
//! does (the report, the archive's backfill and the MQTT read-back read through it). The cut
//! is always between two whole lines; nothing is deleted unless `keep_files` or `keep_gb` say so.

use std::io::{self, BufRead, Read};
use std::path::{Path, PathBuf};

use chrono::{DateTime, NaiveDate, Utc};
use serde::{Deserialize, Serialize};

use crate::Problem;

/// `[output.feed_rotation]`: when the feed file is rotated and what is kept.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FeedRotation {
    /// A file is rotated before it would grow past this many MB (10⁶ bytes); 0 = no size limit.
    pub max_mb: f64,
    /// A file is rotated at the first line of a new UTC day.
    pub daily: bool,
    /// Keep at most this many rotated files (the oldest deleted); none = keep all.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub keep_files: Option<usize>,
    /// Keep at most this many GB (10⁹ bytes) of rotated files (the oldest deleted); none = keep all.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub keep_gb: Option<f64>,
}

/// Default size limit: a day of 3 cameras at 30 fps with 9 tags (~6.8 GB) in four files.
pub const DEFAULT_MAX_MB: f64 = 2000.0;

impl Default for FeedRotation {
    fn default() -> Self {
        FeedRotation { max_mb: DEFAULT_MAX_MB, daily: true, keep_files: None, keep_gb: None }
    }
}

impl FeedRotation {
    /// True for the defaults (not written back into a recording's config).
    pub fn is_default(&self) -> bool {
        *self == FeedRotation::default()
    }

    /// The size limit in bytes, if any.
    pub fn max_bytes(&self) -> Option<u64> {
        (self.max_mb > 0.0).then_some((self.max_mb * 1e6) as u64)
    }

    /// True when the feed file is ever rotated.
    pub fn rotates(&self) -> bool {
        self.max_bytes().is_some() || self.daily
    }

    /// `max_mb` in 0 (off) or 0.001–10⁶, `keep_files` ≥ 1, `keep_gb` > 0; keys relative to
    /// `[output.feed_rotation]`.
    pub fn validate(&self) -> Result<(), Problem> {
        if !(self.max_mb == 0.0 || (0.001..=1e6).contains(&self.max_mb)) {
            return Err(Problem::new("max_mb", format!("{} MB: 0 (no size limit) or 0.001 to 1000000", self.max_mb)));
        }
        if self.keep_files == Some(0) {
            return Err(Problem::new("keep_files", "0: keep at least one rotated file (leave the key out to keep all)"));
        }
        if let Some(g) = self.keep_gb.filter(|g| !(g.is_finite() && *g > 0.0)) {
            return Err(Problem::new("keep_gb", format!("{g}: a size above 0 GB (leave the key out to keep all)")));
        }
        Ok(())
    }
}

/// One file of a run's feed: its number in order and its path.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FeedSegment {
    /// Rotated files count from 1; the current file has the number it will get when rotated.
    pub index: u64,
    /// Where it is.
    pub path: PathBuf,
}

/// Every file of the feed whose current file is `current`, in order: the rotated files by
/// number, then `current` (when it exists). A feed never rotated is `[current]`.
pub fn feed_segments(current: &Path) -> io::Result<Vec<FeedSegment>> {
    let mut out = rotated(current)?;
    let next = out.last().map_or(1, |s| s.index + 1);
    if current.exists() {
        out.push(FeedSegment { index: next, path: current.to_path_buf() });
    }
    Ok(out)
}

/// The paths of [`feed_segments`].
pub fn feed_files(current: &Path) -> io::Result<Vec<PathBuf>> {
    Ok(feed_segments(current)?.into_iter().map(|s| s.path).collect())
}

/// The feed's files ([`feed_files`]) read one after the other as one stream of lines.
pub fn open_feed_set(current: &Path) -> io::Result<Box<dyn BufRead + Send>> {
    let files = feed_files(current)?;
    if files.is_empty() {
        // The error of opening the missing current file.
        std::fs::File::open(current)?;
    }
    let mut reader: Box<dyn Read + Send> = Box::new(io::empty());
    for f in files {
        reader = Box::new(reader.chain(std::fs::File::open(&f)?));
    }
    Ok(Box::new(io::BufReader::with_capacity(1 << 16, reader)))
}

/// The rotated files of `current`, by number.
fn rotated(current: &Path) -> io::Result<Vec<FeedSegment>> {
    let dir = current.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(Path::new("."));
    let Some(name) = current.file_name().and_then(|n| n.to_str()) else { return Ok(Vec::new()) };
    let (stem, ext) = split_name(name);
    let entries = match std::fs::read_dir(dir) {
        Ok(e) => e,
        Err(e) if e.kind() == io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(e),
    };
    let mut out = Vec::new();
    for e in entries {
        let e = e?;
        if let Some(index) = e.file_name().to_str().and_then(|n| index_of(n, stem, ext)) {
            out.push(FeedSegment { index, path: dir.join(e.file_name()) });
        }
    }
    out.sort_by_key(|s| s.index);
    Ok(out)
}

/// `feed.jsonl` → (`feed`, `Some("jsonl")`).
fn split_name(name: &str) -> (&str, Option<&str>) {
    match name.rsplit_once('.') {
        Some((s, e)) if !s.is_empty() => (s, Some(e)),
        _ => (name, None),
    }
}

/// The number of a rotated file's name `<stem>.<NNNNNN>.<time>Z[.<ext>]`.
fn index_of(name: &str, stem: &str, ext: Option<&str>) -> Option<u64> {
    let rest = name.strip_prefix(stem)?.strip_prefix('.')?;
    let rest = match ext {
        Some(e) => rest.strip_suffix(e)?.strip_suffix('.')?,
        None => rest,
    };
    let (n, time) = rest.split_once('.')?;
    let time_ok = time.len() == 20 && time.ends_with('Z') && time.as_bytes()[10] == b'T';
    (n.len() >= 6 && n.bytes().all(|b| b.is_ascii_digit()) && time_ok).then(|| n.parse().ok()).flatten()
}

/// The name the current file gets as rotated file `index`, cut at `t`.
pub fn rotated_path(current: &Path, index: u64, t: DateTime<Utc>) -> PathBuf {
    let name = current.file_name().and_then(|n| n.to_str()).unwrap_or("feed.jsonl");
    let (stem, ext) = split_name(name);
    let time = t.format("%Y-%m-%dT%H-%M-%SZ");
    let rotated = match ext {
        Some(e) => format!("{stem}.{index:06}.{time}.{e}"),
        None => format!("{stem}.{index:06}.{time}"),
    };
    current.with_file_name(rotated)
}

/// Deletes the oldest rotated files beyond `keep_files` / `keep_gb` (none without them);
/// returns the files deleted.
pub fn prune(current: &Path, cfg: &FeedRotation) -> io::Result<Vec<PathBuf>> {
    if cfg.keep_files.is_none() && cfg.keep_gb.is_none() {
        return Ok(Vec::new());
    }
    let files = rotated(current)?;
    let sizes: Vec<u64> = files.iter().map(|s| std::fs::metadata(&s.path).map_or(0, |m| m.len())).collect();
    let mut total: u64 = sizes.iter().sum();
    let max_total = cfg.keep_gb.map(|g| (g * 1e9) as u64);
    let mut deleted = Vec::new();
    for (i, s) in files.iter().enumerate() {
        let left = files.len() - i;
        let over_count = cfg.keep_files.is_some_and(|k| left > k);
        let over_size = max_total.is_some_and(|m| total > m);
        if !over_count && !over_size {
            break;
        }
        std::fs::remove_file(&s.path)?;
        total -= sizes[i];
        deleted.push(s.path.clone());
    }
    Ok(deleted)
}

/// The UTC day of a time.
pub(crate) fn day_of(t: DateTime<Utc>) -> NaiveDate {
    t.date_naive()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rotated_files_are_listed_by_number_then_the_current_one() {
        let dir = tempfile::tempdir().unwrap();
        let cur = dir.path().join("feed.jsonl");
        let t = DateTime::parse_from_rfc3339("2026-12-06T19:40:00Z").unwrap().with_timezone(&Utc);
        let p10 = rotated_path(&cur, 10, t);
        assert_eq!(p10.file_name().unwrap(), "feed.000010.2026-12-06T19-40-00Z.jsonl");
        let p9 = rotated_path(&cur, 9, t + chrono::Duration::days(1));
        for (p, text) in [(&p10, "b\n"), (&p9, "a\n"), (&cur, "c\n")] {
            std::fs::write(p, text).unwrap();
        }
        std::fs::write(dir.path().join("feed.backup.jsonl"), "x\n").unwrap();
        std::fs::write(dir.path().join("other.000001.2026-12-06T19-40-00Z.jsonl"), "x\n").unwrap();
        let segs = feed_segments(&cur).unwrap();
        let idx: Vec<u64> = segs.iter().map(|s| s.index).collect();
        assert_eq!(idx, [9, 10, 11]);
        assert_eq!(segs[2].path, cur);
        let mut text = String::new();
        open_feed_set(&cur).unwrap().read_to_string(&mut text).unwrap();
        assert_eq!(text, "a\nb\nc\n");
        let cfg = FeedRotation { keep_files: Some(1), ..FeedRotation::default() };
        assert_eq!(prune(&cur, &cfg).unwrap(), vec![p9.clone()]);
        assert!(!p9.exists() && p10.exists() && cur.exists());
        assert!(prune(&cur, &FeedRotation::default()).unwrap().is_empty(), "nothing deleted by default");
    }

    /// A rotated file is never replaced: the rename to a name taken fails and leaves both.
    #[test]
    fn a_rotation_never_replaces_a_file_of_the_name_it_takes() {
        let dir = tempfile::tempdir().unwrap();
        let (cur, taken) = (dir.path().join("feed.jsonl"), dir.path().join("feed.000001.2026-12-06T19-40-00Z.jsonl"));
        std::fs::write(&cur, "new\n").unwrap();
        std::fs::write(&taken, "old\n").unwrap();
        let e = crate::feed_file::rename_new(&cur, &taken).unwrap_err();
        assert_eq!(e.kind(), std::io::ErrorKind::AlreadyExists, "{e}");
        assert_eq!(std::fs::read_to_string(&taken).unwrap(), "old\n");
        assert_eq!(std::fs::read_to_string(&cur).unwrap(), "new\n");
        let free = dir.path().join("feed.000002.2026-12-06T19-41-00Z.jsonl");
        crate::feed_file::rename_new(&cur, &free).unwrap();
        assert!(!cur.exists() && std::fs::read_to_string(&free).unwrap() == "new\n");
    }

    #[test]
    fn limits_are_checked() {
        assert!(FeedRotation::default().validate().is_ok());
        for bad in [
            FeedRotation { max_mb: -1.0, ..FeedRotation::default() },
            FeedRotation { keep_files: Some(0), ..FeedRotation::default() },
            FeedRotation { keep_gb: Some(f64::NAN), ..FeedRotation::default() },
        ] {
            assert!(bad.validate().is_err(), "{bad:?}");
        }
    }

    /// Lines written through rotations by size and by day: every line once, in order, each
    /// file whole lines and within its limit.
    #[test]
    fn a_writer_rotates_by_size_and_day_losing_no_line() {
        use crate::feed_file::FeedWriter;
        use std::sync::{Arc, Mutex};
        let dir = tempfile::tempdir().unwrap();
        let cur = dir.path().join("feed.jsonl");
        let t0 = DateTime::parse_from_rfc3339("2026-12-06T23:59:00Z").unwrap().with_timezone(&Utc);
        let clock = Arc::new(Mutex::new(t0));
        let c = clock.clone();
        let cfg = FeedRotation { max_mb: 0.001, ..FeedRotation::default() };
        let mut w = FeedWriter::append_rotating_at(&cur, &cfg, Box::new(move || *c.lock().unwrap())).unwrap();
        for i in 0..40 {
            if i == 30 {
                *clock.lock().unwrap() = t0 + chrono::Duration::minutes(2);
            }
            w.write_text(format!("{{\"seq\":{i},\"pad\":\"{}\"}}", "x".repeat(60))).unwrap();
        }
        w.finish().unwrap();
        let segs = feed_segments(&cur).unwrap();
        assert!(segs.len() >= 4, "{segs:?}");
        let mut seqs = Vec::new();
        for s in &segs {
            let text = std::fs::read_to_string(&s.path).unwrap();
            assert!(text.len() <= 1000 && text.ends_with('\n'), "{}: {} bytes", s.path.display(), text.len());
            seqs.extend(text.lines().map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap()["seq"].as_u64().unwrap()));
        }
        assert_eq!(seqs, (0..40).collect::<Vec<u64>>());
        // The new day's first line starts a file of its own.
        let first_of_day = segs.iter().find(|s| std::fs::read_to_string(&s.path).unwrap().starts_with("{\"seq\":30,")).unwrap();
        let name = first_of_day.path.file_name().unwrap().to_str().unwrap().to_string();
        assert!(name == "feed.jsonl" || name.contains("2026-12-07T"), "{name}");
    }
}
