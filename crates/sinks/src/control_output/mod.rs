//! The control output (`[output.control]`, SPEC "Control output"): the configured gauge as
//! a testing machine's controller or a PLC reads it, from a read-only Modbus TCP server (on
//! `tagdeflect_io::modbus_server`). Named for what SPEC calls it; the tests' HTTP API (SPEC's
//! "control API") is another thing, `http::test_api`.
//!
//! The measurement never waits for it: the sink ([`ControlSink`], on the sinks' thread)
//! only writes the latest value into a small shared block, and the server answers every
//! read from that block on a thread of its own (a single-threaded tokio runtime). Writes, and
//! every function but "read input registers", are refused with the exception "illegal
//! function": the daemon never writes to the machine and nobody writes to it.
//!
//! Input registers (32-bit values high word first):
//!
//! | registers | value |
//! | --- | --- |
//! | 0–1 | the value, f32, mm |
//! | 2–3 | the value, i32, µm (rounded) |
//! | 4–5 | its 1-σ, f32, mm |
//! | 6 | valid: 1 while the value is fresh and its σ below `max_sigma_mm`, else 0 |
//! | 7 | the feed `seq` of the frame set the value comes from, modulo 65 536 |
//! | 8 | age of the value in ms since its frames were exposed, u16, saturating |
//! | 9 | heartbeat, u16, incremented every 50 ms while the daemon runs |
//! | 10–11 | the value's rate, f32, mm/min |
//!
//! Valid follows the signal's rule (`crate::signal`, shared with the analog output): it drops to 0 when the gauge's tags were not solved in `stale_sets` consecutive
//! frame sets, when no frame set arrived for `stale_sets + ½` frame periods (a stalled
//! pipeline), when the value was exposed longer ago than that plus
//! `signal::LATENCY_ALLOWANCE_MS` (lines that come late), when σ exceeds `max_sigma_mm`, and for good when the daemon stops (the
//! heartbeat stops with it; the server answers [`STOP_HOLD`] more before it closes).

pub mod config;
mod summary;

use std::io;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, AtomicU16, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use tagdeflect_core::feed::FeedLine;
use tagdeflect_core::listen::ListenAddrError;
use tagdeflect_io::modbus_server::{read_range, Answer, ModbusServer, ServerName};
use tokio_modbus::{ExceptionCode, Request, Response};

pub use config::{ControlConfig, EXAMPLE_PORT, NET_DEFLECTION};

use crate::signal::{SignalRule, SignalState};
use crate::{Finished, LineSink};

/// Input registers served.
pub const REGISTERS: usize = 12;
/// Heartbeat period.
pub const HEARTBEAT: Duration = Duration::from_millis(50);
/// How long the server answers after the measurement ended (valid 0, the heartbeat still),
/// before it closes: a controller polling it reads the stop, not only a dropped connection.
pub const STOP_HOLD: Duration = Duration::from_secs(1);

/// Why the control output did not start.
#[derive(Debug, thiserror::Error)]
pub enum ControlError {
    /// The address is malformed.
    #[error("[output.control] modbus: {0}")]
    Address(ListenAddrError),
    /// The address cannot be bound.
    #[error("[output.control] cannot serve Modbus TCP on {addr}: {source}")]
    Bind {
        /// The address.
        addr: SocketAddr,
        /// Why.
        source: io::Error,
    },
    /// The server's thread or runtime could not start.
    #[error("[output.control]: cannot start the server: {0}")]
    Start(io::Error),
}

#[derive(Debug)]
struct State {
    /// The signal (`crate::signal`: the rule shared with the analog output).
    signal: SignalState,
    /// Exposure → register latencies seen, ms.
    latencies_ms: Vec<f32>,
}

struct Shared {
    rule: SignalRule,
    /// Where it serves, in words (`control.json`).
    target: String,
    /// The tests served so far (`control.json`).
    log: Mutex<crate::signal_log::SignalLog>,
    state: Mutex<State>,
    heartbeat: AtomicU16,
    stopped: AtomicBool,
}

/// Most latencies kept for the summary.
const MAX_LATENCIES: usize = 1 << 20;

impl Shared {
    fn new(config: &ControlConfig, heartbeat: u16) -> Shared {
        Shared {
            rule: config.rule(),
            target: format!("Modbus TCP input registers served on {}", config.modbus),
            log: Mutex::default(),
            state: Mutex::new(State { signal: SignalState::default(), latencies_ms: Vec::new() }),
            heartbeat: AtomicU16::new(heartbeat),
            stopped: AtomicBool::new(false),
        }
    }

