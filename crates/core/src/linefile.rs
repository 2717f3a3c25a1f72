//! An append-only file of whole lines that survives a full disk and a crash.
//!
//! - Each line is written with **one** `write` of the whole line. When that write fails or
//!   writes only part of the line (ENOSPC in the middle of a line), the file is truncated
//!   back to the end of the last complete line before anything else is written, so a
//!   partial line never ends up in the middle of the file.
//! - Opening an existing file repairs a partial last line (what a crash or power cut in
//!   the middle of a write leaves): it is cut off and the repair is logged.
//! - Durability: [`LineFile::sync_if_due`] calls `fdatasync` at most once per
//!   [`SYNC_INTERVAL`] when lines were written since the last sync, and [`LineFile::sync`]
//!   (called at shutdown and on drop) syncs what is left. A power cut loses at most the
//!   lines written in the last [`SYNC_INTERVAL`] before the cut (more only when the disk
//!   itself lies about its cache).
//!
//! The file is anything implementing [`LineTarget`] (a real [`File`], or a test wrapper
//! that fails on cue).

use std::fs::{File, OpenOptions};
use std::io::{self, Read, Seek, SeekFrom, Write};
use std::path::Path;
use std::time::{Duration, Instant};

/// At most one `fdatasync` per this interval while lines are being written.
pub(crate) const SYNC_INTERVAL: Duration = Duration::from_secs(1);

/// What a [`LineFile`] needs from the file underneath.
pub trait LineTarget: Send {
    /// One write call (may write less than `buf`, like [`Write::write`]).
    fn write_once(&mut self, buf: &[u8]) -> io::Result<usize>;
    /// Cuts the file to `len` bytes; later writes append at `len`.
    fn truncate(&mut self, len: u64) -> io::Result<()>;
    /// Makes the data written so far durable (`fdatasync`).
    fn sync_data(&mut self) -> io::Result<()>;
}

impl LineTarget for File {
    fn write_once(&mut self, buf: &[u8]) -> io::Result<usize> {
        loop {
            match Write::write(self, buf) {
                Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
                r => return r,
            }
        }
    }
    fn truncate(&mut self, len: u64) -> io::Result<()> {
        self.set_len(len)?;
        // In append mode writes go to the end anyway; the seek keeps non-append files right.
        self.seek(SeekFrom::Start(len)).map(|_| ())
    }
    fn sync_data(&mut self) -> io::Result<()> {
        File::sync_data(self)
    }
}

/// A file of complete lines; see the module docs.
pub struct LineFile {
    target: Box<dyn LineTarget>,
    /// Length of the file up to the end of the last complete line.
    good_len: u64,
    /// A failed write left bytes after `good_len` that are not cut off yet.
    dirty_tail: bool,
    unsynced: bool,
    last_sync: Instant,
}

impl LineFile {
    /// Opens `path` for appending (created if absent), repairing a partial last line.
    /// Returns the file and the number of bytes cut off (0 when the file was sound).
    ///
    /// A folder, a FIFO, a socket or a block device is refused here, at open, and so is a
    /// regular file that cannot be synced — a file of a kernel filesystem such as
    /// `/proc/version`, which opens and then fails every write — rather than losing every line
    /// later. A character device (`/dev/full`, a serial line) is taken as it is.
    pub fn open_append(path: &Path) -> io::Result<(LineFile, u64)> {
        use std::os::unix::fs::FileTypeExt;
        let existing = std::fs::metadata(path).ok();
        if let Some(m) = &existing {
            let t = m.file_type();
            if !t.is_file() && !t.is_char_device() {
                return Err(io::Error::new(io::ErrorKind::InvalidInput, "not a regular file (a folder, FIFO, socket or block device)"));
            }
        }
        let mut f = OpenOptions::new().create(true).read(true).append(true).open(path)?;
        if existing.as_ref().is_none_or(|m| m.is_file()) {
            f.sync_all().map_err(|e| io::Error::new(e.kind(), format!("the file does not take writes (sync: {e})")))?;
        }
        let len = f.metadata()?.len();
        let good = complete_prefix_len(&mut f, len)?;
        if good < len {
            f.set_len(good)?;
            tracing::warn!(file = %path.display(), cut_bytes = len - good, "partial last line removed (left by a crash or a full disk)");
        }
        Ok((LineFile::new(Box::new(f), good), len - good))
    }

