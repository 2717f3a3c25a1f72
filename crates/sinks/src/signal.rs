//! The control signal's one rule, shared by the outputs that serve it (the control output's
//! registers, `control_output`, and the analog output, `analog_output`): which value of a
//! feed line is the signal (the net deflection or a `[[gauge]]`), and when it is *valid*.
//!
//! The value is valid while its σ is at most `max_sigma_mm` and it is fresh: it turns
//! invalid once its tags were not solved in `stale_sets` consecutive frame sets, when no
//! frame set arrived for `stale_sets + ½` frame periods (a stalled pipeline; the period is the
//! median of the last [`PERIOD_WINDOW`] spacings of the lines, so that a stall does not
//! lengthen the periods it is judged by), and when the value's age *since its frames were
//! exposed* exceeds `stale_sets + ½` frame periods plus [`LATENCY_ALLOWANCE_MS`] — lines
//! that arrive on time but late (the sinks' thread held up, e.g. by a report made
//! in-process) carry old values and are not fresh. Lines whose times are not this
//! computer's clock (a replayed recording: more than [`FOREIGN_CLOCK_S`] from now) are aged
//! by their arrival alone.

use std::time::Instant;

use tagdeflect_core::feed::FeedLine;
use tagdeflect_core::Problem;

/// Exposure → line latency allowed on top of the frame periods before a value is stale, ms
/// (the pipeline's own is ~17 ms p50, docs/control.md; a loaded machine's a few times that).
pub const LATENCY_ALLOWANCE_MS: f64 = 250.0;
/// A line time this far from the computer's clock is a recording's, s.
pub const FOREIGN_CLOCK_S: f64 = 3600.0;

/// Line spacings the frame period is the median of: a few seconds at the usual rates, and a
/// stall of a few lines moves it not at all (a running mean took a tenth of each stall's length
/// into the period, so a value well past its age limit was still served valid after one).
pub const PERIOD_WINDOW: usize = 31;

/// The gauge served by default: the feed's `net_deflection_mm`.
pub const NET_DEFLECTION: &str = "net_deflection";

/// Which value is the signal and when it is valid (the keys `gauge`, `max_sigma_mm` and
/// `stale_sets` of `[output.control]` and `[output.analog]`).
#[derive(Debug, Clone, PartialEq)]
pub struct SignalRule {
    /// `"net_deflection"` or the name of a `[[gauge]]`.
    pub gauge: String,
    /// Largest 1-σ of a valid value, mm.
    pub max_sigma_mm: f64,
    /// Frame sets without the value (or frame periods without a frame set) before it is stale.
    pub stale_sets: u32,
}

impl SignalRule {
    /// Checks the rule's keys (relative to the section that holds them); `gauges` are the
    /// configured `[[gauge]]` names.
    pub fn validate(&self, gauges: &[String]) -> Result<(), Problem> {
        if self.gauge != NET_DEFLECTION && !gauges.contains(&self.gauge) {
            return Err(Problem::new(
                "gauge",
                format!("\"{}\" is neither \"{NET_DEFLECTION}\" nor a configured [[gauge]] (have: {gauges:?})", self.gauge),
            ));
        }
        if !(self.max_sigma_mm.is_finite() && self.max_sigma_mm > 0.0) {
            return Err(Problem::new("max_sigma_mm", format!("{}: expected a positive number of mm", self.max_sigma_mm)));
        }
        if self.stale_sets == 0 || self.stale_sets > 1000 {
            return Err(Problem::new("stale_sets", format!("{}: expected 1 to 1000 frame sets", self.stale_sets)));
        }
        Ok(())
    }
}

/// The signal's value as taken from one feed line.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sample {
    /// The value, mm (or the gauge's unit).
    pub value: f64,
    /// Its 1-σ.
    pub sigma: f64,
    /// The feed `seq` of its frame set.
    pub seq: u64,
    /// The frame set's time, ns since the epoch.
    pub t_ns: i64,
    /// Its rate, per minute (the feed's, or from the previous value).
    pub rate_mm_per_min: f64,
}

