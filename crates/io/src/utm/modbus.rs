//! The UTM's Modbus TCP client: a poller that reads load (and stroke) at `poll_hz`, stamps
//! each reading on the product's clock and reports the link going down and coming back.
//!
//! Only reads are ever sent (function 3 or 4). Every request, the connect included, runs
//! under `timeout_ms` (tokio-modbus has no timeout of its own); after a timeout, a dropped
//! connection, a Modbus exception or a malformed reply the client context is dropped (it may be
//! out of step) and a new connection is made with backoff (0.2 s doubling to 5 s).

use super::codec::{decode, DecodeError};
use super::UtmSample;
use crate::utm::config::{RegisterConfig, RegisterKind, UtmConfig};
use std::fmt;
use std::net::SocketAddr;
use std::time::Duration;
use tokio::sync::{mpsc, watch};
use tokio::time::{timeout, Instant, MissedTickBehavior};
use tokio_modbus::client::{tcp, Client, Context};
use tokio_modbus::{ExceptionCode, Request, Response, Slave};

/// Largest number of registers one Modbus read may ask for.
pub(crate) const MAX_READ_REGISTERS: u16 = 125;
/// First reconnect delay.
pub(crate) const BACKOFF_MIN: Duration = Duration::from_millis(200);
/// Longest reconnect delay.
pub(crate) const BACKOFF_MAX: Duration = Duration::from_secs(5);

/// What the poller reports.
#[derive(Debug, Clone, PartialEq)]
pub enum UtmEvent {
    /// A reading.
    Sample(UtmSample),
    /// The UTM became unreachable or answers wrongly; sent once per outage (and once at
    /// start when the first attempt fails).
    Down {
        /// What went wrong, naming the address and register.
        reason: String,
    },
    /// The UTM answers again (sent before the first sample after start or after `Down`).
    Up,
}

/// Error that stops the poller before it starts (bad configuration); link faults never stop it.
#[derive(Debug, thiserror::Error)]
pub enum PollerError {
    /// `address = "sim"` must be replaced by the simulated server's address first
    /// (see [`super::sim_server::start_sim_utm`]).
    #[error("utm.address is \"sim\": start the simulated UTM and poll the address it is bound to")]
    SimAddress,
}

/// One Modbus read.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ReadRequest {
    /// Register table.
    pub kind: RegisterKind,
    /// First register (0-based).
    pub start: u16,
    /// Number of registers (1..=125).
    pub count: u16,
}

impl fmt::Display for ReadRequest {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let table = match self.kind {
            RegisterKind::Input => "input",
            RegisterKind::Holding => "holding",
        };
        write!(f, "{table} registers {}..{}", self.start, self.start as u32 + self.count as u32 - 1)
    }
}

/// The reads that fetch load and stroke: one when both are in the same table and fit in one
/// read of at most 125 registers, two otherwise.
#[derive(Debug, Clone, PartialEq)]
pub struct ReadPlan {
    /// The reads, in the order they are sent.
    pub reads: Vec<ReadRequest>,
    load: Slot,
    stroke: Option<Slot>,
}

/// Where a channel's registers are in the replies: read index and offset in it.
#[derive(Debug, Clone, PartialEq)]
struct Slot {
    read: usize,
    offset: usize,
    reg: RegisterConfig,
}

impl ReadPlan {
    /// Plans the reads of `cfg`'s load and stroke.
    pub fn new(cfg: &UtmConfig) -> Self {
        let span = |r: &RegisterConfig| (r.register as u32, r.register as u32 + r.value_type.registers() as u32);
        let single = |r: &RegisterConfig| {
            let (a, b) = span(r);
            ReadRequest { kind: r.kind, start: a as u16, count: (b - a) as u16 }
        };
        let load = &cfg.load;
        let Some(stroke) = &cfg.stroke else {
            return Self { reads: vec![single(load)], load: Slot { read: 0, offset: 0, reg: load.clone() }, stroke: None };
        };
        let (la, lb) = span(load);
        let (sa, sb) = span(stroke);
        let (a, b) = (la.min(sa), lb.max(sb));
        if load.kind == stroke.kind && b - a <= MAX_READ_REGISTERS as u32 {
            let read = ReadRequest { kind: load.kind, start: a as u16, count: (b - a) as u16 };
            Self {
                reads: vec![read],
                load: Slot { read: 0, offset: (la - a) as usize, reg: load.clone() },
                stroke: Some(Slot { read: 0, offset: (sa - a) as usize, reg: stroke.clone() }),
            }
        } else {
            Self {
                reads: vec![single(load), single(stroke)],
                load: Slot { read: 0, offset: 0, reg: load.clone() },
                stroke: Some(Slot { read: 1, offset: 0, reg: stroke.clone() }),
            }
        }
    }

