//! The analog output (`[output.analog]`, docs/control.md "Analog output"): the control
//! signal as a voltage on a networked DAQ's analog output, with a digital "data valid" line on
//! the same device, written by tagdeflect as a Modbus TCP *client* (the DAQ is the server:
//! LabJack T-series DAC0/DAC1 as FLOAT32 volts, or a generic holding-register module).
//!
//! The value and its validity follow the control output's rule (`crate::signal`): valid
//! while fresh and its σ at most `max_sigma_mm`. Every frame set's value is written
//! (`offset_v + volts_per_mm × value`, clamped to `range_v`), then the valid line is
//! raised. When the value turns invalid or stale (checked every [`TICK`], well within a
//! frame period), the valid line drops first, then the output holds its last value
//! (`on_invalid = "hold"`) or goes to the safe voltage (`on_invalid = 0.0`, a number). At
//! stop the line drops (and the safe voltage is written when set). If tagdeflect dies, the device's own watchdog takes over
//! (LabJack: `labjack_watchdog_s`, see `labjack_watchdog`; another module: `watchdog_writes`).
//!
//! One task per device, on a thread of its own: the measurement never waits for it.
//! Overflow policy: the queue between the sinks' thread and the task holds only the newest
//! value — the sink stores it and wakes the task; a value not yet written when the next one
//! comes is replaced (counted as `superseded`), never queued. On a write failure the
//! connection is dropped and made again with backoff (0.2 s doubling to 5 s); once the
//! device answers again the valid line is written low before anything else. A fault is
//! logged once per outage (an ERROR line), its end once (INFO).

pub mod config;
mod device;
pub mod labjack_watchdog;
mod probe;

use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use tagdeflect_core::backoff::Backoff;
use tagdeflect_core::feed::FeedLine;
use tokio::sync::{watch, Notify};

pub use config::{AnalogConfig, DeviceMap, DigitalOutput, OnInvalid, RegisterWrite};
pub use device::DeviceFault;
pub use probe::{probe, Identity, Probe, WriteTest, LABJACK_PRODUCT_ID, LABJACK_SERIAL_NUMBER};

use crate::signal::{SignalRule, SignalState};
use crate::{Finished, LineSink};
use device::Device;

/// How often the task checks the value's freshness (the valid line drops within this of the
/// value turning stale).
pub const TICK: Duration = Duration::from_millis(5);
/// First reconnect delay.
pub const BACKOFF_MIN: Duration = Duration::from_millis(200);
/// Longest reconnect delay.
pub const BACKOFF_MAX: Duration = Duration::from_secs(5);
/// Most latencies kept for the summary.
const MAX_LATENCIES: usize = 1 << 20;
/// Most acknowledgement times kept (the first 36 min at 30 fps; for `bench`).
const MAX_ACKS: usize = 1 << 16;

/// Why the analog output did not start.
#[derive(Debug, thiserror::Error)]
pub enum AnalogError {
    /// The section is wrong (see [`AnalogConfig::validate`]).
    #[error("[output.analog] {0}")]
    Config(tagdeflect_core::Problem),
    /// The task's thread or runtime could not start.
    #[error("[output.analog]: cannot start the device's task: {0}")]
    Start(std::io::Error),
}

/// What the analog output did so far.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct AnalogStatus {
    /// Connected to the device now.
    pub connected: bool,
    /// Values written (acknowledged by the device).
    pub values_written: u64,
    /// Values replaced by a newer one before they were written.
    pub superseded: u64,
    /// Outages (a fault after the device answered, or at start).
    pub outages: u64,
    /// The last fault, if the device is not answering now.
    pub fault: Option<String>,
    /// When the device last acknowledged the valid line written low.
    pub line_low_at: Option<Instant>,
    /// When the device last acknowledged the valid line written high.
    pub line_high_at: Option<Instant>,
    /// Exposure → write-acknowledged latencies, ms.
    latencies_ms: Vec<f32>,
    /// When each value was acknowledged: (feed seq, instant).
    acks: Vec<(u64, Instant)>,
}

impl AnalogStatus {
    /// Exposure → write-acknowledged latency: (values, p50 ms, p99 ms, max ms).
    pub fn latency_ms(&self) -> Option<(usize, f64, f64, f64)> {
        let mut v = self.latencies_ms.clone();
        if v.is_empty() {
            return None;
        }
        v.sort_by(f32::total_cmp);
        let q = |p: f64| v[((v.len() - 1) as f64 * p).round() as usize] as f64;
        Some((v.len(), q(0.5), q(0.99), q(1.0)))
    }

    /// When the device acknowledged each value written: (feed `seq`, instant), the first
    /// 65 536 values (`bench` times exposure → acknowledged on a replay's clock with them).
    pub fn acknowledged(&self) -> &[(u64, Instant)] {
        &self.acks
    }
}

