//! The report at the end of `run` (`[report]` in the config): the run's feed is copied into
//! a new timestamped folder under `[report] out` while it runs (`feed.jsonl`, so the report
//! can be made again with `tagdeflect report`), with every UTM sample at its own rate
//! (`utm.jsonl`, see `graph::utm_file`), and the report is written there at shutdown.

use std::path::PathBuf;

use crate::config::Config;
use tagdeflect_core::feed_file::FeedWriter;
use tagdeflect_report::Feed;

/// A report to be written when the run ends.
pub struct RunReport {
    dir: PathBuf,
    feed: PathBuf,
    config: Config,
}

impl RunReport {
    /// With `[report]` configured: creates the run's report folder and returns the hook and
    /// the feed writer (a sink of the run) that copies the feed into it.
    /// A folder or file that cannot be written is bad input (`[report] out` names it).
    pub fn start(config: &Config) -> Result<Option<(RunReport, FeedWriter)>, tagdeflect_core::BadInput> {
        let bad = |what: String| move |e: std::io::Error| tagdeflect_core::BadInput::new(format!("{what}: {e}"));
        let Some(r) = &config.report else { return Ok(None) };
        let dir = r.out.join(chrono::Utc::now().format("%Y%m%dT%H%M%SZ").to_string());
        std::fs::create_dir_all(&dir).map_err(bad(format!("cannot create the report folder {}", dir.display())))?;
        let feed = dir.join("feed.jsonl");
        let writer = FeedWriter::append(&feed).map_err(bad(format!("cannot write {}", feed.display())))?;
        // The config in force beside the feed: `tagdeflect report feed.jsonl --config tagdeflect.toml` redoes the report.
        let cfg = dir.join("tagdeflect.toml");
        std::fs::write(&cfg, config.to_toml_string()).map_err(bad(format!("cannot write {}", cfg.display())))?;
        tracing::info!("the report of this run goes into {}", dir.display());
        Ok(Some((RunReport { dir, feed, config: config.clone() }, writer)))
    }

    /// The run's report folder (where `utm.jsonl` goes beside the feed).
    pub fn dir(&self) -> &std::path::Path {
        &self.dir
    }

    /// Writes the report (after every sink is flushed). A failure is logged, never fatal:
    /// the feed is already safe on disk and `tagdeflect report` can try again.
    pub fn finish(self) {
        let Some(r) = &self.config.report else { return };
        let cfg_path = self.dir.join("tagdeflect.toml");
        let rig = self.config.test_rig();
        let utm_path = self.dir.join("utm.jsonl");
        let result =
            Feed::read_runs_for(&self.feed, &tagdeflect_report::ReadOptions { limits: r.limits(), allow_restarts: false }, Some(&rig))
                .map(|mut runs| runs.remove(0))
                .and_then(|feed| {
                    let utm = utm_path.is_file().then(|| tagdeflect_report::UtmStream::read(&utm_path, &r.limits())).transpose()?;
                    tagdeflect_report::build(&feed, utm.as_ref(), &rig, &cfg_path, r).and_then(|mut rep| {
                        rep.inputs = vec![("config".into(), cfg_path.clone())];
                        tagdeflect_report::write(&rep, &feed, &self.dir)
                    })
                });
        match result {
            Ok(files) => tracing::info!("report written into {} ({} files)", self.dir.display(), files.len()),
            Err(e) => tracing::error!(
                "the report could not be written: {e}; the run's feed is kept in {} (try `tagdeflect report` on it)",
                self.feed.display()
            ),
        }
    }
}
