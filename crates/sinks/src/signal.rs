//! The control signal's one rule, shared by the outputs that serve it (the control output's
//! registers, `control_output`, and the analog output, `analog_output`): which value of a
//! feed line is the signal (the net deflection or a `[[gauge]]`), and when it is *valid*.
//!
//! The value is valid while its σ is at most `max_sigma_mm` and it is fresh: it turns
//! invalid once its tags were not solved in `stale_sets` consecutive frame sets, or when no
//! frame set arrived for `stale_sets + ½` frame periods (a stalled pipeline; the period is a
//! running mean of the lines' spacing).

use std::time::Instant;

use tagdeflect_core::feed::FeedLine;
use tagdeflect_core::Problem;

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
    /// Frame period, s (running mean of the lines' spacing).
    period_s: Option<f64>,
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
                self.period_s = Some(self.period_s.map_or(dt, |p| 0.9 * p + 0.1 * dt));
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

    /// Valid at `now`: the last lines say so and a frame set came within `stale_sets + ½`
    /// frame periods.
    pub fn valid_at(&self, rule: &SignalRule, now: Instant) -> bool {
        let fresh = match (self.last_line, self.period_s) {
            (Some((at, _)), Some(p)) => now.saturating_duration_since(at).as_secs_f64() <= (rule.stale_sets as f64 + 0.5) * p,
            (Some(_), None) => true,
            _ => false,
        };
        self.valid && fresh
    }

    /// The frame period seen so far, s.
    pub fn period_s(&self) -> Option<f64> {
        self.period_s
    }
}