struct Shared {
    config: AnalogConfig,
    rule: SignalRule,
    signal: Mutex<SignalState>,
    /// A value came that the task has not looked at yet.
    pending: AtomicBool,
    superseded: AtomicU64,
    stopped: AtomicBool,
    status: Mutex<AnalogStatus>,
}

/// What the device should show now.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Level {
    /// A frame set's value: its seq, volts and time.
    Value { seq: u64, volts: f64, t_ns: i64 },
    /// The safe value.
    Safe(f64),
    /// Whatever was last written.
    Hold,
}

impl Shared {
    /// The level and the valid line at `now`.
    fn target(&self, now: Instant, now_ns: i64) -> (Level, bool) {
        let st = self.signal.lock().expect("analog state");
        let valid = st.valid_at(&self.rule, now, now_ns) && !self.stopped.load(Ordering::Relaxed);
        match (valid, st.sample) {
            (true, Some(s)) => (Level::Value { seq: s.seq, volts: self.config.volts_of(s.value), t_ns: s.t_ns }, true),
            _ => (self.invalid_level(), false),
        }
    }

    fn invalid_level(&self) -> Level {
        match self.config.on_invalid.safe_v() {
            Some(v) => Level::Safe(v),
            _ => Level::Hold,
        }
    }

    fn status(&self) -> std::sync::MutexGuard<'_, AnalogStatus> {
        self.status.lock().expect("analog status")
    }
}

/// What was last written on this connection.
#[derive(Debug, Default)]
struct Written {
    level: Option<Level>,
    valid: Option<bool>,
}

/// The device's task: writes the target whenever it changes, reconnects after faults.
struct Task {
    shared: Arc<Shared>,
    device: Device,
    written: Written,
    backoff: Backoff,
    retry_at: Option<tokio::time::Instant>,
    /// The fault of the outage under way.
    outage: Option<String>,
}

impl Task {
    async fn run(mut self, wake: Arc<Notify>, mut stop: watch::Receiver<bool>) {
        let mut tick = tokio::time::interval(TICK);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        loop {
            tokio::select! {
                _ = wake.notified() => {}
                _ = tick.tick() => {}
                _ = stop.changed() => break,
            }
            if *stop.borrow() {
                break;
            }
            if self.retry_at.is_some_and(|t| tokio::time::Instant::now() < t) {
                continue;
            }
            let result = self.step().await;
            self.after(result);
        }
        self.last_words().await;
    }

    /// Connects when needed, then writes what changed.
    async fn step(&mut self) -> Result<(), DeviceFault> {
        if !self.device.connected() {
            self.device.connect().await?;
            self.written = Written::default();
            // Valid low before anything else, then the device's own set-up.
            self.set_line(false).await?;
            self.device.set_up(&self.shared.config).await?;
        }
        self.shared.pending.store(false, Ordering::Relaxed);
        let (level, valid) = self.shared.target(Instant::now(), tagdeflect_core::clock::now_epoch_ns());
        if !valid {
            self.set_line(false).await?;
        }
        self.write_level(level).await?;
        if valid {
            self.set_line(true).await?;
        }
        Ok(())
    }

    async fn write_level(&mut self, level: Level) -> Result<(), DeviceFault> {
        let volts = match level {
            Level::Hold => return Ok(()),
            _ if self.written.level == Some(level) => return Ok(()),
            Level::Value { volts, .. } | Level::Safe(volts) => volts,
        };
        let config = &self.shared.config;
        self.device.write_value(&config.value_register(), config.raw_of(volts)).await?;
        self.written.level = Some(level);
        let mut st = self.shared.status();
        if let Level::Value { t_ns, seq, .. } = level {
            st.values_written += 1;
            if st.acks.len() < MAX_ACKS {
                st.acks.push((seq, Instant::now()));
            }
            if st.latencies_ms.len() < MAX_LATENCIES {
                st.latencies_ms.push(((tagdeflect_core::clock::now_epoch_ns() - t_ns) as f64 * 1e-6) as f32);
            }
        }
        Ok(())
    }

    async fn set_line(&mut self, on: bool) -> Result<(), DeviceFault> {
        let Some(line) = self.shared.config.valid_line() else { return Ok(()) };
        if self.written.valid != Some(on) {
            self.device.write_line(line, on).await?;
            self.written.valid = Some(on);
            let mut st = self.shared.status();
            *(if on { &mut st.line_high_at } else { &mut st.line_low_at }) = Some(Instant::now());
        }
        Ok(())
    }

    /// Logs a fault once per outage and schedules the reconnect; logs the device's return.
    fn after(&mut self, result: Result<(), DeviceFault>) {
        let addr = self.shared.config.address.clone();
        match result {
            Ok(()) => {
                self.backoff.reset();
                self.retry_at = None;
                if self.outage.take().is_some() {
                    tracing::info!(device = %addr, "analog output: the device answers again (valid line written low first)");
                }
                let mut st = self.shared.status();
                st.connected = true;
                st.fault = None;
            }
            Err(fault) => {
                self.device.drop_connection();
                let delay = self.backoff.next_delay();
                let reason = fault.to_string();
                if self.outage.is_none() {
                    tracing::error!(retry_in_ms = delay.as_millis() as u64, "{reason} (retrying with backoff; logged once per outage)");
                    self.shared.status().outages += 1;
                } else {
                    tracing::debug!(retry_in_ms = delay.as_millis() as u64, "{reason}");
                }
                self.outage = Some(reason.clone());
                self.retry_at = Some(tokio::time::Instant::now() + delay);
                let mut st = self.shared.status();
                st.connected = false;
                st.fault = Some(reason);
            }
        }
    }