    /// A line file over any target whose current length is `len` (ending in a newline or empty).
    pub fn new(target: Box<dyn LineTarget>, len: u64) -> LineFile {
        LineFile { target, good_len: len, dirty_tail: false, unsynced: false, last_sync: Instant::now() }
    }

    /// Bytes of complete lines in the file.
    pub fn len(&self) -> u64 {
        self.good_len
    }

    /// True when the file holds no complete line.
    pub fn is_empty(&self) -> bool {
        self.good_len == 0
    }

    /// Appends one line (`line` must end with `\n`) with a single write. On an error or a
    /// short write, the file is cut back to its last complete line and the error returned;
    /// the caller may retry the same line later.
    pub fn write_line(&mut self, line: &[u8]) -> io::Result<()> {
        debug_assert!(line.ends_with(b"\n"));
        if self.dirty_tail {
            self.target.truncate(self.good_len)?;
            self.dirty_tail = false;
        }
        match self.target.write_once(line) {
            Ok(n) if n == line.len() => {
                self.good_len += n as u64;
                self.unsynced = true;
                Ok(())
            }
            Ok(n) => {
                self.cut_back();
                Err(io::Error::new(
                    io::ErrorKind::WriteZero,
                    format!("short write ({n} of {} bytes; cut back to the last complete line)", line.len()),
                ))
            }
            Err(e) => {
                self.cut_back();
                Err(e)
            }
        }
    }

    fn cut_back(&mut self) {
        // If even the truncation fails, it is retried before the next write.
        self.dirty_tail = self.target.truncate(self.good_len).is_err();
    }

    /// `fdatasync` when lines were written and the last sync is [`SYNC_INTERVAL`] old.
    pub fn sync_if_due(&mut self) -> io::Result<()> {
        if self.unsynced && self.last_sync.elapsed() >= SYNC_INTERVAL {
            self.sync()
        } else {
            Ok(())
        }
    }

    /// Cuts off what a failed write left after the last complete line and syncs: the file then
    /// holds whole lines only, on disk (before it is renamed by a rotation).
    pub fn settle(&mut self) -> io::Result<()> {
        if self.dirty_tail {
            self.target.truncate(self.good_len)?;
            self.dirty_tail = false;
        }
        self.unsynced = true;
        self.sync()
    }

    /// `fdatasync` now (shutdown).
    pub fn sync(&mut self) -> io::Result<()> {
        self.last_sync = Instant::now();
        if !self.unsynced {
            return Ok(());
        }
        self.target.sync_data()?;
        self.unsynced = false;
        Ok(())
    }
}

impl Drop for LineFile {
    fn drop(&mut self) {
        if self.dirty_tail {
            let _ = self.target.truncate(self.good_len);
        }
        let _ = self.sync();
    }
}

/// Length of the longest prefix of the file (of length `len`) that ends with a newline
/// (or 0). Reads backwards from the end in blocks.
fn complete_prefix_len<R: Read + Seek>(f: &mut R, len: u64) -> io::Result<u64> {
    let mut end = len;
    let mut buf = [0u8; 4096];
    while end > 0 {
        let start = end.saturating_sub(buf.len() as u64);
        let n = (end - start) as usize;
        f.seek(SeekFrom::Start(start))?;
        f.read_exact(&mut buf[..n])?;
        if let Some(i) = buf[..n].iter().rposition(|&b| b == b'\n') {
            return Ok(start + i as u64 + 1);
        }
        end = start;
    }
    Ok(0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn complete_prefix() {
        let mut c = io::Cursor::new(b"a\nbb\nccc".to_vec());
        assert_eq!(complete_prefix_len(&mut c, 8).unwrap(), 5);
        let mut c = io::Cursor::new(b"a\nbb\n".to_vec());
        assert_eq!(complete_prefix_len(&mut c, 5).unwrap(), 5);
        let mut c = io::Cursor::new(vec![b'x'; 10000]);
        assert_eq!(complete_prefix_len(&mut c, 10000).unwrap(), 0);
        let mut v = vec![b'x'; 10000];
        v[10] = b'\n';
        let mut c = io::Cursor::new(v);
        assert_eq!(complete_prefix_len(&mut c, 10000).unwrap(), 11);
    }
}
