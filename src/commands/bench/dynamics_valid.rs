//! `bench --dynamics --analog ADDR`: what the analog output's valid line does on a lost
//! camera, a stalled pipeline and a device fault, timed on the device's acknowledgements
//! (the analog output's own record of when each write of the line was acknowledged).
//!
//! Frame sets come at 30 per second on the wall clock into an [`AnalogOutput`] writing to
//! the device at ADDR through a loopback TCP relay; the relay cuts the connection (and
//! refuses new ones) to make the device fault, then lets it through again.

use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{anyhow, Context, Result};
use serde::Serialize;
use tagdeflect_core::feed::FeedLine;
use tagdeflect_sinks::analog_output::{AnalogConfig, AnalogOutput};

use super::dynamics::DYNAMICS_FPS;
use super::percentile;

/// Times of each event, repeated.
const REPEATS: usize = 5;
/// Longest wait for the line, s.
const WAIT_S: f64 = 10.0;

/// The valid line's timings, ms (median and worst of [`REPEATS`] events, one device fault).
#[derive(Debug, Clone, Serialize)]
pub struct ValidLineFigures {
    /// Lost camera: the first frame set without the value → the line low acknowledged.
    pub lost_camera_ms: [f64; 2],
    /// Stalled pipeline: the next frame set due → the line low acknowledged.
    pub stall_from_due_ms: [f64; 2],
    /// The same from the last frame set.
    pub stall_from_last_ms: [f64; 2],
    /// Device fault (connection cut): the cut → the fault seen by the output.
    pub fault_detected_ms: f64,
    /// What the line did at the device during the fault (it cannot be written).
    pub fault_line: String,
    /// The device back → the line low acknowledged (written first on reconnect).
    pub back_low_ms: f64,
    /// The device back → the line high again (the next valid value).
    pub back_high_ms: f64,
}

/// A loopback relay to the device that can cut every connection.
struct Relay {
    addr: SocketAddr,
    cut: Arc<AtomicBool>,
    conns: Arc<Mutex<Vec<tokio::task::AbortHandle>>>,
    runtime: tokio::runtime::Runtime,
}

impl Relay {
    fn start(device: SocketAddr) -> Result<Relay> {
        let runtime = tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build()?;
        let listener = runtime.block_on(tokio::net::TcpListener::bind("127.0.0.1:0"))?;
        let addr = listener.local_addr()?;
        let (cut, conns) = (Arc::new(AtomicBool::new(false)), Arc::new(Mutex::new(Vec::new())));
        let (c, k) = (cut.clone(), conns.clone());
        runtime.spawn(async move {
            while let Ok((mut inbound, _)) = listener.accept().await {
                if c.load(Ordering::SeqCst) {
                    continue; // dropped: refused while cut
                }
                let task = tokio::spawn(async move {
                    if let Ok(mut out) = tokio::net::TcpStream::connect(device).await {
                        let _ = tokio::io::copy_bidirectional(&mut inbound, &mut out).await;
                    }
                });
                k.lock().expect("relay").push(task.abort_handle());
            }
        });
        Ok(Relay { addr, cut, conns, runtime })
    }

    fn set_cut(&self, on: bool) {
        self.cut.store(on, Ordering::SeqCst);
        if on {
            for c in self.conns.lock().expect("relay").drain(..) {
                c.abort();
            }
        }
    }
}

/// Frame sets at 30 per second into the output.
struct Pacer<'a> {
    out: &'a AnalogOutput,
    seq: u64,
    next: Instant,
}

impl Pacer<'_> {
    /// Waits for the next set's time, gives it (`value` or none) and returns when it was given.
    fn give(&mut self, value: Option<f64>) -> Instant {
        if let Some(w) = self.next.checked_duration_since(Instant::now()) {
            std::thread::sleep(w);
        }
        let at = Instant::now();
        let line = FeedLine {
            seq: self.seq,
            t_ns: tagdeflect_core::clock::now_epoch_ns(),
            net_deflection_mm: value,
            net_deflection_sigma_mm: value.map(|_| 0.002),
            ..FeedLine::default()
        };
        self.out.take_line(&line);
        self.seq += 1;
        self.next += Duration::from_secs_f64(1.0 / DYNAMICS_FPS);
        at
    }

    /// Gives sets of `value` until the line is acknowledged `on` after `since`; its time.
    fn until_line(&mut self, value: Option<f64>, on: bool, since: Instant) -> Result<Instant> {
        let deadline = Instant::now() + Duration::from_secs_f64(WAIT_S);
        loop {
            let st = self.out.status();
            if let Some(at) = (if on { st.line_high_at } else { st.line_low_at }).filter(|at| *at >= since) {
                return Ok(at);
            }
            if Instant::now() > deadline {
                return Err(anyhow!("the valid line was not acknowledged {} within {WAIT_S} s", if on { "high" } else { "low" }));
            }
            self.give(value);
        }
    }
}