    fn take_line(&self, line: &FeedLine, arrived: Instant, now_ns: i64) {
        let mut st = self.state.lock().expect("control state");
        let taken = st.signal.take_line(&self.rule, line, arrived).is_some();
        let latency_ms = (now_ns - line.t_ns) as f64 * 1e-6;
        if taken && st.latencies_ms.len() < MAX_LATENCIES {
            st.latencies_ms.push(latency_ms as f32);
        }
        self.log_line(&st.signal, line, taken, latency_ms);
    }

    fn registers(&self, now: Instant, now_ns: i64) -> [u16; REGISTERS] {
        let st = self.state.lock().expect("control state");
        let mut r = [0u16; REGISTERS];
        let valid = st.signal.valid_at(&self.rule, now, now_ns) && !self.stopped.load(Ordering::Relaxed);
        if let Some(s) = st.signal.sample {
            let put32 = |r: &mut [u16; REGISTERS], at: usize, bits: u32| {
                r[at] = (bits >> 16) as u16;
                r[at + 1] = bits as u16;
            };
            put32(&mut r, 0, (s.value as f32).to_bits());
            let um = (s.value * 1e3).round().clamp(i32::MIN as f64, i32::MAX as f64) as i32;
            put32(&mut r, 2, um as u32);
            put32(&mut r, 4, (s.sigma as f32).to_bits());
            r[7] = (s.seq % 65_536) as u16;
            r[8] = ((now_ns - s.t_ns).max(0) / 1_000_000).min(u16::MAX as i64) as u16;
            put32(&mut r, 10, (s.rate_mm_per_min as f32).to_bits());
        }
        r[6] = valid as u16;
        r[9] = self.heartbeat.load(Ordering::Relaxed);
        r
    }
}

impl Answer for Shared {
    fn answer(&self, req: &Request<'_>) -> Result<Response, ExceptionCode> {
        let (start, count) = match *req {
            Request::ReadInputRegisters(a, n) => (a, n),
            _ => {
                tracing::warn!("control output: refused {:?} (the control output is read-only: input registers 0–11)", req.function_code());
                return Err(ExceptionCode::IllegalFunction);
            }
        };
        let range = read_range(start, count, REGISTERS)?;
        let regs = self.registers(Instant::now(), tagdeflect_core::clock::now_epoch_ns());
        Ok(Response::ReadInputRegisters(regs[range].to_vec()))
    }
}

/// Exposure → register latency over a run, ms.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LatencySummary {
    /// Values served.
    pub values: usize,
    /// Median.
    pub p50_ms: f64,
    /// 99th percentile.
    pub p99_ms: f64,
    /// Largest.
    pub max_ms: f64,
}

/// The running control output: its server thread and the shared register block.
pub struct ControlOutput {
    addr: SocketAddr,
    shared: Arc<Shared>,
    shutdown: Option<tokio::sync::oneshot::Sender<()>>,
    thread: Option<JoinHandle<()>>,
}

impl ControlOutput {
    /// Binds the server (port 0: a free one) and starts serving; the registers read as 0
    /// (invalid) until the first line.
    pub fn start(config: &ControlConfig) -> Result<ControlOutput, ControlError> {
        let addr = config.addr().map_err(ControlError::Address)?;
        let listener = std::net::TcpListener::bind(addr).map_err(|source| ControlError::Bind { addr, source })?;
        let local = listener.local_addr().map_err(ControlError::Start)?;
        listener.set_nonblocking(true).map_err(ControlError::Start)?;
        let shared = Arc::new(Shared::new(config, 0));
        let runtime = tokio::runtime::Builder::new_current_thread().enable_all().build().map_err(ControlError::Start)?;
        let (tx, rx) = tokio::sync::oneshot::channel::<()>();
        let s = shared.clone();
        let thread = std::thread::Builder::new()
            .name("control-modbus".into())
            .spawn(move || runtime.block_on(serve(listener, s, rx)))
            .map_err(ControlError::Start)?;
        tracing::info!(addr = %local, gauge = %config.gauge, "control output serving Modbus TCP (read-only input registers 0–11)");
        Ok(ControlOutput { addr: local, shared, shutdown: Some(tx), thread: Some(thread) })
    }

    /// Where it listens.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// Takes one feed line (what the sink does).
    pub fn take_line(&self, line: &FeedLine) {
        self.shared.take_line(line, Instant::now(), tagdeflect_core::clock::now_epoch_ns());
    }

