//! The limits on what a lab test may hold — what an operator types and what its record
//! (`test.json`) grows to — defined once: the control API refuses what goes beyond them (400
//! naming the field), the rig's publisher and the archive take everything within them, so the
//! archive never refuses a record the API let through (SPEC "Tests", "Archive").
//!
//! Lengths are in bytes of UTF-8 (what a file name, a column and a message are limited by);
//! the specimen id has a limit in characters as well (what an operator sees).

use crate::Problem;

/// A specimen id: at most this many characters …
pub const SPECIMEN_MAX_CHARS: usize = 64;
/// … and at most this many bytes (64 four-byte letters would make a folder name of 273 bytes,
/// over the 255 a Linux file name may have).
pub const SPECIMEN_MAX_BYTES: usize = 128;
/// A test id: the UTC start (`20261202T013000Z`), `-`, the specimen id.
pub const TEST_ID_MAX_BYTES: usize = 17 + SPECIMEN_MAX_BYTES;
/// Free text: the operator's name, the notes, an event's note.
pub const TEXT_MAX_BYTES: usize = 4096;
/// The name of a measured value (`width_mm`).
pub const MEASURED_KEY_MAX_BYTES: usize = 64;
/// Measured values of one test.
pub const MEASURED_MAX: usize = 64;
/// Events an operator may add to one test (marks, zeros, cracks); the daemon's own (start,
/// preload, resume, stop) are never refused.
pub const OPERATOR_EVENTS_MAX: usize = 1000;
/// A running test's record (compact JSON) after an operator's event: an event that would make
/// it larger is refused.
pub const RECORD_MAX_BYTES: usize = 256 * 1024;
/// A lab test message the archive takes: the record within [`RECORD_MAX_BYTES`] plus room for
/// what the daemon adds on its own (the stop's file hashes, resume events, the rig and run) —
/// the largest packet the rig's MQTT client sends.
pub const ARCHIVE_RECORD_MAX_BYTES: usize = 1 << 20;
/// Events in a record the archive takes (operator's and daemon's).
pub const ARCHIVE_EVENTS_MAX: usize = 10_000;

/// Free text `field`: at most [`TEXT_MAX_BYTES`], no NUL or other control character (a new
/// line allowed when `newlines`).
pub fn check_text(field: &str, text: &str, newlines: bool) -> Result<(), Problem> {
    if text.len() > TEXT_MAX_BYTES || text.chars().any(|c| c.is_control() && !(newlines && c == '\n')) {
        let nl = if newlines { " but new lines" } else { "" };
        return Err(Problem::new(field, format!("{field}: at most {TEXT_MAX_BYTES} bytes, no control characters{nl}")));
    }
    Ok(())
}

/// A specimen id: 1 to [`SPECIMEN_MAX_CHARS`] letters, digits, `_`, `-`, `.` (not first), at
/// most [`SPECIMEN_MAX_BYTES`] — a folder name and text on the page. Checked as given (a
/// caller trims first).
pub fn check_specimen(id: &str) -> Result<(), Problem> {
    let ok = |c: char| c.is_alphanumeric() || matches!(c, '_' | '-' | '.');
    if id.is_empty()
        || id.chars().count() > SPECIMEN_MAX_CHARS
        || id.len() > SPECIMEN_MAX_BYTES
        || id.starts_with('.')
        || !id.chars().all(ok)
    {
        return Err(Problem::new(
            "specimen",
            format!(
                "specimen \"{}\": 1 to {SPECIMEN_MAX_CHARS} letters, digits, `_`, `-` and `.` (not first), at most {SPECIMEN_MAX_BYTES} bytes",
                id.escape_debug()
            ),
        ));
    }
    Ok(())
}

/// A measured value's name: 1 to [`MEASURED_KEY_MAX_BYTES`] bytes, no NUL or other control
/// character (PostgreSQL's jsonb refuses NUL, the page shows the name).
pub fn check_measured_key(key: &str) -> Result<(), Problem> {
    if key.is_empty() || key.len() > MEASURED_KEY_MAX_BYTES || key.chars().any(char::is_control) {
        return Err(Problem::new(
            "measured",
            format!("measured \"{}\": a name of 1 to {MEASURED_KEY_MAX_BYTES} bytes without control characters", key.escape_debug()),
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_limits_fit_each_other_and_name_the_field() {
        // The largest test id is a file name (≤ 255 bytes) and fits the archive's column.
        assert!(TEST_ID_MAX_BYTES < 255);
        // 64 four-byte letters: within the characters, over the bytes.
        let wide = "𝐁".repeat(64);
        assert_eq!(wide.chars().count(), 64);
        assert!(check_specimen(&wide).unwrap_err().message.contains("128 bytes"));
        assert!(check_specimen(&"𝐁".repeat(32)).is_ok());
        assert!(check_specimen("B12").is_ok() && check_specimen(" B12").is_err() && check_specimen(".x").is_err());
        assert!(check_measured_key("a\u{0}b").is_err() && check_measured_key("").is_err() && check_measured_key("mass_kg").is_ok());
        assert!(check_text("notes", "a\nb", true).is_ok() && check_text("note", "a\nb", false).is_err());
        assert!(check_text("note", "a\u{0}", true).unwrap_err().message.starts_with("note:"));
        // A record at the API's limit plus the daemon's own additions fits what the archive takes.
        assert!(RECORD_MAX_BYTES * 2 < ARCHIVE_RECORD_MAX_BYTES && OPERATOR_EVENTS_MAX * 2 < ARCHIVE_EVENTS_MAX);
    }
}
