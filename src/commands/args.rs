//! Argument parsers the command line shares.

/// Longest `--duration-s` accepted (about 115 days).
pub const MAX_DURATION_S: f64 = 1e7;

/// `--duration-s`: a finite number of seconds in (0, 1e7].
pub fn parse_duration_s(s: &str) -> Result<f64, String> {
    let v: f64 = s.trim().parse().map_err(|_| format!("\"{s}\" is not a number of seconds"))?;
    if v.is_finite() && v > 0.0 && v <= MAX_DURATION_S {
        Ok(v)
    } else {
        Err(format!("{s}: expected more than 0 and at most {MAX_DURATION_S} seconds (about 115 days)"))
    }
}