/// The signal as the lines so far left it.
#[derive(Debug, Default)]
pub struct SignalState {
    /// The latest value.
    pub sample: Option<Sample>,
    /// The last lines say: solved recently enough and σ small enough.
    valid: bool,
    /// Consecutive lines without the value.
    missing: u32,
    /// When the last line arrived, and its time.
    last_line: Option<(Instant, i64)>,
    /// The last [`PERIOD_WINDOW`] spacings of the lines, s (the frame period is their median).
    spacings_s: std::collections::VecDeque<f64>,
}

impl SignalState {
    /// Takes one feed line that arrived at `arrived`; returns the new value when the line
    /// carries one.
    pub fn take_line(&mut self, rule: &SignalRule, line: &FeedLine, arrived: Instant) -> Option<Sample> {
        let reading = if let Some(g) = line.gauges.get(&rule.gauge) {
            g.known_sigma().map(|s| (g.value, s, None))
        } else if rule.gauge == NET_DEFLECTION {
            line.net_deflection_mm.zip(line.net_deflection_sigma_mm).map(|(v, s)| (v, s, line.net_deflection_rate_mm_per_min))
        } else {
            None
        };
        if let Some((_, t_prev)) = self.last_line {
            let dt = (line.t_ns - t_prev) as f64 * 1e-9;
            if dt > 0.0 && dt < 10.0 {
                if self.spacings_s.len() == PERIOD_WINDOW {
                    self.spacings_s.pop_front();
                }
                self.spacings_s.push_back(dt);
            }
        }
        self.last_line = Some((arrived, line.t_ns));
        let Some((value, sigma, rate)) = reading.filter(|(v, s, _)| v.is_finite() && s.is_finite()) else {
            self.missing += 1;
            if self.missing >= rule.stale_sets {
                self.valid = false;
            }
            return None;
        };
        let rate_mm_per_min = match (rate, self.sample) {
            (Some(r), _) => r,
            (None, Some(p)) if line.t_ns > p.t_ns => (value - p.value) / ((line.t_ns - p.t_ns) as f64 * 1e-9) * 60.0,
            _ => 0.0,
        };
        let sample = Sample { value, sigma, seq: line.seq, t_ns: line.t_ns, rate_mm_per_min };
        self.sample = Some(sample);
        self.missing = 0;
        self.valid = sigma <= rule.max_sigma_mm;
        Some(sample)
    }

    /// Valid at `now` (`now_ns` the same instant on the feed's clock, ns since the epoch): the
    /// last lines say so, a frame set came within `stale_sets + ½` frame periods, and the
    /// value was exposed no longer ago than that plus [`LATENCY_ALLOWANCE_MS`].
    pub fn valid_at(&self, rule: &SignalRule, now: Instant, now_ns: i64) -> bool {
        let slack_s = self.period_s().map(|p| (rule.stale_sets as f64 + 0.5) * p);
        let arrived_in_time = match (self.last_line, slack_s) {
            (Some((at, _)), Some(slack)) => now.saturating_duration_since(at).as_secs_f64() <= slack,
            (Some(_), None) => true,
            _ => false,
        };
        self.valid && arrived_in_time && self.sample.is_some_and(|s| exposed_in_time(s.t_ns, now_ns, slack_s.unwrap_or(0.0)))
    }

    /// The value's age since exposure at `now_ns`, s (negative: a clock ahead of this one).
    pub fn age_s(&self, now_ns: i64) -> Option<f64> {
        self.sample.map(|s| (now_ns - s.t_ns) as f64 * 1e-9)
    }

    /// The frame period seen so far: the median of the last spacings, s.
    pub fn period_s(&self) -> Option<f64> {
        let mut v: Vec<f64> = self.spacings_s.iter().copied().collect();
        if v.is_empty() {
            return None;
        }
        v.sort_by(f64::total_cmp);
        Some(v[v.len() / 2])
    }
}

