//! Sinks: where solutions go (the feed, recordings).
