//! What one camera's detection of one frame did ([`DetectReport`]) and where its time went
//! ([`DetectParts`]): the figures the measurement sums into `bench`'s breakdown and the
//! metrics.

use super::plan::BackgroundCheck;

/// Time of one frame set's detection by kind of work, seconds.
#[derive(Debug, Clone, Copy, Default)]
pub struct DetectParts {
    /// CPU time confirming tracked tags at their predicted place (refinement and
    /// read-back), summed over the cameras (which run in parallel).
    pub tracking: f64,
    /// Wall time of the window searches of tags not confirmed and of the sweep's tiles,
    /// summed over the cameras (which run in parallel).
    pub search: f64,
    /// Of `search`, the wall time of the retries at the configured resolution of windows
    /// whose expected tag the decimated search missed (likewise).
    pub retry: f64,
    /// Wall time of full-frame searches (likewise).
    pub full_frame: f64,
    /// Wall time spent waiting for a background search that had not finished when its
    /// result was due (likewise; 0 when the searches keep up).
    pub background_wait: f64,
}

impl DetectParts {
    /// Adds another frame set's (or camera's) times.
    pub fn add(&mut self, other: &DetectParts) {
        self.tracking += other.tracking;
        self.search += other.search;
        self.retry += other.retry;
        self.full_frame += other.full_frame;
        self.background_wait += other.background_wait;
    }
}

/// What one camera's detection of one frame did.
#[derive(Debug, Clone, Copy, Default)]
pub struct DetectReport {
    /// Time by kind of work.
    pub parts: DetectParts,
    /// Full-frame searches run in the frame (0, 1, or 2 when the decimated start-up search
    /// was repeated at full resolution).
    pub full_frame_searches: u64,
    /// The whole frame was searched at the configured resolution in the frame (a
    /// full-frame search, not only the decimated start-up one): a whole-frame search again
    /// would find nothing new.
    pub searched_whole: bool,
    /// Whole-frame searches started in the background.
    pub background_searches: u64,
    /// Window and sweep-tile searches run.
    pub window_searches: u64,
    /// Of those, windows searched again at the configured resolution because the decimated
    /// search missed a tag seen the last time it was looked for.
    pub window_retries: u64,
    /// Tags confirmed at their predicted place (no search needed).
    pub confirmed_tags: u64,
    /// Of those, fitted on the pixels selected in an earlier frame (the tag had barely moved).
    pub reused_bands: u64,
    /// What the frame showed of the background tags followed (lost, shifted).
    pub background: BackgroundCheck,
}
