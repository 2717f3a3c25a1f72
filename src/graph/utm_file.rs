//! Every UTM sample of a live run at the rate it was read, as SPEC `utm.jsonl` lines, beside
//! the run's feed: in the `[report]` folder of the run (the report takes its loads from it)
//! and beside an `[output] feed` file. One line per sample, written as it arrives (line
//! files: a crash leaves whole lines); a write that fails is logged once and retried with
//! the next sample, never stopping the run.

use std::path::{Path, PathBuf};
use std::sync::Mutex;

use tagdeflect_core::linefile::LineFile;
use tagdeflect_core::utm_sample::UtmSample;

/// The run's `utm.jsonl` files.
pub struct UtmFiles {
    files: Mutex<Vec<(PathBuf, LineFile, bool)>>,
}

impl UtmFiles {
    /// The files of a live run: `utm.jsonl` in `report_dir` and beside the `[output] feed`
    /// file (none for a replay or `record`, whose recording keeps its own).
    pub fn for_run(feed: Option<&str>, report_dir: Option<&Path>, live: bool) -> UtmFiles {
        let mut paths: Vec<PathBuf> = Vec::new();
        if live {
            if let Some(d) = report_dir {
                paths.push(d.join("utm.jsonl"));
            }
            if let Some(f) = feed.filter(|f| *f != "-") {
                let dir = Path::new(f).parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(Path::new("."));
                let p = dir.join("utm.jsonl");
                if !paths.contains(&p) {
                    paths.push(p);
                }
            }
        }
        let files = paths
            .into_iter()
            .filter_map(|p| match LineFile::open_append(&p) {
                Ok((f, _)) => Some((p, f, false)),
                Err(e) => {
                    tracing::error!("cannot write the UTM samples to {}: {e}", p.display());
                    None
                }
            })
            .collect();
        UtmFiles { files: Mutex::new(files) }
    }

    /// Writes one sample to every file.
    pub fn push(&self, s: &UtmSample) {
        let Ok(line) = serde_json::to_string(s) else { return };
        let mut line = line.into_bytes();
        line.push(b'\n');
        let mut files = self.files.lock().unwrap_or_else(|e| e.into_inner());
        for (p, f, failing) in files.iter_mut() {
            match f.write_line(&line).and_then(|_| f.sync_if_due()) {
                Ok(()) => *failing = false,
                Err(e) if !*failing => {
                    *failing = true;
                    tracing::error!("cannot write a UTM sample to {}: {e}", p.display());
                }
                Err(_) => {}
            }
        }
    }
}