/// Waits (without frame sets) until the line is acknowledged low after `since`.
fn line_low_after(out: &AnalogOutput, since: Instant) -> Result<Instant> {
    let deadline = Instant::now() + Duration::from_secs_f64(WAIT_S);
    while Instant::now() < deadline {
        if let Some(at) = out.status().line_low_at.filter(|at| *at >= since) {
            return Ok(at);
        }
        std::thread::sleep(Duration::from_micros(200));
    }
    Err(anyhow!("the valid line was not acknowledged low within {WAIT_S} s of the stall"))
}

fn ms(a: Instant, b: Instant) -> f64 {
    b.saturating_duration_since(a).as_secs_f64() * 1e3
}

fn median_max(mut v: Vec<f64>) -> [f64; 2] {
    v.sort_by(f64::total_cmp);
    [percentile(&v, 0.5), v.last().copied().unwrap_or(f64::NAN)]
}

/// Measures the valid line's timings against the device at `device` (LabJack T-series map).
pub fn valid_line_figures(device: &str) -> Result<ValidLineFigures> {
    let addr: SocketAddr = device.parse().with_context(|| format!("--analog {device}: expected IP:PORT"))?;
    let relay = Relay::start(addr)?;
    let config = AnalogConfig { offset_v: 1.0, ..AnalogConfig::labjack(&relay.addr.to_string(), 1.0) };
    let mut out = AnalogOutput::start(&config)?;
    let mut p = Pacer { out: &out, seq: 0, next: Instant::now() };
    let (mut lost, mut due, mut last) = (Vec::new(), Vec::new(), Vec::new());
    for _ in 0..REPEATS {
        p.until_line(Some(0.1), true, Instant::now())?;
        let event = p.give(None);
        lost.push(ms(event, p.until_line(None, false, event)?));
        p.until_line(Some(0.1), true, Instant::now())?;
        for _ in 0..5 {
            p.give(Some(0.1));
        }
        let given = p.give(Some(0.1));
        let due_at = given + Duration::from_secs_f64(1.0 / DYNAMICS_FPS);
        let low = line_low_after(p.out, given)?;
        due.push(ms(due_at, low));
        last.push(ms(given, low));
        p.next = Instant::now();
    }
    let fault = device_fault(&mut p, &relay)?;
    drop(p);
    out.shutdown();
    relay.runtime.shutdown_background();
    Ok(ValidLineFigures {
        lost_camera_ms: median_max(lost),
        stall_from_due_ms: median_max(due),
        stall_from_last_ms: median_max(last),
        ..fault
    })
}

/// The device fault: 1 s cut while frame sets keep coming, then back.
fn device_fault(p: &mut Pacer<'_>, relay: &Relay) -> Result<ValidLineFigures> {
    p.until_line(Some(0.1), true, Instant::now())?;
    let low_before = p.out.status().line_low_at;
    let cut_at = Instant::now();
    relay.set_cut(true);
    let mut detected = None;
    while cut_at.elapsed() < Duration::from_secs(1) {
        p.give(Some(0.1));
        if detected.is_none() && p.out.status().fault.is_some() {
            detected = Some(Instant::now());
        }
    }
    let unchanged = p.out.status().line_low_at == low_before;
    let back_at = Instant::now();
    relay.set_cut(false);
    let low = p.until_line(Some(0.1), false, back_at)?;
    let high = p.until_line(Some(0.1), true, low)?;
    Ok(ValidLineFigures {
        lost_camera_ms: [f64::NAN; 2],
        stall_from_due_ms: [f64::NAN; 2],
        stall_from_last_ms: [f64::NAN; 2],
        fault_detected_ms: detected.map_or(f64::NAN, |d| ms(cut_at, d)),
        fault_line: if unchanged {
            "left as last written (high): only the device's watchdog can lower it".into()
        } else {
            "written during the cut (unexpected)".into()
        },
        back_low_ms: ms(back_at, low),
        back_high_ms: ms(back_at, high),
    })
}
