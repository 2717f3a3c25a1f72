//! The simulated UTM (`[utm] address = "sim"`): a real Modbus TCP server on loopback
//! (tokio-modbus) that answers every register read with load and stroke at the current time,
//! encoded exactly as the configured layout says (type, word order, scale, offset), so the
//! product reads it through its ordinary Modbus client.
//!
//! Registers outside the layout read as 0. Writes, and every other function, are answered
//! with the exception "illegal function": the product never writes, and the server does not
//! accept writes from anyone else either.

use super::codec::encode;
use crate::modbus_server::{read_range, Answer, ModbusServer, ServerName};
use crate::utm::config::{RegisterConfig, RegisterKind, UtmConfig};
use std::io;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;
use tokio::task::JoinHandle;
use tokio_modbus::{ExceptionCode, Request, Response};

/// The simulated machine: `t_ns` (ns since the Unix epoch) → (load kN, stroke mm).
pub type UtmModel = Arc<dyn Fn(i64) -> (f64, f64) + Send + Sync>;

/// The simulated UTM's name in log lines.
const NAME: ServerName = ServerName { name: "simulated UTM", clients_at_info: false };

/// Serves the simulated UTM on `bind` (use port 0 for a free port) until the returned task is
/// aborted (which also closes every open connection). Returns the bound address.
pub async fn serve_sim_utm(bind: SocketAddr, layout: &UtmConfig, model: UtmModel) -> io::Result<(SocketAddr, JoinHandle<()>)> {
    serve_sim_utm_with_outage(bind, layout, model, None).await
}

/// As [`serve_sim_utm`], silent during `outage` ([start, end) in ns since the Unix epoch):
/// requests then get no reply at all, as from a machine whose cable was pulled (fault
/// injection, `[sim] utm_outage_at_s`).
pub async fn serve_sim_utm_with_outage(
    bind: SocketAddr,
    layout: &UtmConfig,
    model: UtmModel,
    outage: Option<(i64, i64)>,
) -> io::Result<(SocketAddr, JoinHandle<()>)> {
    let server = bind_sim_utm(bind, layout, model, outage).await?;
    Ok((server.addr(), server.into_task()))
}

/// The simulated UTM's server on `bind`, silent during `outage`.
async fn bind_sim_utm(bind: SocketAddr, layout: &UtmConfig, model: UtmModel, outage: Option<(i64, i64)>) -> io::Result<ModbusServer> {
    let service = Arc::new(SimService { load: layout.load.clone(), stroke: layout.stroke.clone(), model, outage });
    let server = ModbusServer::bind(bind, NAME, service).await?;
    tracing::info!(local = %server.addr(), "simulated UTM serving Modbus TCP");
    Ok(server)
}

/// `cfg` with its address replaced by `addr` (the bound simulated server).
pub(crate) fn with_address(cfg: &UtmConfig, addr: SocketAddr) -> UtmConfig {
    UtmConfig { address: crate::utm::config::UtmAddress::Tcp(addr.to_string()), ..cfg.clone() }
}

/// A running simulated UTM; stops (and closes its connections) when dropped.
#[derive(Debug)]
pub struct SimUtm {
    /// Where it listens.
    pub addr: SocketAddr,
    _server: ModbusServer,
}

impl SimUtm {
    /// Stops the server now (same as dropping it).
    pub fn stop(self) {}
}

/// Starts the simulated UTM for `cfg` (whose address is `"sim"`, or anything: it is ignored)
/// on 127.0.0.1 with a free port, and returns the config to poll it with.
pub async fn start_sim_utm(cfg: &UtmConfig, model: UtmModel) -> io::Result<(UtmConfig, SimUtm)> {
    start_sim_utm_with_outage(cfg, model, None).await
}

/// As [`start_sim_utm`], silent during `outage` (see [`serve_sim_utm_with_outage`]).
pub async fn start_sim_utm_with_outage(cfg: &UtmConfig, model: UtmModel, outage: Option<(i64, i64)>) -> io::Result<(UtmConfig, SimUtm)> {
    let server = bind_sim_utm(SocketAddr::from(([127, 0, 0, 1], 0)), cfg, model, outage).await?;
    let addr = server.addr();
    if let Some((a, b)) = outage {
        tracing::info!(
            in_s = (a - tagdeflect_core::clock::now_epoch_ns()) as f64 * 1e-9,
            for_s = (b - a) as f64 * 1e-9,
            "simulated UTM: an outage is scheduled"
        );
    }
    Ok((with_address(cfg, addr), SimUtm { addr, _server: server }))
}

/// A simple loading history for demos: load rises at `kn_per_s` from `start_ns` up to
/// `max_kn` and holds; stroke is `mm_per_kn` × load.
pub fn ramp_model(start_ns: i64, kn_per_s: f64, max_kn: f64, mm_per_kn: f64) -> UtmModel {
    Arc::new(move |t_ns: i64| {
        let s = ((t_ns - start_ns) as f64 * 1e-9).max(0.0);
        let load = (kn_per_s * s).min(max_kn);
        (load, load * mm_per_kn)
    })
}

/// Answers reads from the model.
struct SimService {
    load: RegisterConfig,
    stroke: Option<RegisterConfig>,
    model: UtmModel,
    /// Silent in [start, end) ns since the Unix epoch.
    outage: Option<(i64, i64)>,
}