    /// Decodes load and stroke from the replies to [`Self::reads`] (same order).
    pub fn decode(&self, replies: &[Vec<u16>]) -> Result<(f64, Option<f64>), DecodeError> {
        let value = |s: &Slot| {
            let words = replies.get(s.read).map(|w| w.get(s.offset..).unwrap_or(&[])).unwrap_or(&[]);
            decode(&s.reg, words)
        };
        let load = value(&self.load)?;
        let stroke = match &self.stroke {
            Some(s) => Some(value(s)?),
            None => None,
        };
        Ok((load, stroke))
    }
}

/// Why one poll failed.
#[derive(Debug, thiserror::Error)]
pub enum PollFault {
    /// Name resolution or TCP connect failed.
    #[error("UTM {address}: cannot connect: {detail}")]
    Connect {
        /// Configured address.
        address: String,
        /// The cause.
        detail: String,
    },
    /// No answer within `timeout_ms`.
    #[error("UTM {address}: no answer to {what} within {ms} ms")]
    Timeout {
        /// Configured address.
        address: String,
        /// The request (connect or a read).
        what: String,
        /// The timeout.
        ms: f64,
    },
    /// The connection failed or the reply did not match the request.
    #[error("UTM {address}: reading {request}: {detail}")]
    Transport {
        /// Configured address.
        address: String,
        /// The read.
        request: ReadRequest,
        /// The cause.
        detail: String,
    },
    /// The device answered with a Modbus exception.
    #[error("UTM {address}: reading {request}: Modbus exception {code} ({name})")]
    Exception {
        /// Configured address.
        address: String,
        /// The read.
        request: ReadRequest,
        /// Exception code.
        code: u8,
        /// Its name.
        name: String,
    },
    /// The reply has the wrong type or number of registers.
    #[error("UTM {address}: reading {request}: bad reply: {detail}")]
    BadReply {
        /// Configured address.
        address: String,
        /// The read.
        request: ReadRequest,
        /// What was wrong.
        detail: String,
    },
    /// The reply could not be decoded at all (the client library failed on it).
    #[error("UTM {address}: malformed reply: {detail}")]
    Malformed {
        /// Configured address.
        address: String,
        /// What failed.
        detail: String,
    },
    /// The registers do not decode to a value.
    #[error("UTM {address}: {source}")]
    Decode {
        /// Configured address.
        address: String,
        /// The decoding error (names the register).
        source: DecodeError,
    },
}

/// The poller's connection to the UTM.
struct Link {
    cfg: UtmConfig,
    plan: ReadPlan,
    timeout: Duration,
    ctx: Option<Context>,
}

impl Link {
    async fn connect(&mut self) -> Result<(), PollFault> {
        let address = self.cfg.address.to_string();
        let unit = self.cfg.unit;
        let attempt = async {
            let addrs: Vec<SocketAddr> = tokio::net::lookup_host(address.as_str())
                .await
                .map_err(|e| PollFault::Connect { address: address.clone(), detail: format!("cannot resolve: {e}") })?
                .collect();
            let mut last = format!("\"{address}\" resolves to no address");
            for a in addrs {
                match tcp::connect_slave(a, Slave(unit)).await {
                    Ok(ctx) => return Ok(ctx),
                    Err(e) => last = format!("{a}: {e}"),
                }
            }
            Err(PollFault::Connect { address: address.clone(), detail: last })
        };
        let ctx = timeout(self.timeout, attempt).await.map_err(|_| PollFault::Timeout {
            address: address.clone(),
            what: "connect".into(),
            ms: self.cfg.timeout_ms,
        })??;
        self.ctx = Some(ctx);
        Ok(())
    }

