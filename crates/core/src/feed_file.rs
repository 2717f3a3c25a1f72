//! The feed writer: JSON lines to stdout or appended to a file.
//!
//! A file output is a [`LineFile`]: each line is one write; a failed or partial write
//! (disk full) is cut back to the last complete line, so the file never holds a partial
//! line in its middle; a partial last line left by a crash is repaired when the file is
//! reopened. Lines that cannot be written are held back (at most [`BACKLOG_LINES`], the
//! oldest dropped and counted beyond that) and written, in order, once the output works
//! again; retries back off from [`RETRY_MIN`] to [`RETRY_MAX`]. Only a closed stdout pipe
//! (nobody reads any more) turns an output off for good. Durability: `fdatasync` at most
//! once per second while lines flow, and at shutdown (see [`crate::linefile`]).
//!
//! The run's feed file rotates ([`FeedWriter::append_rotating`], [`crate::feed_rotation`]):
//! before a line that would take the file past its size limit (or the first line of a new UTC
//! day) the file — whole lines only, synced — is renamed and a new one started under the
//! configured name. A rotation is part of writing a line: when the new file cannot be made or
//! written (disk full), the line and those after it are held back as any other failing write.

use std::collections::VecDeque;
use std::io::{self, Write};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use crate::backoff::Backoff;
use crate::feed::FeedLine;
use crate::feed_rotation::{self, FeedRotation};
use crate::linefile::{LineFile, LineTarget};

/// Lines held back while an output fails; beyond that the oldest are dropped (counted).
pub const BACKLOG_LINES: usize = 10_000;
/// First retry this long after a failure; doubled after each failed retry.
pub const RETRY_MIN: Duration = Duration::from_millis(500);
/// Longest wait between retries.
pub const RETRY_MAX: Duration = Duration::from_secs(30);

/// State of a sink, as reported in the feed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SinkState {
    /// Writing.
    Ok,
    /// Failing; retried with backoff.
    Failing,
    /// Off for good (e.g. nobody reads stdout any more).
    Off,
}

impl SinkState {
    /// `"ok"`, `"failing"` or `"off"`.
    pub fn as_str(self) -> &'static str {
        match self {
            SinkState::Ok => "ok",
            SinkState::Failing => "failing",
            SinkState::Off => "off",
        }
    }
}

enum Out {
    File(LineFile),
    /// Between a rotation and the new current file (not made yet: retried as a failed write).
    Rotated,
    Stream(Box<dyn Write + Send>),
    Off,
}

/// A clock of UTC times (tests set their own).
pub type UtcClock = Box<dyn Fn() -> chrono::DateTime<chrono::Utc> + Send>;

/// The rotation state of a file output.
struct Rotator {
    path: PathBuf,
    cfg: FeedRotation,
    /// The UTC day of the current file's first line.
    day: chrono::NaiveDate,
    /// A failed rename is retried after this, or earlier at the next cut by size.
    retry_after: Option<Instant>,
    /// The length at which a file whose rename failed is next due by size.
    retry_at_len: Option<u64>,
    /// Renames failed since the last one that worked (the first is logged, the others not).
    failed_tries: u32,
    now: UtcClock,
}

/// A failed rename (the folder read-only, ...) is retried after this, or at the next cut by
/// size (another `max_mb` written) if that comes first; lines go on into the current file
/// meanwhile.
const RENAME_RETRY: Duration = Duration::from_secs(60);

/// Writes feed lines to one destination; see the module docs.
pub struct FeedWriter {
    target: String,
    out: Out,
    written: u64,
    backlog: VecDeque<String>,
    dropped: u64,
    failing_since: Option<Instant>,
    next_retry: Instant,
    backoff: Backoff,
    rotator: Option<Rotator>,
}

impl FeedWriter {
    fn with_out(target: String, out: Out) -> Self {
        Self {
            target,
            out,
            written: 0,
            backlog: VecDeque::new(),
            dropped: 0,
            failing_since: None,
            next_retry: Instant::now(),
            backoff: Backoff::new(RETRY_MIN, RETRY_MAX),
            rotator: None,
        }
    }

    /// Standard output.
    pub fn stdout() -> Self {
        Self::with_out("stdout".into(), Out::Stream(Box::new(io::stdout())))
    }