    /// At stop: the valid line low and, when set, the safe value (one attempt each).
    async fn last_words(&mut self) {
        let result = async {
            if !self.device.connected() {
                self.device.connect().await?;
                self.written = Written::default();
            }
            // Low at stop whatever was written before.
            self.written.valid = None;
            self.set_line(false).await?;
            if let Some(v) = self.shared.config.on_invalid.safe_v() {
                self.write_level(Level::Safe(v)).await?;
            }
            Ok::<(), DeviceFault>(())
        }
        .await;
        if let Err(e) = result {
            tracing::warn!("{e} (at stop: the device's watchdog must take over)");
        }
        self.device.drop_connection();
        self.shared.status().connected = false;
    }
}

/// The running analog output: the device's task on its own thread.
pub struct AnalogOutput {
    shared: Arc<Shared>,
    wake: Arc<Notify>,
    stop: Option<watch::Sender<bool>>,
    thread: Option<JoinHandle<()>>,
}

impl AnalogOutput {
    /// Starts the device's task (it connects in the background; faults are retried).
    pub fn start(config: &AnalogConfig) -> Result<AnalogOutput, AnalogError> {
        let addr: SocketAddr = config.addr().map_err(AnalogError::Config)?;
        let shared = Arc::new(Shared {
            config: config.clone(),
            rule: config.rule(),
            signal: Mutex::new(SignalState::default()),
            pending: AtomicBool::new(false),
            superseded: AtomicU64::new(0),
            stopped: AtomicBool::new(false),
            status: Mutex::new(AnalogStatus::default()),
        });
        let task = Task {
            shared: shared.clone(),
            device: Device::new(config, addr),
            written: Written::default(),
            backoff: Backoff::new(BACKOFF_MIN, BACKOFF_MAX),
            retry_at: None,
            outage: None,
        };
        let runtime = tokio::runtime::Builder::new_current_thread().enable_all().build().map_err(AnalogError::Start)?;
        let wake = Arc::new(Notify::new());
        let (tx, rx) = watch::channel(false);
        let w = wake.clone();
        let thread = std::thread::Builder::new()
            .name("analog-output".into())
            .spawn(move || runtime.block_on(task.run(w, rx)))
            .map_err(AnalogError::Start)?;
        tracing::info!(device = %addr, map = ?config.device, gauge = %config.gauge, "analog output writing to the device (Modbus TCP client)");
        Ok(AnalogOutput { shared, wake, stop: Some(tx), thread: Some(thread) })
    }

    /// Takes one feed line (never waits for the device).
    pub fn take_line(&self, line: &FeedLine) {
        let taken = self.shared.signal.lock().expect("analog state").take_line(&self.shared.rule, line, Instant::now());
        if taken.is_some() && self.shared.pending.swap(true, Ordering::Relaxed) {
            self.shared.superseded.fetch_add(1, Ordering::Relaxed);
        }
        self.wake.notify_one();
    }

    /// What it did so far.
    pub fn status(&self) -> AnalogStatus {
        let mut s = self.shared.status().clone();
        s.superseded = self.shared.superseded.load(Ordering::Relaxed);
        s
    }

    /// Stops: the valid line drops (and the safe voltage is written when set), the task ends.
    pub fn shutdown(&mut self) {
        self.shared.stopped.store(true, Ordering::Relaxed);
        if let Some(tx) = self.stop.take() {
            let _ = tx.send(true);
        }
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

impl Drop for AnalogOutput {
    fn drop(&mut self) {
        self.shutdown();
    }
}

/// The analog output as a line sink.
pub struct AnalogSink(pub AnalogOutput);

impl LineSink for AnalogSink {
    fn name(&self) -> String {
        format!("analog output on {}", self.0.shared.config.address)
    }

    fn accept(&mut self, finished: &Finished) {
        self.0.take_line(&finished.line);
    }

    fn finish(&mut self) {
        self.0.shutdown();
        let s = self.0.status();
        match s.latency_ms() {
            Some((values, p50_ms, p99_ms, max_ms)) if p50_ms.abs() < 3.6e6 => {
                tracing::info!(
                    values,
                    p50_ms,
                    p99_ms,
                    max_ms,
                    superseded = s.superseded,
                    outages = s.outages,
                    "analog output: exposure → write acknowledged"
                )
            }
            _ => tracing::info!(values = s.values_written, outages = s.outages, "analog output stopped"),
        }
    }
}