    /// One poll: every read of the plan; the sample time is the middle of the exchange.
    async fn poll(&mut self) -> Result<UtmSample, PollFault> {
        if self.ctx.is_none() {
            self.connect().await?;
        }
        let address = self.cfg.address.to_string();
        let t0 = tagdeflect_core::clock::now_epoch_ns();
        let mut replies = Vec::with_capacity(self.plan.reads.len());
        for &request in &self.plan.reads {
            let ctx = self.ctx.as_mut().ok_or_else(|| PollFault::Connect { address: address.clone(), detail: "not connected".into() })?;
            let call = match request.kind {
                RegisterKind::Input => Request::ReadInputRegisters(request.start, request.count),
                RegisterKind::Holding => Request::ReadHoldingRegisters(request.start, request.count),
            };
            let reply = timeout(self.timeout, ctx.call(call)).await.map_err(|_| PollFault::Timeout {
                address: address.clone(),
                what: request.to_string(),
                ms: self.cfg.timeout_ms,
            })?;
            let words = match reply {
                Err(e) => return Err(PollFault::Transport { address, request, detail: transport_detail(&e) }),
                Ok(Err(code)) => {
                    return Err(PollFault::Exception { address, request, code: u8::from(code), name: exception_name(code) });
                }
                Ok(Ok(Response::ReadInputRegisters(w))) if request.kind == RegisterKind::Input => w,
                Ok(Ok(Response::ReadHoldingRegisters(w))) if request.kind == RegisterKind::Holding => w,
                Ok(Ok(other)) => {
                    return Err(PollFault::BadReply { address, request, detail: format!("unexpected response {other:?}") });
                }
            };
            if words.len() < request.count as usize {
                let detail = format!("{} register(s) instead of {}", words.len(), request.count);
                return Err(PollFault::BadReply { address, request, detail });
            }
            replies.push(words);
        }
        let t1 = tagdeflect_core::clock::now_epoch_ns();
        let (load_kn, stroke_mm) = self.plan.decode(&replies).map_err(|source| PollFault::Decode { address, source })?;
        Ok(UtmSample { t_ns: t0 + (t1 - t0) / 2, load_kn, stroke_mm })
    }

    fn drop_connection(&mut self) {
        // Dropping the context closes the socket; no graceful disconnect (it may hang).
        self.ctx = None;
    }
}

/// Words a client error: tokio-modbus reports a connection closed by the peer with whatever
/// `errno` was last set (EAGAIN, EINPROGRESS), which would only confuse.
fn transport_detail(e: &tokio_modbus::Error) -> String {
    match e {
        tokio_modbus::Error::Transport(io) => {
            let stale_errno = io.kind() == std::io::ErrorKind::WouldBlock || io.raw_os_error() == Some(libc::EINPROGRESS);
            if stale_errno || io.kind() == std::io::ErrorKind::UnexpectedEof {
                "connection closed by the device".to_string()
            } else {
                format!("connection lost: {io}")
            }
        }
        tokio_modbus::Error::Protocol(p) => format!("reply does not match the request: {p}"),
    }
}

fn exception_name(code: ExceptionCode) -> String {
    match code {
        ExceptionCode::IllegalFunction => "illegal function".into(),
        ExceptionCode::IllegalDataAddress => "illegal data address: register not mapped on the device".into(),
        ExceptionCode::IllegalDataValue => "illegal data value".into(),
        ExceptionCode::ServerDeviceFailure => "server device failure".into(),
        ExceptionCode::Acknowledge => "acknowledge".into(),
        ExceptionCode::ServerDeviceBusy => "server device busy".into(),
        ExceptionCode::MemoryParityError => "memory parity error".into(),
        ExceptionCode::GatewayPathUnavailable => "gateway path unavailable".into(),
        ExceptionCode::GatewayTargetDevice => "gateway target device failed to respond".into(),
        ExceptionCode::Custom(c) => format!("custom code {c}"),
    }
}

/// Link state as last reported.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Reported {
    Nothing,
    Up,
    Down,
}