    /// Appends to a file (created if absent, a partial last line repaired); `-` means stdout.
    pub fn append(path: &Path) -> io::Result<Self> {
        if path == Path::new("-") {
            return Ok(Self::stdout());
        }
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir)?;
        }
        let (f, _cut) = LineFile::open_append(path)?;
        Ok(Self::with_out(path.display().to_string(), Out::File(f)))
    }

    /// [`FeedWriter::append`] with rotation (`[output.feed_rotation]`; see the module docs).
    /// A path that is not a regular file (`-`, `/dev/full`) is never rotated.
    pub fn append_rotating(path: &Path, cfg: &FeedRotation) -> io::Result<Self> {
        Self::append_rotating_at(path, cfg, Box::new(chrono::Utc::now))
    }

    /// [`FeedWriter::append_rotating`] with the UTC clock given (tests of the daily cut).
    pub fn append_rotating_at(path: &Path, cfg: &FeedRotation, now: UtcClock) -> io::Result<Self> {
        let mut w = Self::append(path)?;
        let meta = std::fs::metadata(path).ok().filter(|m| m.is_file());
        if let (Some(meta), true) = (meta, cfg.rotates()) {
            // A file left by an earlier run is of the day it was last written.
            let modified = meta.modified().ok().filter(|_| meta.len() > 0).map(chrono::DateTime::<chrono::Utc>::from);
            let day = feed_rotation::day_of(modified.unwrap_or_else(&now));
            w.rotator = Some(Rotator {
                path: path.to_path_buf(),
                cfg: cfg.clone(),
                day,
                retry_after: None,
                retry_at_len: None,
                failed_tries: 0,
                now,
            });
        }
        Ok(w)
    }

    /// Any writer (tests, in-memory sinks); written with `write_all` + `flush` per line.
    pub fn from_writer(name: &str, w: Box<dyn Write + Send>) -> Self {
        Self::with_out(name.into(), Out::Stream(w))
    }

    /// A line file over any [`LineTarget`] currently `len` bytes long (fault injection).
    pub fn from_target(name: &str, target: Box<dyn LineTarget>, len: u64) -> Self {
        Self::with_out(name.into(), Out::File(LineFile::new(target, len)))
    }

    /// Sets the retry backoff (first wait, longest wait).
    pub fn with_backoff(mut self, min: Duration, max: Duration) -> Self {
        self.backoff = Backoff::new(min, max);
        self
    }

    /// Where the lines go.
    pub fn target(&self) -> &str {
        &self.target
    }

    /// Lines written so far.
    pub fn written(&self) -> u64 {
        self.written
    }

    /// Lines dropped so far (backlog overflow while failing, or written after the output was off).
    pub fn dropped(&self) -> u64 {
        self.dropped
    }

    /// Lines held back, waiting for the output to work again.
    pub fn pending(&self) -> usize {
        self.backlog.len()
    }

    /// True unless the sink is off for good.
    pub fn is_open(&self) -> bool {
        !matches!(self.out, Out::Off)
    }

    /// The sink's state.
    pub fn state(&self) -> SinkState {
        match (&self.out, self.failing_since) {
            (Out::Off, _) => SinkState::Off,
            (_, Some(_)) => SinkState::Failing,
            _ => SinkState::Ok,
        }
    }

    /// Queues one line and writes every held-back line. Returns an error only when the
    /// output starts failing (once per outage) or turns off; while it fails, lines are held
    /// back and retried with backoff.
    pub fn write(&mut self, line: &FeedLine) -> io::Result<()> {
        self.write_text(line.to_json())
    }

    /// [`FeedWriter::write`] of a line already made (any JSON text without its newline: a
    /// test's UTM samples).
    pub fn write_text(&mut self, mut text: String) -> io::Result<()> {
        if matches!(self.out, Out::Off) {
            self.dropped += 1;
            return Ok(());
        }
        text.push('\n');
        self.backlog.push_back(text);
        if self.backlog.len() > BACKLOG_LINES {
            self.backlog.pop_front();
            self.dropped += 1;
        }
        if self.failing_since.is_some() && Instant::now() < self.next_retry {
            return Ok(());
        }
        self.drain()
    }

    /// Writes the backlog; see [`FeedWriter::write`].
    fn drain(&mut self) -> io::Result<()> {
        if let Err(e) = self.write_backlog() {
            return self.failed(e);
        }
        if let Some(since) = self.failing_since.take() {
            tracing::info!(output = %self.target, after_s = since.elapsed().as_secs(), dropped = self.dropped, "feed output writes again");
            self.backoff.reset();
        }
        if let Out::File(f) = &mut self.out {
            if let Err(e) = f.sync_if_due() {
                tracing::warn!(output = %self.target, "fdatasync failed: {e}");
            }
        }
        Ok(())
    }

    /// Writes the held-back lines in order until one fails (its error).
    fn write_backlog(&mut self) -> io::Result<()> {
        while let Some(len) = self.backlog.front().map(String::len) {
            self.rotate_if_due(len as u64)?;
            let text = self.backlog.front().expect("a line");
            match &mut self.out {
                Out::File(f) => f.write_line(text.as_bytes())?,
                Out::Rotated => unreachable!("rotate_if_due opens the new file"),
                Out::Stream(w) => w.write_all(text.as_bytes()).and_then(|_| w.flush())?,
                Out::Off => return Ok(()),
            }
            self.backlog.pop_front();
            self.written += 1;
        }
        Ok(())
    }

    fn failed(&mut self, e: io::Error) -> io::Result<()> {
        if e.kind() == io::ErrorKind::BrokenPipe && matches!(self.out, Out::Stream(_)) {
            self.out = Out::Off;
            self.dropped += self.backlog.len() as u64;
            self.backlog.clear();
            self.failing_since = None;
            return Err(io::Error::new(
                e.kind(),
                format!("feed output {}: {e}; nobody reads it any more, it is off, the others go on", self.target),
            ));
        }
        let wait = self.backoff.next_delay();
        self.next_retry = Instant::now() + wait;
        if self.failing_since.is_none() {
            self.failing_since = Some(Instant::now());
            return Err(io::Error::new(
                e.kind(),
                format!(
                    "feed output {}: {e}; lines are held back (up to {BACKLOG_LINES}) and retried, first in {:.1} s; the others go on",
                    self.target,
                    wait.as_secs_f64()
                ),
            ));
        }
        tracing::debug!(output = %self.target, retry_in_s = wait.as_secs_f64(), "feed output still failing: {e}");
        Ok(())
    }

    /// Writes what is held back now (whatever the backoff) and syncs; an error when lines stay
    /// held back (they are kept for a later try) or the sync fails. Nothing is dropped.
    pub fn flush_held(&mut self) -> io::Result<()> {
        if let Err(e) = self.write_backlog() {
            let held = self.backlog.len();
            let _ = self.failed(io::Error::new(e.kind(), e.to_string()));
            return Err(io::Error::new(e.kind(), format!("{}: {e}; {held} line(s) held back, not written yet", self.target)));
        }
        self.drain()?;
        match &mut self.out {
            Out::File(f) => f.sync(),
            Out::Stream(w) => w.flush(),
            Out::Off | Out::Rotated => Ok(()),
        }
    }

    /// Writes what is held back (one last try) and syncs (shutdown).
    pub fn finish(&mut self) -> io::Result<()> {
        if !self.backlog.is_empty() {
            let _ = self.drain();
        }
        if !self.backlog.is_empty() {
            let n = self.backlog.len() as u64;
            self.dropped += n;
            self.backlog.clear();
            tracing::error!(output = %self.target, lines = n, "feed output: lines could not be written before shutdown");
        }
        match &mut self.out {
            Out::File(f) => f.sync(),
            Out::Stream(w) => w.flush(),
            Out::Off | Out::Rotated => Ok(()),
        }
    }

    /// Before a line of `add` bytes: rotates the current file when it is due, and makes the new
    /// current file when a rotation left none (an error: the line is held back and retried).
    fn rotate_if_due(&mut self, add: u64) -> io::Result<()> {
        let Some(r) = &mut self.rotator else { return Ok(()) };
        if matches!(self.out, Out::Rotated) {
            let (f, _) = LineFile::open_append(&r.path)?;
            self.out = Out::File(f);
            r.day = feed_rotation::day_of((r.now)());
            return Ok(());
        }
        let Out::File(f) = &mut self.out else { return Ok(()) };
        let now = (r.now)();
        let full = r.cfg.max_bytes().is_some_and(|m| f.len() + add > m);
        let new_day = r.cfg.daily && feed_rotation::day_of(now) != r.day;
        let next_cut = r.retry_at_len.is_some_and(|l| f.len() + add > l);
        let waiting = r.retry_after.is_some_and(|t| Instant::now() < t) && !next_cut;
        if f.is_empty() || !(full || new_day) || waiting {
            if f.is_empty() {
                r.day = feed_rotation::day_of(now);
            }
            return Ok(());
        }
        f.settle()?;
        let index = feed_rotation::feed_segments(&r.path)?.last().map_or(1, |s| s.index);
        let to = feed_rotation::rotated_path(&r.path, index, now);
        if let Err(e) = rename_new(&r.path, &to) {
            r.failed(&self.target, &to, f.len(), e);
            return Ok(());
        }
        if r.failed_tries > 0 {
            tracing::info!(output = %self.target, to = %to.display(), bytes = f.len(), "feed file rotated after {} failed tries", r.failed_tries);
        } else {
            tracing::info!(output = %self.target, to = %to.display(), bytes = f.len(), "feed file rotated");
        }
        (r.retry_after, r.retry_at_len, r.failed_tries) = (None, None, 0);
        self.out = Out::Rotated;
        sync_folder(&r.path);
        match feed_rotation::prune(&r.path, &r.cfg) {
            Ok(gone) => gone.iter().for_each(|p| tracing::info!(file = %p.display(), "rotated feed file deleted (keep_files/keep_gb)")),
            Err(e) => tracing::warn!(output = %self.target, "rotated feed files not pruned: {e}"),
        }
        self.rotate_if_due(add)
    }
}

