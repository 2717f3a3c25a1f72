//! Frame sources: each produces timestamped [`crate::frame::Frame`]s.