    /// The registers as a read would return them now.
    pub fn registers(&self) -> [u16; REGISTERS] {
        self.shared.registers(Instant::now(), tagdeflect_core::clock::now_epoch_ns())
    }

    /// Exposure → register latency of the values served so far.
    pub fn latency(&self) -> Option<LatencySummary> {
        let mut v = self.shared.state.lock().expect("control state").latencies_ms.clone();
        if v.is_empty() {
            return None;
        }
        v.sort_by(f32::total_cmp);
        let q = |p: f64| v[((v.len() - 1) as f64 * p).round() as usize] as f64;
        Some(LatencySummary { values: v.len(), p50_ms: q(0.5), p99_ms: q(0.99), max_ms: q(1.0) })
    }

    /// The daemon stops: valid drops to 0 and the heartbeat stops; the server keeps answering
    /// until [`shutdown`](Self::shutdown) (or drop).
    pub fn stop_values(&self) {
        self.shared.stopped.store(true, Ordering::Relaxed);
    }

    /// Stops the server (closing its connections).
    pub fn shutdown(&mut self) {
        self.stop_values();
        if let Some(tx) = self.shutdown.take() {
            let _ = tx.send(());
        }
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

impl Drop for ControlOutput {
    fn drop(&mut self) {
        self.shutdown();
    }
}

/// The control output's name in log lines; its clients are logged at INFO.
const NAME: ServerName = ServerName { name: "control output", clients_at_info: true };

async fn serve(listener: std::net::TcpListener, shared: Arc<Shared>, stop: tokio::sync::oneshot::Receiver<()>) {
    let server = tokio::net::TcpListener::from_std(listener).and_then(|l| ModbusServer::serve(l, NAME, shared.clone()));
    let mut server = match server {
        Ok(s) => s,
        Err(e) => {
            tracing::error!("control output: cannot serve: {e}");
            return;
        }
    };
    let beat = shared.clone();
    let heartbeat = async move {
        let mut tick = tokio::time::interval(HEARTBEAT);
        loop {
            tick.tick().await;
            if !beat.stopped.load(Ordering::Relaxed) {
                beat.heartbeat.fetch_add(1, Ordering::Relaxed);
            }
        }
    };
    tokio::select! {
        _ = heartbeat => {}
        _ = server.stopped() => {}
        _ = stop => {}
    }
}

/// The control output as a line sink.
pub struct ControlSink(pub Arc<Mutex<ControlOutput>>);

impl ControlSink {
    /// Starts the control output of `config` as a sink.
    pub fn start(config: &ControlConfig) -> Result<ControlSink, ControlError> {
        Ok(ControlSink(Arc::new(Mutex::new(ControlOutput::start(config)?))))
    }
}

impl LineSink for ControlSink {
    fn name(&self) -> String {
        match self.0.lock() {
            Ok(c) => format!("control output on {}", c.addr()),
            Err(_) => "control output".into(),
        }
    }

    fn accept(&mut self, finished: &Finished) {
        if let Ok(c) = self.0.lock() {
            c.take_line(&finished.line);
        }
    }

    fn finish(&mut self) {
        if let Ok(mut c) = self.0.lock() {
            // A replayed recording's lines carry the recording's times, not this clock's: no
            // latency can be read from them (register 8 then saturates at 65 535 ms too).
            if let Some(l) = c.latency().filter(|l| l.p50_ms.abs() > 3.6e6) {
                tracing::info!(
                    values = l.values,
                    "control output: the lines' times are not this computer's clock (a replayed recording): no exposure → register latency"
                );
            } else if let Some(l) = c.latency() {
                tracing::info!(
                    values = l.values,
                    p50_ms = l.p50_ms,
                    p99_ms = l.p99_ms,
                    max_ms = l.max_ms,
                    "control output: exposure → register latency"
                );
            }
            c.stop_values();
            std::thread::sleep(STOP_HOLD);
            c.shutdown();
        }
    }
}

/// Decodes the registers (as a controller would): value, µm, σ, valid, seq, age ms,
/// heartbeat, rate.
pub fn decode(r: &[u16; REGISTERS]) -> (f32, i32, f32, bool, u16, u16, u16, f32) {
    let u32_at = |at: usize| ((r[at] as u32) << 16) | r[at + 1] as u32;
    (f32::from_bits(u32_at(0)), u32_at(2) as i32, f32::from_bits(u32_at(4)), r[6] == 1, r[7], r[8], r[9], f32::from_bits(u32_at(10)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use tagdeflect_core::feed::GaugeReading;

    fn shared(gauge: &str) -> Shared {
        Shared::new(&ControlConfig { gauge: gauge.into(), ..ControlConfig::on("127.0.0.1:0") }, 7)
    }

    fn line(seq: u64, net: Option<(f64, f64)>) -> FeedLine {
        FeedLine {
            seq,
            t_ns: 1_000_000_000 + seq as i64 * 200_000_000,
            net_deflection_mm: net.map(|n| n.0),
            net_deflection_sigma_mm: net.map(|n| n.1),
            ..FeedLine::default()
        }
    }

    #[test]
    fn registers_hold_the_value_as_the_spec_says() {
        let s = shared(NET_DEFLECTION);
        let t0 = Instant::now();
        assert_eq!(s.registers(t0, 0)[6], 0, "invalid before the first value");
        let l = line(70_000, Some((1.2345, 0.002)));
        s.take_line(&l, t0, l.t_ns + 30_000_000);
        let r = s.registers(t0, l.t_ns + 45_000_000);
        let (v, um, sigma, valid, seq, age, beat, _) = decode(&r);
        assert!((v - 1.2345).abs() < 1e-6 && um == 1235 && (sigma - 0.002).abs() < 1e-9 && valid);
        assert_eq!(seq, (70_000 % 65_536) as u16);
        assert_eq!(age, 45);
        assert_eq!(beat, 7);
        // The next line 0.2 s later, 0.01 mm more: 3 mm/min.
        let l2 = line(70_001, Some((1.2445, 0.002)));
        s.take_line(&l2, t0 + Duration::from_millis(200), l2.t_ns);
        let rate = decode(&s.registers(t0 + Duration::from_millis(200), l2.t_ns)).7;
        assert!((rate - 3.0).abs() < 1e-3, "{rate}");
    }

    #[test]
    fn valid_drops_on_a_missing_value_a_large_sigma_a_stall_and_a_stop() {
        let s = shared(NET_DEFLECTION);
        let t0 = Instant::now();
        for k in 0..5 {
            let l = line(k, Some((0.1, 0.002)));
            s.take_line(&l, t0 + Duration::from_millis(200 * k), l.t_ns);
        }
        let now = t0 + Duration::from_millis(800);
        assert_eq!(s.registers(now, 0)[6], 1);
        // No frame set for 1.5 periods: invalid.
        assert_eq!(s.registers(now + Duration::from_millis(310), 0)[6], 0, "stalled");
        // A set without the tags: invalid at once (stale_sets = 1), value kept.
        let l = line(5, None);
        s.take_line(&l, now + Duration::from_millis(200), l.t_ns);
        let r = s.registers(now + Duration::from_millis(200), 0);
        assert_eq!((r[6], r[7]), (0, 4));
        // σ too large.
        let l = line(6, Some((0.1, 0.02)));
        s.take_line(&l, now + Duration::from_millis(400), l.t_ns);
        assert_eq!(s.registers(now + Duration::from_millis(400), 0)[6], 0);
        let l = line(7, Some((0.1, 0.002)));
        s.take_line(&l, now + Duration::from_millis(600), l.t_ns);
        assert_eq!(s.registers(now + Duration::from_millis(600), 0)[6], 1);
        s.stopped.store(true, Ordering::Relaxed);
        assert_eq!(s.registers(now + Duration::from_millis(600), 0)[6], 0, "stopped");
    }

    #[test]
    fn a_named_gauge_is_served_and_writes_are_refused() {
        let s = shared("cmod");
        let mut l = line(1, Some((5.0, 0.001)));
        l.gauges.insert("cmod".into(), GaugeReading::new(0.25, 0.001, "mm"));
        s.take_line(&l, Instant::now(), l.t_ns);
        let Ok(Response::ReadInputRegisters(w)) = s.answer(&Request::ReadInputRegisters(0, 12)) else { panic!("no reply") };
        assert_eq!(f32::from_bits(((w[0] as u32) << 16) | w[1] as u32), 0.25);
        assert_eq!(s.answer(&Request::WriteSingleRegister(0, 1)).unwrap_err(), ExceptionCode::IllegalFunction);
        assert_eq!(s.answer(&Request::WriteMultipleRegisters(0, vec![1, 2].into())).unwrap_err(), ExceptionCode::IllegalFunction);
        assert_eq!(s.answer(&Request::ReadHoldingRegisters(0, 2)).unwrap_err(), ExceptionCode::IllegalFunction);
        assert_eq!(s.answer(&Request::ReadInputRegisters(10, 3)).unwrap_err(), ExceptionCode::IllegalDataAddress);
    }
}