impl Rotator {
    /// A rename that failed: said once (the first of an outage), retried at the next cut by
    /// size or after [`RENAME_RETRY`]; the lines go on into the current file meanwhile.
    fn failed(&mut self, target: &str, to: &Path, len: u64, e: io::Error) {
        if self.failed_tries == 0 {
            tracing::warn!(output = %target, to = %to.display(), "feed file not rotated ({e}); lines go on into it, the rotation is tried again at the next cut (another max_mb, or in {} s); said once", RENAME_RETRY.as_secs());
        } else {
            tracing::debug!(output = %target, to = %to.display(), tries = self.failed_tries + 1, "feed file still not rotated: {e}");
        }
        self.failed_tries += 1;
        self.retry_after = Some(Instant::now() + RENAME_RETRY);
        self.retry_at_len = self.cfg.max_bytes().map(|m| len + m);
    }
}

/// Renames `from` to `to` unless `to` exists (then `AlreadyExists`, both left as they were):
/// a rotated file is never replaced, even by a second writer of the same feed that picked the
/// same number. `renameat2(RENAME_NOREPLACE)`; where the filesystem lacks it, a check then a
/// rename.
pub(crate) fn rename_new(from: &Path, to: &Path) -> io::Result<()> {
    use rustix::fs::{renameat_with, RenameFlags, CWD};
    let e = match renameat_with(CWD, from, CWD, to, RenameFlags::NOREPLACE) {
        Ok(()) => return Ok(()),
        Err(e) => io::Error::from(e),
    };
    if !matches!(e.raw_os_error(), Some(libc::EINVAL) | Some(libc::ENOSYS)) {
        return Err(e);
    }
    if std::fs::symlink_metadata(to).is_ok() {
        return Err(io::Error::new(io::ErrorKind::AlreadyExists, format!("{} exists", to.display())));
    }
    std::fs::rename(from, to)
}

/// Makes a rename in the folder of `path` durable (best effort).
fn sync_folder(path: &Path) {
    let dir = path.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(Path::new("."));
    if let Ok(d) = std::fs::File::open(dir) {
        let _ = d.sync_all();
    }
}

impl Drop for FeedWriter {
    fn drop(&mut self) {
        let _ = self.finish();
    }
}

/// Path of the feed file for `[output] feed`, or `None` for stdout.
pub fn feed_path(spec: &str) -> Option<PathBuf> {
    (spec != "-").then(|| PathBuf::from(spec))
}
