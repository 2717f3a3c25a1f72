//! A simulated testing machine with an actuator, for closing the loop in simulation: a
//! controller (a separate process, over Modbus TCP as a real one) commands the actuator's
//! stroke rate; the specimen, in series with the machine's compliance, answers with its
//! deflection and load under the rig's load law (a first crack, then softening).
//!
//! Mechanics: the stroke `s` is the specimen's midspan deflection `δ` plus the machine's
//! elastic give, `s = δ + C P(δ)` (C = `compliance_mm_per_kn`, P the law of
//! [`load_at`](crate::law)). At the first crack the load drops, the frame springs back and
//! δ jumps — what a controller on stroke alone cannot prevent and one on δ must correct.
//!
//! Registers of its Modbus TCP server ([`serve_machine`]):
//!
//! | registers | kind | value |
//! | --- | --- | --- |
//! | 0–1 | holding (read/write) | commanded stroke rate, f32, mm/min (clamped to ±`max_rate`) |
//! | 0–1 | input | load, f32, kN |
//! | 2–3 | input | stroke, f32, mm |

use std::io;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};

use tagdeflect_io::modbus_server::{Answer, ModbusServer, ServerName};
use tokio_modbus::{ExceptionCode, Request, Response};

use crate::law::load_at;
use crate::SimParams;

/// One moment of the machine's history.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct MachineSample {
    /// Time, ns since the Unix epoch.
    pub t_ns: i64,
    /// Stroke, mm.
    pub stroke_mm: f64,
    /// The specimen's true midspan deflection, mm.
    pub deflection_mm: f64,
    /// Load, kN.
    pub load_kn: f64,
    /// The stroke rate in force, mm/min.
    pub command_mm_per_min: f64,
}

#[derive(Debug)]
struct State {
    now: MachineSample,
    history: Vec<MachineSample>,
}

/// The simulated machine (see the module docs).
#[derive(Debug)]
pub struct SimMachine {
    params: SimParams,
    max_rate: f64,
    state: Mutex<State>,
}

impl SimMachine {
    /// A machine at rest at `t_ns` with the specimen of `params` (its load law, stiffness
    /// and the machine's compliance); the actuator's rate is limited to ±`max_rate` mm/min.
    pub fn new(params: &SimParams, t_ns: i64, max_rate: f64) -> SimMachine {
        let now = MachineSample { t_ns, stroke_mm: 0.0, deflection_mm: 0.0, load_kn: 0.0, command_mm_per_min: 0.0 };
        SimMachine { params: params.clone(), max_rate, state: Mutex::new(State { now, history: vec![now] }) }
    }

    /// Moves the actuator on to `t_ns` at the commanded rate and returns the state then.
    pub fn advance(&self, t_ns: i64) -> MachineSample {
        let mut st = self.state.lock().expect("machine state");
        let dt = (t_ns - st.now.t_ns) as f64 * 1e-9;
        if dt <= 0.0 {
            return st.now;
        }
        let stroke = st.now.stroke_mm + st.now.command_mm_per_min / 60.0 * dt;
        let d = self.deflection_at(stroke, st.now.deflection_mm);
        st.now = MachineSample {
            t_ns,
            stroke_mm: stroke,
            deflection_mm: d,
            load_kn: load_at(&self.params, d).max(0.0),
            command_mm_per_min: st.now.command_mm_per_min,
        };
        let now = st.now;
        st.history.push(now);
        now
    }

    /// Sets the commanded stroke rate (mm/min), clamped; from `t_ns` on.
    pub fn command(&self, t_ns: i64, mm_per_min: f64) {
        self.advance(t_ns);
        let v = if mm_per_min.is_finite() { mm_per_min.clamp(-self.max_rate, self.max_rate) } else { 0.0 };
        self.state.lock().expect("machine state").now.command_mm_per_min = v;
    }

    /// The history so far (one sample per advance).
    pub fn history(&self) -> Vec<MachineSample> {
        self.state.lock().expect("machine state").history.clone()
    }

