//! The analog output's Modbus TCP client: one connection to the device, the writes it sends
//! (function 16 for the value, 6 or 5 for the valid line) and why one failed. Only writes
//! to the configured registers are ever sent; every request, the connect included, runs
//! under `timeout_ms` (tokio-modbus has no timeout of its own).

use std::borrow::Cow;
use std::net::SocketAddr;
use std::time::Duration;

use tokio::time::timeout;
use tokio_modbus::client::{tcp, Client, Context, Reader};
use tokio_modbus::{Request, Response, Slave};

use tagdeflect_io::utm::codec::encode;
use tagdeflect_io::utm::config::RegisterConfig;

use super::config::{AnalogConfig, DigitalOutput};
use super::labjack_watchdog;

/// Why a write (or the connect) failed; the connection is dropped after any of them.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DeviceFault {
    /// The TCP connect failed.
    #[error("analog output {addr}: cannot connect: {detail}")]
    Connect {
        /// The device.
        addr: SocketAddr,
        /// Why.
        detail: String,
    },
    /// No answer within `timeout_ms`.
    #[error("analog output {addr}: no answer to {what} within {ms} ms")]
    Timeout {
        /// The device.
        addr: SocketAddr,
        /// The request.
        what: String,
        /// The timeout.
        ms: f64,
    },
    /// The connection failed or the reply did not match the request.
    #[error("analog output {addr}: {what}: {detail}")]
    Transport {
        /// The device.
        addr: SocketAddr,
        /// The request.
        what: String,
        /// Why.
        detail: String,
    },
    /// The device answered with a Modbus exception.
    #[error("analog output {addr}: {what}: Modbus exception {code}")]
    Exception {
        /// The device.
        addr: SocketAddr,
        /// The request.
        what: String,
        /// The exception, as tokio-modbus names it.
        code: String,
    },
    /// A value does not fit its register (cannot happen for a checked config).
    #[error("analog output {addr}: {detail}")]
    Encode {
        /// The device.
        addr: SocketAddr,
        /// Why.
        detail: String,
    },
}

/// One connection to the device (or none).
pub(super) struct Device {
    addr: SocketAddr,
    unit: u8,
    timeout: Duration,
    timeout_ms: f64,
    ctx: Option<Context>,
}

impl Device {
    pub(super) fn new(config: &AnalogConfig, addr: SocketAddr) -> Device {
        let timeout_ms = config.timeout_ms.max(1.0);
        Device { addr, unit: config.unit_id, timeout: Duration::from_secs_f64(timeout_ms / 1000.0), timeout_ms, ctx: None }
    }

    pub(super) fn connected(&self) -> bool {
        self.ctx.is_some()
    }

    pub(super) async fn connect(&mut self) -> Result<(), DeviceFault> {
        let attempt = tcp::connect_slave(self.addr, Slave(self.unit));
        let ctx = timeout(self.timeout, attempt)
            .await
            .map_err(|_| DeviceFault::Timeout { addr: self.addr, what: "connect".into(), ms: self.timeout_ms })?
            .map_err(|e| DeviceFault::Connect { addr: self.addr, detail: e.to_string() })?;
        self.ctx = Some(ctx);
        Ok(())
    }

    /// Drops the connection (no graceful disconnect: it may hang).
    pub(super) fn drop_connection(&mut self) {
        self.ctx = None;
    }

    /// Writes `raw` to the registers of `reg` (function 16).
    pub(super) async fn write_value(&mut self, reg: &RegisterConfig, raw: f64) -> Result<(), DeviceFault> {
        let words = encode(reg, raw).map_err(|e| DeviceFault::Encode { addr: self.addr, detail: e.to_string() })?;
        let what = format!("writing holding register {} ({raw})", reg.register);
        self.call(Request::WriteMultipleRegisters(reg.register, Cow::Owned(words)), &what).await
    }

    /// Sets the valid line.
    pub(super) async fn write_line(&mut self, line: DigitalOutput, on: bool) -> Result<(), DeviceFault> {
        match line {
            DigitalOutput::Register(r) => {
                self.call(Request::WriteSingleRegister(r, on as u16), &format!("writing the valid line (register {r}) {}", on as u8)).await
            }
            DigitalOutput::Coil(c) => {
                self.call(Request::WriteSingleCoil(c, on), &format!("writing the valid line (coil {c}) {}", on as u8)).await
            }
        }
    }

