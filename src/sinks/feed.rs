//! The feed writer: JSON lines to stdout or appended to a file, flushed per line.

use std::fs::OpenOptions;
use std::io::{self, Write};
use std::path::{Path, PathBuf};

use crate::feed::FeedLine;

/// Writes feed lines to one destination, flushing each.
pub struct FeedWriter {
    target: String,
    out: Option<Box<dyn Write + Send>>,
    written: u64,
}

impl FeedWriter {
    /// Standard output.
    pub fn stdout() -> Self {
        Self { target: "stdout".into(), out: Some(Box::new(io::stdout())), written: 0 }
    }

    /// Appends to a file (created if absent); `-` means stdout.
    pub fn append(path: &Path) -> io::Result<Self> {
        if path == Path::new("-") {
            return Ok(Self::stdout());
        }
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir)?;
        }
        let f = OpenOptions::new().create(true).append(true).open(path)?;
        Ok(Self { target: path.display().to_string(), out: Some(Box::new(f)), written: 0 })
    }

    /// Any writer (tests, in-memory sinks).
    pub fn from_writer(name: &str, w: Box<dyn Write + Send>) -> Self {
        Self { target: name.into(), out: Some(w), written: 0 }
    }

    /// Where the lines go.
    pub fn target(&self) -> &str {
        &self.target
    }

    /// Lines written so far.
    pub fn written(&self) -> u64 {
        self.written
    }

    /// True while the sink still works.
    pub fn is_open(&self) -> bool {
        self.out.is_some()
    }

    /// Writes one line and flushes it. On an error (disk full, closed pipe) the sink is
    /// disabled and the error returned once; a partial line is never followed by more data.
    pub fn write(&mut self, line: &FeedLine) -> io::Result<()> {
        let Some(out) = self.out.as_mut() else { return Ok(()) };
        let mut text = line.to_json();
        text.push('\n');
        let res = out.write_all(text.as_bytes()).and_then(|_| out.flush());
        match res {
            Ok(()) => {
                self.written += 1;
                Ok(())
            }
            Err(e) => {
                self.out = None;
                Err(io::Error::new(e.kind(), format!("feed output {}: {e}; this output is disabled, the others go on", self.target)))
            }
        }
    }
}

/// Path of the feed file for `[output] feed`, or `None` for stdout.
pub fn feed_path(spec: &str) -> Option<PathBuf> {
    (spec != "-").then(|| PathBuf::from(spec))
}