/// Polls the UTM of `cfg` at `cfg.poll_hz` until `shutdown` turns true (or its sender is
/// dropped, or `tx` is closed), sending [`UtmEvent`]s on `tx`.
///
/// Samples are sent with `try_send`: when the receiver lags, samples are dropped (counted in
/// the log) rather than delaying the polls; `Up`/`Down` are always delivered. Returns an error
/// only for an unusable configuration (`address = "sim"`); link faults are reported as `Down`
/// and retried forever.
pub async fn run_poller(cfg: UtmConfig, tx: mpsc::Sender<UtmEvent>, mut shutdown: watch::Receiver<bool>) -> Result<(), PollerError> {
    if cfg.address.is_sim() {
        return Err(PollerError::SimAddress);
    }
    let period = Duration::from_secs_f64(1.0 / cfg.poll_hz.clamp(1e-3, 1000.0));
    let plan = ReadPlan::new(&cfg);
    let reads: Vec<String> = plan.reads.iter().map(|r| r.to_string()).collect();
    tracing::info!(address = %cfg.address, unit = cfg.unit, poll_hz = cfg.poll_hz, reads = ?reads, "UTM poller started");
    let mut link = Link { timeout: Duration::from_secs_f64(cfg.timeout_ms.max(1.0) / 1000.0), plan, cfg, ctx: None };
    let address = link.cfg.address.clone();
    let mut reported = Reported::Nothing;
    let mut last_reason = String::new();
    let mut backoff = tagdeflect_core::backoff::Backoff::new(BACKOFF_MIN, BACKOFF_MAX);
    let mut dropped: u64 = 0;
    let mut ticks = tokio::time::interval(period);
    ticks.set_missed_tick_behavior(MissedTickBehavior::Delay);

    loop {
        if *shutdown.borrow() {
            break;
        }
        tokio::select! {
            _ = ticks.tick() => {}
            r = shutdown.changed() => if r.is_err() || *shutdown.borrow() { break } else { continue },
        }
        let result = tokio::select! {
            r = poll_guarded(&mut link) => r,
            r = shutdown.changed() => {
                // The poll was cancelled mid-request: its connection may be out of step.
                link.drop_connection();
                if r.is_err() || *shutdown.borrow() { break } else { continue }
            }
        };
        match result {
            Ok(sample) => {
                backoff.reset();
                if reported != Reported::Up {
                    tracing::info!(address = %address, "UTM up");
                    reported = Reported::Up;
                    last_reason.clear();
                    if !deliver(&tx, UtmEvent::Up, &mut shutdown).await {
                        break;
                    }
                }
                match tx.try_send(UtmEvent::Sample(sample)) {
                    Ok(()) => {}
                    Err(mpsc::error::TrySendError::Full(_)) => {
                        dropped += 1;
                        if dropped.is_power_of_two() {
                            tracing::warn!(address = %address, dropped, "UTM samples dropped: the receiver lags behind the poller");
                        }
                    }
                    Err(mpsc::error::TrySendError::Closed(_)) => break,
                }
            }
            Err(fault) => {
                link.drop_connection();
                let reason = fault.to_string();
                let delay = backoff.next_delay();
                if reason != last_reason {
                    tracing::error!(retry_in_ms = delay.as_millis() as u64, "{reason}");
                } else {
                    tracing::debug!(retry_in_ms = delay.as_millis() as u64, "{reason}");
                }
                last_reason = reason.clone();
                if reported != Reported::Down {
                    reported = Reported::Down;
                    if !deliver(&tx, UtmEvent::Down { reason }, &mut shutdown).await {
                        break;
                    }
                }
                let wake = Instant::now() + delay;
                tokio::select! {
                    _ = tokio::time::sleep_until(wake) => {}
                    r = shutdown.changed() => if r.is_err() || *shutdown.borrow() { break },
                }
                ticks.reset_immediately();
            }
        }
    }
    link.drop_connection();
    tracing::info!(address = %address, "UTM poller stopped");
    Ok(())
}

/// One poll of `link`, with a panic inside the Modbus client library turned into a fault.
///
/// tokio-modbus 0.15 panics (index out of bounds in `unpack_coils`) when a reply claims
/// more coil bytes than it carries — a reply to a request the poller never sent, from a
/// device out of step or a noisy serial gateway (upstream issue slowtec/tokio-modbus#298;
/// found by the `modbus_peer` fuzz target). Such a panic must not end the poller (the test
/// would go on without load, silently): the reply is reported as malformed, the connection
/// is dropped and re-made like after any other bad reply.
async fn poll_guarded(link: &mut Link) -> Result<UtmSample, PollFault> {
    use futures_util::FutureExt;
    match std::panic::AssertUnwindSafe(link.poll()).catch_unwind().await {
        Ok(r) => r,
        Err(panic) => {
            let what = panic
                .downcast_ref::<String>()
                .map(String::as_str)
                .or_else(|| panic.downcast_ref::<&str>().copied())
                .unwrap_or("a panic")
                .to_string();
            Err(PollFault::Malformed {
                address: link.cfg.address.to_string(),
                detail: format!("the Modbus client library failed on the reply ({what})"),
            })
        }
    }
}