    /// Reads `count` holding registers from `register` (function 3; `check` only).
    pub(super) async fn read_holding(&mut self, register: u16, count: u16) -> Result<Vec<u16>, DeviceFault> {
        let addr = self.addr;
        let what = format!("reading holding registers {register}..{}", register as u32 + count as u32 - 1);
        let ctx = self.ctx.as_mut().ok_or_else(|| DeviceFault::Connect { addr, detail: "not connected".into() })?;
        let reply = timeout(self.timeout, ctx.read_holding_registers(register, count)).await.map_err(|_| DeviceFault::Timeout {
            addr,
            what: what.clone(),
            ms: self.timeout_ms,
        })?;
        match reply {
            Err(e) => Err(DeviceFault::Transport { addr, what, detail: e.to_string() }),
            Ok(Err(code)) => Err(DeviceFault::Exception { addr, what, code: format!("{code:?} ({})", u8::from(code)) }),
            Ok(Ok(words)) if words.len() == count as usize => Ok(words),
            Ok(Ok(words)) => Err(DeviceFault::Transport { addr, what, detail: format!("{} registers in the reply", words.len()) }),
        }
    }

    /// The `[output.analog] watchdog_writes`, in order, then the LabJack watchdog's plan
    /// when the device does not hold it already (`labjack_watchdog`).
    pub(super) async fn set_up(&mut self, config: &AnalogConfig) -> Result<(), DeviceFault> {
        for w in &config.watchdog_writes {
            self.write_value(&w.register_config(), w.value).await?;
        }
        let Some(plan) = labjack_watchdog::plan(config) else { return Ok(()) };
        let words = self.read_holding(labjack_watchdog::BLOCK.0, labjack_watchdog::BLOCK.1).await?;
        if labjack_watchdog::already_set(&plan, &words) {
            tracing::debug!("[output.analog] {}: the LabJack watchdog is set up already", self.addr);
            return Ok(());
        }
        for w in &plan {
            self.write_value(&w.register_config(), w.value).await?;
        }
        tracing::info!(
            "[output.analog] {}: LabJack watchdog set up: {} s without a write → valid line low{}",
            self.addr,
            config.labjack_watchdog_s.unwrap_or_default(),
            config.on_invalid.safe_v().map(|v| format!(", DAC at {v} V")).unwrap_or_default()
        );
        Ok(())
    }

    async fn call(&mut self, request: Request<'static>, what: &str) -> Result<(), DeviceFault> {
        let addr = self.addr;
        let ctx = self.ctx.as_mut().ok_or_else(|| DeviceFault::Connect { addr, detail: "not connected".into() })?;
        let reply = timeout(self.timeout, ctx.call(request.clone())).await.map_err(|_| DeviceFault::Timeout {
            addr,
            what: what.to_string(),
            ms: self.timeout_ms,
        })?;
        let transport = |detail: String| DeviceFault::Transport { addr, what: what.to_string(), detail };
        match reply {
            Err(e) => Err(transport(e.to_string())),
            Ok(Err(code)) => Err(DeviceFault::Exception { addr, what: what.to_string(), code: format!("{code:?} ({})", u8::from(code)) }),
            Ok(Ok(response)) => {
                echoes(&request, &response).then_some(()).ok_or_else(|| transport(format!("unexpected reply {response:?}")))
            }
        }
    }
}

/// The reply a write's request expects (the echo of function 5 and 6; address and count of 16).
fn echoes(request: &Request<'_>, response: &Response) -> bool {
    match (request, response) {
        (Request::WriteSingleCoil(a, v), Response::WriteSingleCoil(b, w)) => a == b && v == w,
        (Request::WriteSingleRegister(a, v), Response::WriteSingleRegister(b, w)) => a == b && v == w,
        (Request::WriteMultipleRegisters(a, words), Response::WriteMultipleRegisters(b, n)) => a == b && words.len() == *n as usize,
        _ => false,
    }
}
