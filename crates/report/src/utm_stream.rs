//! The UTM's own samples (SPEC `utm.jsonl`: `{"t_ns", "load_kN", "stroke_mm"}` per reading, at
//! the rate the machine was read): the load-based quantities are taken from them, never from
//! loads sampled at the frame rate alone.

use std::path::{Path, PathBuf};

use tagdeflect_core::utm_sample::UtmSample;

use crate::error::ReportError;
use crate::feed_reader::Limits;

/// A UTM stream read from a file.
#[derive(Debug, Clone)]
pub struct UtmStream {
    /// Where it was read from.
    pub path: PathBuf,
    /// The samples in time order (UTM clock).
    pub samples: Vec<UtmSample>,
    /// A truncated last line skipped.
    pub warnings: Vec<String>,
}

impl UtmStream {
    /// Reads `utm.jsonl`: every line a sample, times strictly increasing, values finite and
    /// within `limits`; anything else is an error naming the file and line. A truncated last
    /// line (a writer killed mid-line) is skipped with a warning.
    pub fn read(path: &Path, limits: &Limits) -> Result<UtmStream, ReportError> {
        let text = std::fs::read_to_string(path)
            .map_err(|e| ReportError::Io { path: path.to_path_buf(), message: format!("cannot read the UTM samples: {e}") })?;
        Self::parse(&text, path, limits)
    }

    /// Parses the text of a `utm.jsonl`; `path` names it in errors.
    pub fn parse(text: &str, path: &Path, limits: &Limits) -> Result<UtmStream, ReportError> {
        let bad = |line: usize, message: String| ReportError::BadLine { path: path.to_path_buf(), line, message };
        let raw: Vec<&str> = text.lines().collect();
        let mut samples: Vec<UtmSample> = Vec::with_capacity(raw.len());
        let mut warnings = Vec::new();
        let mut prev_line = 0;
        for (i, line) in raw.iter().enumerate() {
            let no = i + 1;
            if line.trim().is_empty() {
                continue;
            }
            let s: UtmSample = match serde_json::from_str(line) {
                Ok(s) => s,
                Err(e) if no == raw.len() && !text.ends_with('\n') && e.is_eof() => {
                    warnings.push(format!("{}:{no}: truncated last line skipped", path.display()));
                    continue;
                }
                Err(e) => return Err(bad(no, format!("not a UTM sample: {e}"))),
            };
            if !(0..=7_258_118_400_000_000_000).contains(&s.t_ns) {
                return Err(bad(no, format!("t_ns {} is not a time between 1970 and 2200", s.t_ns)));
            }
            if !(s.load_kn.is_finite() && s.load_kn.abs() <= limits.max_load_kn) {
                return Err(bad(
                    no,
                    format!("load_kN = {} is outside ±{} kN (max_load_kn)", crate::feed_reader::fmt_g(s.load_kn), limits.max_load_kn),
                ));
            }
            if let Some(st) = s.stroke_mm {
                if !(st.is_finite() && st.abs() <= limits.max_length_mm) {
                    return Err(bad(
                        no,
                        format!("stroke_mm = {} is outside ±{} mm (max_length_mm)", crate::feed_reader::fmt_g(st), limits.max_length_mm),
                    ));
                }
            }
            if let Some(p) = samples.last() {
                if s.t_ns <= p.t_ns {
                    return Err(bad(
                        no,
                        format!("t_ns {} is not after t_ns {} of line {prev_line}: samples must be in time order", s.t_ns, p.t_ns),
                    ));
                }
            }
            samples.push(s);
            prev_line = no;
        }
        if samples.len() < 2 {
            return Err(bad(raw.len().max(1), format!("{} UTM sample(s): at least 2 are needed", samples.len())));
        }
        Ok(UtmStream { path: path.to_path_buf(), samples, warnings })
    }

    /// Median sampling period, s.
    pub fn period_s(&self) -> f64 {
        let mut d: Vec<f64> = self.samples.windows(2).map(|w| (w[1].t_ns - w[0].t_ns) as f64 * 1e-9).collect();
        crate::curve::median(&mut d)
    }

    /// Gaps between samples longer than `max_s`: `(from_t_ns, to_t_ns)` on the UTM clock.
    pub fn gaps(&self, max_s: f64) -> Vec<(i64, i64)> {
        self.samples.windows(2).filter(|w| (w[1].t_ns - w[0].t_ns) as f64 * 1e-9 > max_s).map(|w| (w[0].t_ns, w[1].t_ns)).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_samples_and_names_bad_lines() {
        let p = Path::new("utm.jsonl");
        let ok = "{\"t_ns\":10,\"load_kN\":1.0,\"stroke_mm\":0.1}\n{\"t_ns\":20,\"load_kN\":2.0}\n{\"t_ns\":30,\"lo";
        let s = UtmStream::parse(ok, p, &Limits::default()).unwrap();
        assert_eq!(s.samples.len(), 2);
        assert_eq!(s.warnings.len(), 1);
        let e = UtmStream::parse("{\"t_ns\":10,\"load_kN\":1.0}\n{\"t_ns\":10,\"load_kN\":2.0}\n", p, &Limits::default()).unwrap_err();
        assert!(e.to_string().starts_with("utm.jsonl:2:") && e.to_string().contains("time order"), "{e}");
        let e = UtmStream::parse("{\"t_ns\":10,\"load_kN\":1e300}\n", p, &Limits::default()).unwrap_err();
        assert!(e.to_string().contains("load_kN = 1e300"), "{e}");
    }
}