/// Sends a state event, waiting for room unless shutdown comes first; false = stop polling.
async fn deliver(tx: &mpsc::Sender<UtmEvent>, event: UtmEvent, shutdown: &mut watch::Receiver<bool>) -> bool {
    loop {
        tokio::select! {
            permit = tx.reserve() => {
                return match permit {
                    Ok(p) => {
                        p.send(event);
                        true
                    }
                    Err(_) => false,
                };
            }
            r = shutdown.changed() => if r.is_err() || *shutdown.borrow() { return false },
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::utm::config::{ValueType, WordOrder};

    fn reg(register: u16, kind: RegisterKind, value_type: ValueType) -> RegisterConfig {
        RegisterConfig { register, kind, value_type, word_order: WordOrder::Abcd, scale: 1.0, offset: 0.0 }
    }

    fn cfg(load: RegisterConfig, stroke: Option<RegisterConfig>) -> UtmConfig {
        UtmConfig { address: "127.0.0.1:502".into(), unit: 1, poll_hz: 50.0, timeout_ms: 200.0, load, stroke }
    }

    #[test]
    fn load_and_stroke_in_one_table_are_one_read() {
        let p = ReadPlan::new(&cfg(reg(10, RegisterKind::Input, ValueType::F32), Some(reg(2, RegisterKind::Input, ValueType::I16))));
        assert_eq!(p.reads, vec![ReadRequest { kind: RegisterKind::Input, start: 2, count: 10 }]);
        let mut w = vec![0u16; 10];
        w[0] = 0xFFFE; // stroke i16 -2 at register 2
        w[8] = 0x4148; // load f32 12.5 at registers 10-11
        assert_eq!(p.decode(&[w]).unwrap(), (12.5, Some(-2.0)));
        assert_eq!(p.reads[0].to_string(), "input registers 2..11");
    }

    #[test]
    fn far_apart_or_different_tables_are_two_reads() {
        let far = ReadPlan::new(&cfg(reg(0, RegisterKind::Holding, ValueType::F32), Some(reg(124, RegisterKind::Holding, ValueType::U32))));
        assert_eq!(far.reads.len(), 2);
        let edge =
            ReadPlan::new(&cfg(reg(0, RegisterKind::Holding, ValueType::F32), Some(reg(123, RegisterKind::Holding, ValueType::U32))));
        assert_eq!(edge.reads, vec![ReadRequest { kind: RegisterKind::Holding, start: 0, count: 125 }]);
        let tables = ReadPlan::new(&cfg(reg(0, RegisterKind::Input, ValueType::F32), Some(reg(10, RegisterKind::Holding, ValueType::I32))));
        assert_eq!(
            tables.reads,
            vec![
                ReadRequest { kind: RegisterKind::Input, start: 0, count: 2 },
                ReadRequest { kind: RegisterKind::Holding, start: 10, count: 2 }
            ]
        );
        let got = tables.decode(&[vec![0x4148, 0], vec![0xFFFF, 0x9E58]]).unwrap();
        assert_eq!(got, (12.5, Some(-25000.0)));
        // A short reply is a decode error, not a panic.
        assert!(tables.decode(&[vec![0x4148, 0], vec![0xFFFF]]).is_err());
        assert!(tables.decode(&[]).is_err());
        let only_load = ReadPlan::new(&cfg(reg(65534, RegisterKind::Input, ValueType::U32), None));
        assert_eq!(only_load.reads, vec![ReadRequest { kind: RegisterKind::Input, start: 65534, count: 2 }]);
        assert_eq!(only_load.decode(&[vec![0, 7]]).unwrap(), (7.0, None));
    }

    #[tokio::test]
    async fn sim_address_is_refused() {
        let (tx, _rx) = mpsc::channel(4);
        let (_stop, stop_rx) = watch::channel(false);
        let mut c = cfg(reg(0, RegisterKind::Input, ValueType::F32), None);
        c.address = "sim".into();
        assert!(matches!(run_poller(c, tx, stop_rx).await, Err(PollerError::SimAddress)));
    }
}