impl Answer for SimService {
    fn answer(&self, req: &Request<'_>) -> Result<Response, ExceptionCode> {
        let (kind, start, count) = match *req {
            Request::ReadInputRegisters(a, n) => (RegisterKind::Input, a, n),
            Request::ReadHoldingRegisters(a, n) => (RegisterKind::Holding, a, n),
            _ => {
                tracing::warn!("simulated UTM: refused {:?} (only register reads are served)", req.function_code());
                return Err(ExceptionCode::IllegalFunction);
            }
        };
        read_range(start, count, 1 << 16)?;
        let (load, stroke) = (self.model)(tagdeflect_core::clock::now_epoch_ns());
        let mut words = vec![0u16; count as usize];
        let channels = [(Some(&self.load), load), (self.stroke.as_ref(), stroke)];
        for (reg, value) in channels {
            let Some(reg) = reg.filter(|r| r.kind == kind) else { continue };
            let encoded = encode(reg, value).map_err(|e| {
                tracing::warn!("simulated UTM: {e}");
                ExceptionCode::ServerDeviceFailure
            })?;
            for (i, w) in encoded.into_iter().enumerate() {
                let r = reg.register as usize + i;
                if r >= start as usize && r < start as usize + count as usize {
                    words[r - start as usize] = w;
                }
            }
        }
        Ok(match kind {
            RegisterKind::Input => Response::ReadInputRegisters(words),
            RegisterKind::Holding => Response::ReadHoldingRegisters(words),
        })
    }

    /// Silent during the outage: the reply comes only after it, long after the client gave up.
    fn hold(&self) -> Option<Duration> {
        let now = tagdeflect_core::clock::now_epoch_ns();
        match self.outage {
            Some((a, b)) if now >= a && now < b => Some(Duration::from_nanos((b - now) as u64)),
            _ => None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::utm::codec::decode;
    use crate::utm::config::{ValueType, WordOrder};

    fn layout() -> UtmConfig {
        UtmConfig {
            address: crate::utm::config::UtmAddress::Sim,
            unit: 1,
            poll_hz: 50.0,
            timeout_ms: 200.0,
            load: RegisterConfig {
                register: 0,
                kind: RegisterKind::Input,
                value_type: ValueType::F32,
                word_order: WordOrder::Cdab,
                scale: 1.0,
                offset: 0.0,
            },
            stroke: Some(RegisterConfig {
                register: 3,
                kind: RegisterKind::Input,
                value_type: ValueType::I32,
                word_order: WordOrder::Dcba,
                scale: 0.001,
                offset: 0.0,
            }),
        }
    }

    fn service() -> SimService {
        let l = layout();
        SimService { load: l.load, stroke: l.stroke, model: Arc::new(|_| (12.5, -1.234)), outage: None }
    }

    #[test]
    fn reads_encode_the_model_per_layout() {
        let s = service();
        let Ok(Response::ReadInputRegisters(w)) = s.answer(&Request::ReadInputRegisters(0, 6)) else { panic!("no register reply") };
        assert_eq!(w.len(), 6);
        assert_eq!(&w[0..2], &[0x0000, 0x4148]);
        assert_eq!(w[2], 0);
        assert_eq!(decode(&layout().stroke.unwrap(), &w[3..5]).unwrap(), -1.234);
        // A read that covers only half of the stroke gets that half.
        let Ok(Response::ReadInputRegisters(w)) = s.answer(&Request::ReadInputRegisters(4, 1)) else { panic!("no register reply") };
        assert_eq!(w.len(), 1);
        // Holding registers hold nothing in this layout.
        let Ok(Response::ReadHoldingRegisters(w)) = s.answer(&Request::ReadHoldingRegisters(0, 4)) else { panic!("no register reply") };
        assert_eq!(w, vec![0; 4]);
    }

    #[test]
    fn writes_and_bad_reads_are_exceptions() {
        let s = service();
        assert_eq!(s.answer(&Request::WriteSingleRegister(0, 1)).unwrap_err(), ExceptionCode::IllegalFunction);
        assert_eq!(s.answer(&Request::WriteMultipleRegisters(0, vec![1, 2].into())).unwrap_err(), ExceptionCode::IllegalFunction);
        assert_eq!(s.answer(&Request::ReadCoils(0, 1)).unwrap_err(), ExceptionCode::IllegalFunction);
        assert_eq!(s.answer(&Request::ReadInputRegisters(0, 126)).unwrap_err(), ExceptionCode::IllegalDataValue);
        assert_eq!(s.answer(&Request::ReadInputRegisters(0, 0)).unwrap_err(), ExceptionCode::IllegalDataValue);
        assert_eq!(s.answer(&Request::ReadInputRegisters(65535, 2)).unwrap_err(), ExceptionCode::IllegalDataAddress);
    }

    #[test]
    fn values_the_layout_cannot_hold_are_a_device_failure() {
        let l = layout();
        let s = SimService { load: l.load, stroke: l.stroke, model: Arc::new(|_| (1.0, 1e9)), outage: None };
        assert_eq!(s.answer(&Request::ReadInputRegisters(0, 6)).unwrap_err(), ExceptionCode::ServerDeviceFailure);
    }

    #[test]
    fn ramp_rises_and_holds() {
        let m = ramp_model(1_000_000_000, 2.0, 10.0, 0.1);
        assert_eq!(m(0), (0.0, 0.0));
        let (l, s) = m(3_000_000_000);
        assert!((l - 4.0).abs() < 1e-12 && (s - 0.4).abs() < 1e-12);
        assert_eq!(m(100_000_000_000).0, 10.0);
    }
}