/// A value exposed at `t_ns` is fresh at `now_ns`: its age is at most `slack_s` plus the
/// latency allowance, unless its clock is a recording's (then its arrival alone counts).
fn exposed_in_time(t_ns: i64, now_ns: i64, slack_s: f64) -> bool {
    let age_s = (now_ns - t_ns) as f64 * 1e-9;
    age_s.abs() > FOREIGN_CLOCK_S || age_s <= slack_s + LATENCY_ALLOWANCE_MS * 1e-3
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    fn line(seq: u64, t_ns: i64) -> FeedLine {
        FeedLine { seq, t_ns, net_deflection_mm: Some(0.1), net_deflection_sigma_mm: Some(0.001), ..FeedLine::default() }
    }

    /// Lines that arrive on time but carry values exposed 1.18 s ago (the sinks' thread was
    /// held up) are not fresh: the age counts from exposure, not arrival.
    #[test]
    fn a_value_is_aged_from_its_exposure_not_its_arrival() {
        let rule = SignalRule { gauge: NET_DEFLECTION.into(), max_sigma_mm: 0.01, stale_sets: 1 };
        let mut st = SignalState::default();
        let (t0, ns0) = (Instant::now(), 1_800_000_000_000_000_000i64);
        let period_ns = 100_000_000;
        for k in 0..10u64 {
            let t_ns = ns0 + k as i64 * period_ns;
            st.take_line(&rule, &line(k, t_ns), t0 + Duration::from_millis(100 * k));
            // Read 20 ms after each arrival, 30 ms after exposure: fresh.
            let now = t0 + Duration::from_millis(100 * k + 20);
            assert!(st.valid_at(&rule, now, t_ns + 30_000_000), "set {k}");
        }
        // The next line arrives on time but was exposed 1.18 s before.
        let t_ns = ns0 + 10 * period_ns;
        st.take_line(&rule, &line(10, t_ns), t0 + Duration::from_millis(1000));
        let now = t0 + Duration::from_millis(1010);
        assert!(!st.valid_at(&rule, now, t_ns + 1_180_000_000), "a value 1.18 s old is stale");
        assert!(st.valid_at(&rule, now, t_ns + 50_000_000), "a value 50 ms old is fresh");
        // A replayed recording's clock (days from now): its arrival alone counts.
        assert!(st.valid_at(&rule, now, t_ns + 86_400_000_000_000));
    }

    /// A stall of 3 s among lines 100 ms apart does not lengthen the period a value is judged
    /// by: four lines after it, a value exposed 0.6 s ago (over 1.5 periods + 250 ms) is stale
    /// (a running mean of the spacings took the period to 0.31 s and called it fresh).
    #[test]
    fn a_stall_does_not_lengthen_the_period_values_are_aged_by() {
        let rule = SignalRule { gauge: NET_DEFLECTION.into(), max_sigma_mm: 0.01, stale_sets: 1 };
        let mut st = SignalState::default();
        let (t0, ns0) = (Instant::now(), 1_800_000_000_000_000_000i64);
        let mut t_ms = 0u64;
        for k in 0..40u64 {
            t_ms += if k == 36 { 3000 } else { 100 };
            st.take_line(&rule, &line(k, ns0 + t_ms as i64 * 1_000_000), t0 + Duration::from_millis(t_ms));
        }
        assert!((st.period_s().unwrap() - 0.1).abs() < 1e-9, "{:?}", st.period_s());
        let t_ns = ns0 + t_ms as i64 * 1_000_000;
        let now = t0 + Duration::from_millis(t_ms + 20);
        assert!(st.valid_at(&rule, now, t_ns + 300_000_000), "0.3 s old: within 0.15 s + 0.25 s");
        assert!(!st.valid_at(&rule, now, t_ns + 600_000_000), "0.6 s old: stale");
    }
}
