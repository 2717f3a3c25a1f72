//! The UTM over Modbus TCP against real peers that are not our code: pymodbus's server
//! (tests/fixtures/modbus_server.py) for the poller, pymodbus's client for the simulated UTM.
//!
//! Needs python3 with pymodbus: `scripts/setup.sh` makes target/test-venv and
//! `scripts/test.sh` points TAGDEFLECT_PYTHON at it. Without it these tests fail (never skip).

use std::net::TcpListener as StdListener;
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};
use tagdeflect::config::{RegisterConfig, RegisterKind, UtmConfig, ValueType, WordOrder};

use tagdeflect_io::utm::{decode, run_poller, start_sim_utm, UtmEvent, UtmSample};
use tokio::sync::{mpsc, watch};
use tokio::task::JoinHandle;

// ----------------------------------------------------------------------------------------
// Python and the pymodbus server.

use crate::common::{python, start_pymodbus, start_pymodbus_on, unused_port};

// ----------------------------------------------------------------------------------------
// The poller.

fn reg(register: u16, kind: RegisterKind, value_type: ValueType, word_order: WordOrder, scale: f64, offset: f64) -> RegisterConfig {
    RegisterConfig { register, kind, value_type, word_order, scale, offset }
}

fn utm(address: String, load: RegisterConfig, stroke: Option<RegisterConfig>) -> UtmConfig {
    UtmConfig { address: tagdeflect::config::UtmAddress::from(address.as_str()), unit: 1, poll_hz: 20.0, timeout_ms: 300.0, load, stroke }
}

/// A running poller; stopped (and awaited) by [`Poller::stop`], aborted on drop.
struct Poller {
    rx: mpsc::Receiver<UtmEvent>,
    stop: watch::Sender<bool>,
    task: Option<JoinHandle<()>>,
}

impl Poller {
    fn start(cfg: UtmConfig) -> Self {
        let (tx, rx) = mpsc::channel(256);
        let (stop, stop_rx) = watch::channel(false);
        let task = tokio::spawn(async move {
            run_poller(cfg, tx, stop_rx).await.expect("poller refused its config");
        });
        Self { rx, stop, task: Some(task) }
    }

    /// The next event within `within`, or None.
    async fn next(&mut self, within: Duration) -> Option<UtmEvent> {
        tokio::time::timeout(within, self.rx.recv()).await.ok().flatten()
    }

    /// Events until one matches `want` (returned) or `within` runs out (panic naming `what`).
    async fn wait_for(&mut self, within: Duration, what: &str, want: impl Fn(&UtmEvent) -> bool) -> (UtmEvent, Vec<UtmEvent>) {
        let deadline = Instant::now() + within;
        let mut seen = Vec::new();
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.next(left).await {
                Some(e) if want(&e) => return (e, seen),
                Some(e) => seen.push(e),
                None => panic!("no {what} within {within:?}; events seen: {seen:?}"),
            }
        }
    }

    async fn sample(&mut self, within: Duration) -> UtmSample {
        match self.wait_for(within, "sample", |e| matches!(e, UtmEvent::Sample(_))).await.0 {
            UtmEvent::Sample(s) => s,
            _ => unreachable!(),
        }
    }

    async fn stop(mut self) {
        let _ = self.stop.send(true);
        if let Some(task) = self.task.take() {
            tokio::time::timeout(Duration::from_secs(5), task)
                .await
                .expect("the poller did not stop within 5 s of shutdown")
                .expect("the poller task panicked");
        }
    }
}

impl Drop for Poller {
    fn drop(&mut self) {
        if let Some(t) = self.task.take() {
            t.abort();
        }
    }
}

fn close(a: f64, b: f64, tol: f64) -> bool {
    (a - b).abs() <= tol
}

