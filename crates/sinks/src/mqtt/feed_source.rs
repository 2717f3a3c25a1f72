//! This run's part of the feed file (`[output] feed`), read back for lines that left the
//! memory buffer before the archive confirmed them, by a task of its own, off the lock.

use std::path::{Path, PathBuf};

use std::sync::Arc;
use std::time::Duration;
use tagdeflect_core::feed_rotation::feed_segments;

use super::state::Shared;

/// Lines read back from the feed file (seq, bytes), and the largest seq the file holds so far.
type ReadBack = (Vec<(u64, Vec<u8>)>, Option<u64>);

/// This run's lines in the feed file (`[output] feed`): read back for lines that left the
/// memory buffer before the archive confirmed them. The file may be rotated meanwhile
/// (`[output.feed_rotation]`): the run's lines are read across its files in order
/// ([`tagdeflect_core::feed_rotation::feed_segments`]).
pub(super) struct FeedSource {
    /// The current feed file.
    pub(super) path: PathBuf,
    /// The number the current file had when the run started (it keeps it once rotated).
    pub(super) start_index: u64,
    /// Where this run's lines start in that file (its length when the run started: the feed
    /// file is appended to, earlier runs' lines come before).
    pub(super) start: u64,
    /// Where the last read stopped (file number, byte), and the seq of the last line read before it.
    pub(super) pos: (u64, u64),
    pub(super) last_seq: Option<u64>,
}

impl FeedSource {
    /// This run's part of the feed whose current file is `path`, from its present end.
    pub(super) fn new(path: &Path) -> FeedSource {
        let start = std::fs::metadata(path).map_or(0, |m| m.len());
        let start_index = current_index(path).unwrap_or(1);
        FeedSource { path: path.to_path_buf(), start_index, start, pos: (start_index, start), last_seq: None }
    }

    /// Reads the lines of `wanted` (ascending) from the files; also says the largest seq the
    /// files hold so far (a wanted seq below it that was not found is not in the feed).
    pub(super) fn read(&mut self, wanted: &[u64]) -> std::io::Result<ReadBack> {
        let Some(&first) = wanted.first() else { return Ok((Vec::new(), self.last_seq)) };
        if self.last_seq.is_none_or(|l| first <= l) {
            self.pos = (self.start_index, self.start);
            self.last_seq = None;
        }
        let want: std::collections::HashSet<u64> = wanted.iter().copied().collect();
        let mut out = Vec::new();
        let mut max_seen = self.last_seq;
        let from = self.pos.0;
        for seg in feed_segments(&self.path)?.into_iter().filter(|s| s.index >= from) {
            if seg.index > self.pos.0 {
                self.pos = (seg.index, 0);
            }
            let file = std::fs::File::open(&seg.path)?;
            if seg.path == self.path && current_index(&self.path)? != seg.index {
                break; // rotated between the listing and the open: read on next time
            }
            let done = self.read_file(file, &want, *wanted.last().expect("non-empty"), &mut out, &mut max_seen)?;
            if done {
                break;
            }
        }
        Ok((out, max_seen))
    }

    /// Reads one file from `self.pos`; true when the last wanted seq was reached.
    fn read_file(
        &mut self,
        file: std::fs::File,
        want: &std::collections::HashSet<u64>,
        last_wanted: u64,
        out: &mut Vec<(u64, Vec<u8>)>,
        max_seen: &mut Option<u64>,
    ) -> std::io::Result<bool> {
        use std::io::{BufRead, Seek, SeekFrom};
        #[derive(serde::Deserialize)]
        struct SeqOnly {
            seq: u64,
        }
        let mut f = std::io::BufReader::new(file);
        f.seek(SeekFrom::Start(self.pos.1))?;
        let mut buf = Vec::new();
        loop {
            buf.clear();
            let n = f.read_until(b'\n', &mut buf)?;
            if n == 0 || buf.last() != Some(&b'\n') {
                return Ok(false); // the end, or a line still being written
            }
            let line = &buf[..buf.len() - 1];
            self.pos.1 += n as u64;
            let Ok(SeqOnly { seq }) = serde_json::from_slice::<SeqOnly>(line) else { continue };
            *max_seen = Some(max_seen.map_or(seq, |m| m.max(seq)));
            if want.contains(&seq) {
                out.push((seq, line.to_vec()));
            }
            self.last_seq = Some(seq);
            if seq >= last_wanted {
                return Ok(true);
            }
        }
    }
}

/// The number of the current feed file (one above the last rotated one).
fn current_index(path: &Path) -> std::io::Result<u64> {
    let segs = feed_segments(path)?;
    let rotated_last = segs.iter().filter(|s| s.path != path).map(|s| s.index).max();
    Ok(rotated_last.map_or(1, |i| i + 1))
}

/// Reads lines the memory no longer holds back from the feed file when [`Shared::pump`]
/// asks, a window at a time, off the lock.
pub(super) async fn load_loop(shared: Arc<Shared>) {
    loop {
        shared.load.notified().await;
        loop {
            let wanted: Vec<u64> = {
                let mut st = shared.state.lock().expect("mqtt state");
                if !st.want_load {
                    break;
                }
                st.want_load = false;
                let mut w = Vec::new();
                for (a, b) in st.todo.iter() {
                    for seq in a..=b {
                        if !st.mem.contains_key(&seq) && !st.loaded.contains_key(&seq) {
                            w.push(seq);
                        }
                        if w.len() >= shared.window {
                            break;
                        }
                    }
                    if w.len() >= shared.window {
                        break;
                    }
                }
                w
            };
            if wanted.is_empty() {
                break;
            }
            let sh = shared.clone();
            let w = wanted.clone();
            let read =
                tokio::task::spawn_blocking(move || sh.feed.as_ref().expect("a feed file").lock().expect("feed source").read(&w)).await;
            // How long to wait before trying again (nothing found yet, or a read error).
            let retry_in = {
                let mut st = shared.state.lock().expect("mqtt state");
                let retry = match read {
                    Ok(Ok((lines, max_seen))) => {
                        let found: std::collections::HashSet<u64> = lines.iter().map(|l| l.0).collect();
                        for (seq, bytes) in lines {
                            if st.todo.contains(seq) {
                                st.loaded.insert(seq, bytes);
                            }
                        }
                        // Not in the file though the file went past it: the feed file lost it.
                        let mut lost = 0;
                        for seq in wanted.iter().filter(|s| !found.contains(s) && max_seen.is_some_and(|m| m > **s)) {
                            if st.todo.contains(*seq) {
                                shared.forget(&mut st, *seq);
                                lost += 1;
                            }
                        }
                        if lost > 0 {
                            tracing::warn!(lines = lost, "MQTT: feed lines the archive lacks are not in the feed file; counted as dropped");
                        }
                        // Nothing found: not written yet (the feed output is failing?).
                        (found.is_empty() && lost == 0).then_some(Duration::from_millis(500))
                    }
                    Ok(Err(e)) => {
                        tracing::warn!("MQTT: cannot read the feed file back ({e}); retrying");
                        Some(Duration::from_secs(1))
                    }
                    Err(_) => return,
                };
                if retry.is_none() {
                    shared.pump(&mut st);
                }
                retry
            };
            if let Some(d) = retry_in {
                tokio::time::sleep(d).await;
                let mut st = shared.state.lock().expect("mqtt state");
                st.want_load = true;
                shared.pump(&mut st);
            }
        }
    }
}