    /// The deflection at stroke `s`: the root of `δ + C P(δ) = s` on the branch the
    /// specimen is on (searched from just below the previous δ; a crack does not heal).
    fn deflection_at(&self, s: f64, previous: f64) -> f64 {
        let c = self.params.compliance_mm_per_kn;
        let f = |d: f64| d + c * load_at(&self.params, d.max(0.0)) - s;
        let mut lo = (previous - 0.05).max(0.0);
        if f(lo) > 0.0 {
            lo = 0.0;
            if f(lo) >= 0.0 {
                return 0.0;
            }
        }
        let mut hi = s.max(lo) + 1.0;
        while f(hi) < 0.0 {
            hi += 1.0;
        }
        // The first crossing: bisection keeps f(lo) < 0 ≤ f(hi).
        for _ in 0..80 {
            let mid = 0.5 * (lo + hi);
            if f(mid) < 0.0 {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        hi
    }
}

impl Answer for SimMachine {
    fn answer(&self, req: &Request<'_>) -> Result<Response, ExceptionCode> {
        let now = tagdeflect_core::clock::now_epoch_ns();
        let words = |v: f32| {
            let b = v.to_bits();
            [(b >> 16) as u16, b as u16]
        };
        match *req {
            Request::ReadInputRegisters(a, n) => {
                let s = self.advance(now);
                let mut regs = [0u16; 4];
                regs[0..2].copy_from_slice(&words(s.load_kn as f32));
                regs[2..4].copy_from_slice(&words(s.stroke_mm as f32));
                let (a, n) = (a as usize, n as usize);
                if n == 0 || a + n > regs.len() {
                    return Err(ExceptionCode::IllegalDataAddress);
                }
                Ok(Response::ReadInputRegisters(regs[a..a + n].to_vec()))
            }
            Request::ReadHoldingRegisters(0, 2) => {
                let s = self.advance(now);
                Ok(Response::ReadHoldingRegisters(words(s.command_mm_per_min as f32).to_vec()))
            }
            Request::WriteMultipleRegisters(0, ref w) if w.len() == 2 => {
                let v = f32::from_bits(((w[0] as u32) << 16) | w[1] as u32);
                self.command(now, v as f64);
                Ok(Response::WriteMultipleRegisters(0, 2))
            }
            Request::ReadHoldingRegisters(..) | Request::WriteMultipleRegisters(..) => Err(ExceptionCode::IllegalDataAddress),
            _ => Err(ExceptionCode::IllegalFunction),
        }
    }
}

/// Serves `machine` on `bind` (port 0: a free one) until the returned task is aborted (which
/// also closes its connections).
pub async fn serve_machine(bind: SocketAddr, machine: Arc<SimMachine>) -> io::Result<(SocketAddr, tokio::task::JoinHandle<()>)> {
    let server = ModbusServer::bind(bind, ServerName { name: "simulated machine", clients_at_info: false }, machine).await?;
    Ok((server.addr(), server.into_task()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::LoadLaw;

    fn params() -> SimParams {
        SimParams {
            load_law: LoadLaw::Softening,
            stiffness_kn_per_mm: 60.0,
            crack_deflection_mm: 0.2,
            compliance_mm_per_kn: 0.01,
            softening_mm: 0.3,
            ..SimParams::default()
        }
    }

    #[test]
    fn stroke_splits_into_deflection_and_the_frames_give_and_the_crack_makes_a_jump() {
        let m = SimMachine::new(&params(), 0, 100.0);
        m.command(0, 6.0); // 0.1 mm/s
        let mut last = m.advance(0);
        let mut jump: f64 = 0.0;
        for k in 1..=100 {
            let s = m.advance(k * 50_000_000);
            assert!((s.stroke_mm - 0.1 * k as f64 * 0.05).abs() < 1e-9);
            let c = params().compliance_mm_per_kn;
            assert!((s.deflection_mm + c * s.load_kn - s.stroke_mm).abs() < 1e-6, "{s:?}");
            jump = jump.max(s.deflection_mm - last.deflection_mm);
            last = s;
        }
        // The elastic part: δ = s / (1 + C k); the crack's drop of 10 % of Pc = 12 kN → 0.012 mm.
        assert!(jump > 0.01, "the first crack's jump: {jump}");
        assert!(last.load_kn < 0.95 * 60.0 * 0.2);
    }

    #[test]
    fn commands_are_clamped_and_writes_go_through_modbus_requests() {
        let m = SimMachine::new(&params(), 0, 10.0);
        m.command(0, 50.0);
        assert_eq!(m.advance(60_000_000_000).stroke_mm, 10.0);
        let w = [(1.5f32.to_bits() >> 16) as u16, 1.5f32.to_bits() as u16];
        assert!(m.answer(&Request::WriteMultipleRegisters(0, w.to_vec().into())).is_ok());
        assert!(m.answer(&Request::WriteSingleRegister(0, 1)).is_err());
    }
}