// ----------------------------------------------------------------------------------------
// Against pymodbus's server.

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn poller_decodes_and_scales_what_pymodbus_serves() {
    let (_server, port) = start_pymodbus();
    let addr = format!("127.0.0.1:{port}");
    let i = RegisterKind::Input;
    let h = RegisterKind::Holding;

    // The SPEC example layout: f32 load CDAB at input 0, i32 stroke at holding 10 (two reads).
    let before = tagdeflect_now();
    let cfg = utm(
        addr.clone(),
        reg(0, i, ValueType::F32, WordOrder::Cdab, 1.0, 0.0),
        Some(reg(10, h, ValueType::I32, WordOrder::Abcd, 0.0001, 0.0)),
    );
    let mut p = Poller::start(cfg);
    let (first, _) = p.wait_for(Duration::from_secs(10), "Up", |e| matches!(e, UtmEvent::Up)).await;
    assert_eq!(first, UtmEvent::Up);
    let s1 = p.sample(Duration::from_secs(5)).await;
    let s2 = p.sample(Duration::from_secs(5)).await;
    let after = tagdeflect_now();
    println!("pymodbus f32 CDAB / i32 ABCD: {s1:?}");
    assert_eq!(s1.load_kn, 12.5);
    assert!(close(s1.stroke_mm.unwrap(), -2.5, 1e-12), "{s1:?}");
    assert!(s1.t_ns >= before && s2.t_ns <= after && s2.t_ns > s1.t_ns, "sample times {} {} outside [{before}, {after}]", s1.t_ns, s2.t_ns);
    p.stop().await;

    // Every other type and word order, in one table (one read each).
    let cases = [
        (reg(2, i, ValueType::F32, WordOrder::Abcd, 2.0, 1.0), -5.5),
        (reg(4, i, ValueType::I16, WordOrder::Abcd, 0.1, 0.0), -123.4),
        (reg(5, i, ValueType::U16, WordOrder::Abcd, 1.0, -54000.0), 321.0),
        (reg(6, i, ValueType::U32, WordOrder::Badc, 1e-6, 0.0), 3000.0),
        (reg(8, i, ValueType::F32, WordOrder::Dcba, 1.0, 0.0), 7.75),
    ];
    for (load, want) in cases {
        let stroke = reg(4, i, ValueType::I16, WordOrder::Abcd, 1.0, 0.0);
        let mut p = Poller::start(utm(addr.clone(), load.clone(), Some(stroke)));
        let s = p.sample(Duration::from_secs(10)).await;
        println!("{:?} {:?} at input {}: {s:?}", load.value_type, load.word_order, load.register);
        assert!(close(s.load_kn, want, 1e-9), "{load:?}: got {} want {want}", s.load_kn);
        assert_eq!(s.stroke_mm, Some(-1234.0));
        p.stop().await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn server_killed_is_down_and_restarted_is_up_again() {
    let (server, port) = start_pymodbus();
    let load = reg(0, RegisterKind::Input, ValueType::F32, WordOrder::Cdab, 1.0, 0.0);
    let mut p = Poller::start(utm(format!("127.0.0.1:{port}"), load, None));
    p.wait_for(Duration::from_secs(10), "Up", |e| *e == UtmEvent::Up).await;
    assert_eq!(p.sample(Duration::from_secs(5)).await.load_kn, 12.5);

    drop(server); // killed
    let (down, _) = p.wait_for(Duration::from_secs(10), "Down after the server was killed", |e| matches!(e, UtmEvent::Down { .. })).await;
    println!("after kill: {down:?}");
    let UtmEvent::Down { reason } = down else { unreachable!() };
    assert!(reason.contains(&format!("127.0.0.1:{port}")), "the reason names the address: {reason}");

    // Down is reported once: nothing (no samples, no second Down) while the server is away.
    tokio::time::sleep(Duration::from_millis(1500)).await;
    let mut quiet = Vec::new();
    while let Ok(e) = p.rx.try_recv() {
        quiet.push(e);
    }
    assert!(quiet.is_empty(), "events while the server was down: {quiet:?}");

    let _server = start_pymodbus_on(port); // back on the same port
    let t0 = Instant::now();
    let (_, before_up) = p.wait_for(Duration::from_secs(15), "Up after the restart", |e| *e == UtmEvent::Up).await;
    assert!(before_up.is_empty(), "events between Down and Up: {before_up:?}");
    println!("Up again {:.2} s after the restart (backoff ≤ 5 s)", t0.elapsed().as_secs_f64());
    for _ in 0..3 {
        assert_eq!(p.sample(Duration::from_secs(5)).await.load_kn, 12.5);
    }
    p.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn poller_started_before_the_server_by_host_name_comes_up() {
    // The daemon may start before the UTM is switched on; the address may be a host name.
    let port = unused_port();
    let load = reg(0, RegisterKind::Input, ValueType::F32, WordOrder::Cdab, 1.0, 0.0);
    let mut p = Poller::start(utm(format!("localhost:{port}"), load, None));
    let (down, _) = p.wait_for(Duration::from_secs(5), "Down", |e| matches!(e, UtmEvent::Down { .. })).await;
    println!("nothing listening: {down:?}");
    let UtmEvent::Down { reason } = down else { unreachable!() };
    assert!(reason.contains(&format!("localhost:{port}")) && reason.contains("cannot connect"), "{reason}");
    let _server = start_pymodbus_on(port);
    p.wait_for(Duration::from_secs(15), "Up once the server listens", |e| *e == UtmEvent::Up).await;
    assert_eq!(p.sample(Duration::from_secs(5)).await.load_kn, 12.5);
    p.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn exception_reply_is_a_clear_error() {
    let (_server, port) = start_pymodbus();
    // Input registers 1000.. are not mapped by the fixture: Illegal Data Address.
    let load = reg(1000, RegisterKind::Input, ValueType::F32, WordOrder::Abcd, 1.0, 0.0);
    let mut p = Poller::start(utm(format!("127.0.0.1:{port}"), load, None));
    let (down, _) = p.wait_for(Duration::from_secs(10), "Down", |e| matches!(e, UtmEvent::Down { .. })).await;
    let UtmEvent::Down { reason } = down else { unreachable!() };
    println!("unmapped register: {reason}");
    assert!(reason.contains(&format!("127.0.0.1:{port}")), "{reason}");
    assert!(reason.contains("input registers 1000..1001"), "{reason}");
    assert!(reason.contains("exception 2"), "{reason}");
    // No sample ever comes, and the poller is still alive (stops cleanly).
    assert!(p.next(Duration::from_millis(700)).await.is_none());
    p.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn silent_server_times_out_and_is_retried() {
    // A TCP listener that accepts and never answers.
    let listener = StdListener::bind("127.0.0.1:0").unwrap();
    let addr = listener.local_addr().unwrap();
    let accepted = Arc::new(AtomicUsize::new(0));
    let count = accepted.clone();
    listener.set_nonblocking(true).unwrap();
    let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let stop_l = stop.clone();
    let acceptor = std::thread::spawn(move || {
        let mut held = Vec::new();
        while !stop_l.load(Ordering::Relaxed) {
            match listener.accept() {
                Ok((s, _)) => {
                    count.fetch_add(1, Ordering::Relaxed);
                    held.push(s);
                }
                Err(_) => std::thread::sleep(Duration::from_millis(10)),
            }
        }
    });

    let load = reg(0, RegisterKind::Input, ValueType::F32, WordOrder::Abcd, 1.0, 0.0);
    let mut cfg = utm(addr.to_string(), load, None);
    cfg.timeout_ms = 150.0;
    let mut p = Poller::start(cfg);
    let (down, _) = p.wait_for(Duration::from_secs(5), "Down", |e| matches!(e, UtmEvent::Down { .. })).await;
    let UtmEvent::Down { reason } = down else { unreachable!() };
    println!("silent server: {reason}");
    assert!(reason.contains("no answer") && reason.contains("150 ms") && reason.contains(&addr.to_string()), "{reason}");
    // Reconnects with backoff (0.2, 0.4, 0.8 s ...; 1.4 s for three): waited for, with a
    // deadline far beyond it for a busy machine; one Down whatever the count.
    let deadline = Instant::now() + Duration::from_secs(60);
    while accepted.load(Ordering::Relaxed) < 3 && Instant::now() < deadline {
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let n = accepted.load(Ordering::Relaxed);
    println!("connections to the silent server: {n}");
    assert!(n >= 3, "the poller reconnected {n} time(s)");
    let mut later = Vec::new();
    while let Ok(e) = p.rx.try_recv() {
        later.push(e);
    }
    assert!(later.is_empty(), "a second event while still down: {later:?}");
    p.stop().await;
    stop.store(true, Ordering::Relaxed);
    acceptor.join().unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn nan_from_the_device_is_a_clear_error() {
    let (_server, port) = start_pymodbus();
    let load = reg(10, RegisterKind::Input, ValueType::F32, WordOrder::Abcd, 1.0, 0.0);
    let mut p = Poller::start(utm(format!("127.0.0.1:{port}"), load, None));
    let (down, _) = p.wait_for(Duration::from_secs(10), "Down", |e| matches!(e, UtmEvent::Down { .. })).await;
    let UtmEvent::Down { reason } = down else { unreachable!() };
    println!("NaN load: {reason}");
    assert!(reason.contains("register 10") && reason.contains("not a finite number"), "{reason}");
    assert!(p.next(Duration::from_millis(500)).await.is_none());
    p.stop().await;
}

/// A hand-made Modbus TCP device on loopback: every 12-byte read request (MBAP + function,
/// address, count) is answered with `reply(request, connection index)`.
async fn scripted_device(reply: impl Fn(&[u8; 12], usize) -> Vec<u8> + Send + Sync + 'static) -> (std::net::SocketAddr, JoinHandle<()>) {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let reply = Arc::new(reply);
    let device = tokio::spawn(async move {
        use tokio::io::{AsyncReadExt, AsyncWriteExt};
        let mut connection = 0;
        while let Ok((mut s, _)) = listener.accept().await {
            let (reply, index) = (Arc::clone(&reply), connection);
            connection += 1;
            tokio::spawn(async move {
                let mut req = [0u8; 12];
                while s.read_exact(&mut req).await.is_ok() {
                    if s.write_all(&reply(&req, index)).await.is_err() {
                        break;
                    }
                }
            });
        }
    });
    (addr, device)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn short_reply_is_a_clear_error() {
    // A hand-made device that answers every read with one register, whatever was asked.
    // Same transaction and unit, length 5 = unit + function + count + 2 bytes.
    let (addr, device) = scripted_device(|req, _| vec![req[0], req[1], 0, 0, 0, 5, req[6], req[7], 2, 0x41, 0x48]).await;
    let load = reg(0, RegisterKind::Input, ValueType::F32, WordOrder::Abcd, 1.0, 0.0);
    let mut p = Poller::start(utm(addr.to_string(), load, None));
    let (down, _) = p.wait_for(Duration::from_secs(5), "Down", |e| matches!(e, UtmEvent::Down { .. })).await;
    let UtmEvent::Down { reason } = down else { unreachable!() };
    println!("short reply: {reason}");
    assert!(reason.contains(&addr.to_string()) && reason.contains("input registers 0..1"), "{reason}");
    assert!(reason.contains("bad reply: 1 register(s) instead of 2"), "{reason}");
    p.stop().await;
    device.abort();
}

/// A device whose first reply is a read-coils answer claiming 194 coil bytes and carrying
/// none: tokio-modbus 0.15 panics decoding it (slowtec/tokio-modbus#298, found by the
/// `modbus_peer` fuzz target). The poller reports a malformed reply, reconnects, and reads
/// the well-formed replies that follow: the test goes on with load.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_reply_that_breaks_the_modbus_library_is_a_fault_not_the_end_of_the_poller() {
    let (addr, device) = scripted_device(|req, connection| {
        if connection == 0 {
            // Function 1 (read coils), byte count 0xc2, no bytes.
            vec![req[0], req[1], 0, 0, 0, 3, req[6], 1, 0xc2]
        } else {
            // Two input registers: f32 12.5 (0x41480000).
            vec![req[0], req[1], 0, 0, 0, 7, req[6], req[7], 4, 0x41, 0x48, 0, 0]
        }
    })
    .await;
    let load = reg(0, RegisterKind::Input, ValueType::F32, WordOrder::Abcd, 1.0, 0.0);
    let mut p = Poller::start(utm(addr.to_string(), load, None));
    let (down, _) = p.wait_for(Duration::from_secs(5), "Down", |e| matches!(e, UtmEvent::Down { .. })).await;
    let UtmEvent::Down { reason } = down else { unreachable!() };
    println!("poisoned reply: {reason}");
    assert!(reason.contains(&addr.to_string()) && reason.contains("malformed reply"), "{reason}");
    let s = p.sample(Duration::from_secs(5)).await;
    assert!(close(s.load_kn, 12.5, 1e-9), "{s:?}");
    p.stop().await;
    device.abort();
}

// ----------------------------------------------------------------------------------------
// Our simulated UTM.

fn sim_layout() -> UtmConfig {
    utm(
        "sim".into(),
        reg(0, RegisterKind::Input, ValueType::F32, WordOrder::Cdab, 1.0, 0.0),
        Some(reg(4, RegisterKind::Input, ValueType::I32, WordOrder::Badc, 0.001, 0.0)),
    )
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sim_server_read_by_our_client_follows_the_model() {
    let t0 = tagdeflect_now();
    // 1 kN/s from t0, stroke 0.1 mm/kN.
    let model = tagdeflect_io::utm::sim_server::ramp_model(t0, 1.0, 1000.0, 0.1);
    let (cfg, sim) = start_sim_utm(&sim_layout(), model.clone()).await.unwrap();
    assert_eq!(cfg.address.to_string(), sim.addr.to_string());
    let mut p = Poller::start(cfg);
    p.wait_for(Duration::from_secs(5), "Up", |e| *e == UtmEvent::Up).await;
    let mut worst_kn: f64 = 0.0;
    let mut times = Vec::new();
    for _ in 0..10 {
        let s = p.sample(Duration::from_secs(5)).await;
        times.push(s.t_ns);
        let (want_load, want_stroke) = model(s.t_ns);
        worst_kn = worst_kn.max((s.load_kn - want_load).abs());
        // The server evaluates the model during the request, whose middle is t_ns: at 1 kN/s
        // 0.1 kN is 100 ms of skew, far more than a loopback request takes.
        assert!(close(s.load_kn, want_load, 0.1), "{s:?} vs model {want_load}");
        assert!(close(s.stroke_mm.unwrap(), want_stroke, 0.01 + 0.0005), "{s:?} vs model {want_stroke}");
    }
    println!("sim UTM through our client: worst |load − model(t_ns)| = {worst_kn:.6} kN at 1 kN/s");
    let span_s = (times[times.len() - 1] - times[0]) as f64 * 1e-9;
    println!("poll rate: {:.2} Hz measured over {} samples (configured 20 Hz)", (times.len() - 1) as f64 / span_s, times.len());
    assert!(times.windows(2).all(|w| w[1] > w[0]), "sample times not increasing: {times:?}");

    sim.stop(); // closes its connections too
    let (down, _) = p.wait_for(Duration::from_secs(5), "Down after the sim stopped", |e| matches!(e, UtmEvent::Down { .. })).await;
    println!("sim stopped: {down:?}");
    p.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sim_server_read_by_pymodbus_client() {
    let py = python();
    let model: tagdeflect_io::utm::UtmModel = Arc::new(|_| (12.5, -1.234));
    let layout = sim_layout();
    let (cfg, sim) = start_sim_utm(&layout, model).await.unwrap();
    let port = sim.addr.port();
    let script = format!(
        r#"
from pymodbus.client import ModbusTcpClient
c = ModbusTcpClient("127.0.0.1", port={port})
assert c.connect(), "cannot connect"
r = c.read_input_registers(0, count=6)
assert not r.isError(), r
print("regs", " ".join(str(x) for x in r.registers))
w = c.write_register(0, 7)
print("write_error", w.isError(), getattr(w, "exception_code", None))
r = c.read_holding_registers(0, count=2)
print("holding", " ".join(str(x) for x in r.registers))
c.close()
"#
    );
    let out = tokio::task::spawn_blocking(move || Command::new(py).args(["-c", &script]).stdin(Stdio::null()).output())
        .await
        .unwrap()
        .expect("cannot run python");
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "pymodbus client failed: {}\n{stdout}", String::from_utf8_lossy(&out.stderr));
    println!("pymodbus client on our sim UTM:\n{stdout}");
    let line = |key: &str| -> Vec<String> {
        let l = stdout.lines().find(|l| l.starts_with(key)).unwrap_or_else(|| panic!("no {key} line in {stdout}"));
        l.split_whitespace().skip(1).map(str::to_string).collect()
    };
    let regs: Vec<u16> = line("regs ").iter().map(|x| x.parse().unwrap()).collect();
    assert_eq!(regs.len(), 6);
    assert_eq!(&regs[0..2], &[0x0000, 0x4148], "f32 12.5 CDAB");
    assert_eq!(decode(&cfg.load, &regs[0..2]).unwrap(), 12.5);
    assert!(close(decode(cfg.stroke.as_ref().unwrap(), &regs[4..6]).unwrap(), -1.234, 1e-12));
    assert_eq!(line("write_error "), vec!["True".to_string(), "1".to_string()], "a write is refused with exception 1 (illegal function)");
    assert_eq!(line("holding "), vec!["0", "0"], "the write changed nothing");
    drop(sim);
}

fn tagdeflect_now() -> i64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_nanos() as i64
}
