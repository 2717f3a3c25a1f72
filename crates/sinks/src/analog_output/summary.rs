//! The analog output's part in a test's `control.json`: each frame set's verdict (the valid
//! line high after it, or why not) into the [`SignalLog`](crate::signal_log::SignalLog), and the
//! test's figures with the output's configuration.

use std::sync::Arc;
use std::time::Instant;

use tagdeflect_core::control_summary::{AnalogScaling, OutputSummary};
use tagdeflect_core::feed::FeedLine;

use super::{AnalogOutput, DeviceMap, Shared};
use crate::signal_log::{stall_s, verdict, SignalLog, TestSummaries, Verdict};

impl Shared {
    pub(super) fn log(&self) -> std::sync::MutexGuard<'_, SignalLog> {
        self.log.lock().expect("analog test log")
    }

    /// Takes one feed line into the signal and the test log; true when it carries a value.
    pub(super) fn take_and_log(&self, line: &FeedLine) -> bool {
        let now = Instant::now();
        let mut st = self.signal.lock().expect("analog state");
        let taken = st.take_line(&self.rule, line, now).is_some();
        let verdict = verdict(&st, &self.rule, taken, now).and_then(|()| self.device_answers());
        let stall_s = stall_s(&st, &self.rule);
        drop(st);
        self.log().take(line.test.as_ref().map(|t| t.id.as_str()), line.seq, line.t_ns, &verdict, stall_s);
        taken
    }

    /// A valid value raises the line only on a device that answers.
    fn device_answers(&self) -> Verdict {
        let status = self.status();
        match (&status.fault, status.connected) {
            (None, true) => Ok(()),
            (Some(f), _) => Err(format!("the device not answering ({f})")),
            (None, false) => Err("the device not connected yet".into()),
        }
    }
}

impl AnalogOutput {
    /// The figures of test `id` with this output's configuration (`control.json`).
    pub fn test_summary(&self, id: &str) -> Option<OutputSummary> {
        summary_of(&self.shared, id)
    }

    /// The same, as a handle that outlives the sink (the tests' folder hook).
    pub fn test_summaries(&self) -> TestSummaries {
        let shared = self.shared.clone();
        Arc::new(move |id: &str| summary_of(&shared, id))
    }
}

fn summary_of(shared: &Shared, id: &str) -> Option<OutputSummary> {
    let mut s = shared.log().summary(id)?;
    let c = &shared.config;
    let (low, high) = c.range();
    let target = match c.device {
        DeviceMap::LabjackT => format!("LabJack T-series at {}, DAC{}", c.address, c.channel),
        DeviceMap::Generic => format!("holding-register module at {}, register {}", c.address, c.register.unwrap_or_default()),
    };
    s.kind = "analog".into();
    s.target = target;
    s.gauge = c.gauge.clone();
    s.max_sigma_mm = c.max_sigma_mm;
    s.stale_sets = c.stale_sets;
    s.scaling =
        Some(AnalogScaling { volts_per_mm: c.volts_per_mm, offset_v: c.offset_v, range_v: [low, high], safe_v: c.on_invalid.safe_v() });
    Some(s)
}
