//! The analog output (`[output.analog]`) against real Modbus peers: pymodbus
//! devices with the LabJack T-series map and a generic holding-register module's
//! (tests/fixtures/analog_device.py), which record every write. Each write's value and
//! scaling, the clamp, the valid line, hold vs safe, a stall, the stop, a device that
//! disappears and comes back, a device that answers an exception; and the config errors
//! located by key.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use tagdeflect::config::Config;
use tagdeflect_core::feed::FeedLine;
use tagdeflect_io::utm::config::{ValueType, WordOrder};
use tagdeflect_sinks::analog_output::{AnalogConfig, AnalogOutput, DeviceMap, DigitalOutput, OnInvalid};

use crate::common::{listens_within_30_s, python, unused_port, ChildGuard};

/// One write the device received.
#[derive(Debug, Clone, PartialEq)]
struct Write {
    /// When the device received it, s since the epoch.
    t: f64,
    fc: u8,
    address: u16,
    values: Vec<u16>,
}

/// A pymodbus device and the writes it recorded.
pub(crate) struct Dac {
    _server: ChildGuard,
    port: u16,
    writes: Arc<Mutex<Vec<Write>>>,
}

fn fixture() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/analog_device.py")
}

impl Dac {
    /// The device of `map` on a free loopback port.
    pub(crate) fn start(map: &str, refuse: Option<u16>) -> Dac {
        for _ in 0..5 {
            if let Some(d) = Dac::try_on(map, unused_port(), refuse) {
                return d;
            }
        }
        panic!("the pymodbus device did not listen on any of 5 free ports");
    }

    /// The device of `map` on `port` (restarted where it was).
    fn on(map: &str, port: u16) -> Dac {
        Dac::try_on(map, port, None).unwrap_or_else(|| panic!("the pymodbus device did not listen on 127.0.0.1:{port}"))
    }

    fn try_on(map: &str, port: u16, refuse: Option<u16>) -> Option<Dac> {
        let mut cmd = Command::new(python());
        cmd.arg(fixture()).arg(map).arg(port.to_string());
        if let Some(r) = refuse {
            cmd.args(["--refuse", &r.to_string()]);
        }
        let child = cmd.stdin(Stdio::null()).stdout(Stdio::piped()).stderr(Stdio::piped()).spawn().expect("cannot start python");
        let mut guard = ChildGuard(child);
        let writes = Arc::new(Mutex::new(Vec::new()));
        let out = guard.0.stdout.take().expect("stdout");
        let w = writes.clone();
        std::thread::spawn(move || {
            for line in BufReader::new(out).lines().map_while(Result::ok) {
                let Ok(v) = serde_json::from_str::<serde_json::Value>(&line) else { continue };
                let values = v["values"].as_array().expect("values").iter().map(|x| x.as_u64().expect("value") as u16).collect();
                let write = Write {
                    t: v["t"].as_f64().expect("t"),
                    fc: v["fc"].as_u64().expect("fc") as u8,
                    address: v["address"].as_u64().expect("address") as u16,
                    values,
                };
                w.lock().unwrap().push(write);
            }
        });
        listens_within_30_s(&mut guard, port, "the pymodbus device").then(|| Dac { _server: guard, port, writes })
    }

    pub(crate) fn addr(&self) -> String {
        format!("127.0.0.1:{}", self.port)
    }

    fn writes(&self) -> Vec<Write> {
        self.writes.lock().unwrap().clone()
    }

    /// Waits (up to 30 s) until a write satisfies `pred`; returns the writes then.
    fn wait_for(&self, what: &str, pred: impl Fn(&Write) -> bool) -> Vec<Write> {
        self.wait_until(what, |w| w.iter().any(&pred))
    }

    /// Waits (up to 30 s) until the writes satisfy `cond`; returns them.
    fn wait_until(&self, what: &str, cond: impl Fn(&[Write]) -> bool) -> Vec<Write> {
        let deadline = Instant::now() + Duration::from_secs(30);
        loop {
            let w = self.writes();
            if cond(&w) {
                return w;
            }
            assert!(Instant::now() < deadline, "no {what} within 30 s; writes: {w:?}");
            std::thread::sleep(Duration::from_millis(2));
        }
    }
}

/// The float32 of a write of two registers, high word first (the LabJack's order).
fn f32_abcd(w: &Write) -> f32 {
    f32::from_bits(((w.values[0] as u32) << 16) | w.values[1] as u32)
}

fn is_dac(w: &Write) -> bool {
    w.fc == 16 && w.address == 1000
}

fn fio0(on: u16) -> impl Fn(&Write) -> bool {
    move |w| w.fc == 6 && w.address == 2000 && w.values == [on]
}

fn count(w: &[Write], pred: impl Fn(&Write) -> bool) -> usize {
    w.iter().filter(|w| pred(w)).count()
}

/// A line with the net deflection `net` (σ 0.002 mm) at `seq`, lines one second apart on a
/// made-up clock.
fn line(seq: u64, net: Option<f64>) -> FeedLine {
    FeedLine {
        seq,
        t_ns: 1_000_000_000_000 + seq as i64 * 1_000_000_000,
        net_deflection_mm: net,
        net_deflection_sigma_mm: net.map(|_| 0.002),
        ..FeedLine::default()
    }
}

/// Lines one second apart on the feed's clock and `stale_sets` 1000: never stale in a test.
fn never_stale(mut c: AnalogConfig) -> AnalogConfig {
    c.stale_sets = 1000;
    c
}

/// Feeds the lines of `values` one at a time, each once the previous one's write arrived.
fn feed_one_by_one(out: &AnalogOutput, dac: &Dac, values: &[f64], is_value: impl Fn(&Write) -> bool) -> Vec<Write> {
    for (k, &v) in values.iter().enumerate() {
        let before = dac.writes().iter().filter(|w| is_value(w)).count();
        let l = line(k as u64, Some(v));
        out.take_line(&l);
        let deadline = Instant::now() + Duration::from_secs(30);
        while dac.writes().iter().filter(|w| is_value(w)).count() == before {
            assert!(Instant::now() < deadline, "value {v} not written: {:?}", dac.writes());
            std::thread::sleep(Duration::from_millis(5));
        }
    }
    dac.writes()
}

#[test]
fn labjack_gets_each_value_scaled_and_clamped_then_the_valid_line() {
    let dac = Dac::start("labjack", None);
    let cfg = never_stale(AnalogConfig { offset_v: 1.0, ..AnalogConfig::labjack(&dac.addr(), 0.5) });
    let mut out = AnalogOutput::start(&cfg).unwrap();
    dac.wait_for("valid low at connect", fio0(0));
    // 1 V + 0.5 V/mm: 0 mm → 1 V, 1 mm → 1.5 V, 2.5 mm → 2.25 V, 20 mm → 11 V clamped to 5 V,
    // -10 mm → -4 V clamped to 0 V.
    let writes = feed_one_by_one(&out, &dac, &[0.0, 1.0, 2.5, 20.0, -10.0], is_dac);
    let volts: Vec<f32> = writes.iter().filter(|w| is_dac(w)).map(f32_abcd).collect();
    assert_eq!(volts, vec![1.0, 1.5, 2.25, 5.0, 0.0], "{writes:?}");
    // The line low first (at connect), the first value, then the line high — once.
    let first_dac = writes.iter().position(is_dac).unwrap();
    let low = writes.iter().position(fio0(0)).unwrap();
    let high = writes.iter().position(fio0(1)).expect("valid high");
    assert!(low < first_dac && first_dac < high, "{writes:?}");
    assert_eq!(writes.iter().filter(|w| fio0(1)(w)).count(), 1, "{writes:?}");
    assert!(writes.iter().all(|w| is_dac(w) || w.address == 2000), "writes only DAC0 and FIO0: {writes:?}");
    // Stop: the line drops; hold mode writes no value.
    out.shutdown();
    let after = dac.wait_until("valid low at stop", |w| count(w, fio0(0)) >= 2);
    assert!(fio0(0)(after.last().unwrap()) && count(&after, is_dac) == 5, "{after:?}");
    let s = out.status();
    assert_eq!((s.values_written, s.outages), (5, 0));
    let (n, p50, p99, _) = s.latency_ms().unwrap();
    println!("feed time → DAC write acknowledged over {n} values: p50 {p50:.1} ms, p99 {p99:.1} ms (lines of a made-up clock)");
}

/// `labjack_watchdog_s`: after connect the device's own watchdog is set up (disabled first,
/// the timeout, no reset, only FIO0 driven — low — on a trip, DAC0 to the safe voltage,
/// enabled last); a second connect finds it set and writes none of it (flash registers).
#[test]
fn the_labjack_watchdog_is_set_up_after_connect_and_left_alone_when_it_holds() {
    let dac = Dac::start("labjack", None);
    let cfg = never_stale(AnalogConfig {
        labjack_watchdog_s: Some(2),
        on_invalid: OnInvalid::Volts(0.25),
        ..AnalogConfig::labjack(&dac.addr(), 1.0)
    });
    let mut out = AnalogOutput::start(&cfg).unwrap();
    let writes = dac.wait_for("the watchdog enabled", |w| w.address == 61600 && w.values == [0, 1]);
    let watchdog: Vec<(u16, Vec<u16>)> = writes.iter().filter(|w| w.address >= 61600).map(|w| (w.address, w.values.clone())).collect();
    let quarter = 0.25f32.to_bits();
    assert_eq!(
        watchdog,
        vec![
            (61600, vec![0, 0]),
            (61604, vec![0, 2]),
            (61620, vec![0, 0]),
            (61630, vec![0, 1]),
            (61632, vec![0, 0]),
            (61634, vec![0, 1]),
            (61636, vec![0x7F, 0xFFFE]),
            (61640, vec![0, 1]),
            (61642, vec![(quarter >> 16) as u16, quarter as u16]),
            (61600, vec![0, 1]),
        ]
    );
    out.shutdown();
    let before = dac.writes().len();
    let mut again = AnalogOutput::start(&cfg).unwrap();
    let after = feed_one_by_one(&again, &dac, &[0.5], is_dac);
    again.shutdown();
    assert!(after[before..].iter().any(is_dac), "{after:?}");
    assert!(after[before..].iter().all(|w| w.address < 61600), "the watchdog held its set-up: nothing rewritten {:?}", &after[before..]);
}

#[test]
fn invalid_values_drop_the_line_then_hold_or_go_safe() {
    for on_invalid in [OnInvalid::Hold, OnInvalid::Volts(0.25)] {
        let dac = Dac::start("labjack", None);
        let cfg = AnalogConfig { on_invalid, ..AnalogConfig::labjack(&dac.addr(), 1.0) };
        let mut out = AnalogOutput::start(&never_stale(cfg)).unwrap();
        feed_one_by_one(&out, &dac, &[2.0], is_dac);
        dac.wait_for("valid high", fio0(1));
        // A σ above max_sigma_mm turns the value invalid at once.
        let mut l = line(1, Some(3.0));
        l.net_deflection_sigma_mm = Some(0.5);
        out.take_line(&l);
        dac.wait_until("valid low on the invalid value", |w| count(w, fio0(0)) >= 2);
        let w = match on_invalid {
            OnInvalid::Volts(_) => dac.wait_for("the safe value", |w| is_dac(w) && f32_abcd(w) == 0.25),
            OnInvalid::Hold => {
                // Nothing more is written while invalid; the stop writes the line low again.
                out.shutdown();
                dac.wait_until("valid low at stop", |w| count(w, fio0(0)) >= 3)
            }
        };
        let drop_at = w.iter().enumerate().filter(|(_, w)| fio0(0)(w)).map(|(i, _)| i).nth(1).unwrap();
        let dac_after: Vec<f32> = w[drop_at..].iter().filter(|w| is_dac(w)).map(f32_abcd).collect();
        match on_invalid {
            OnInvalid::Hold => assert!(dac_after.is_empty(), "hold writes nothing: {w:?}"),
            OnInvalid::Volts(_) => assert_eq!(dac_after, vec![0.25], "the line drops first, then the safe value: {w:?}"),
        }
        assert!(!w.iter().any(|w| is_dac(w) && f32_abcd(w) == 3.0), "the invalid value is never written: {w:?}");
        out.shutdown();
    }
}

/// Feeds `value` in lines 20 ms apart (on both clocks) until `done` holds for the writes;
/// returns when the last line was taken.
fn feed_until(out: &AnalogOutput, dac: &Dac, seq: &mut u64, value: f64, done: impl Fn(&[Write]) -> bool) -> Instant {
    let t0 = tagdeflect_core::clock::now_epoch_ns() - *seq as i64 * 20_000_000;
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        let mut l = line(*seq, Some(value));
        l.t_ns = t0 + *seq as i64 * 20_000_000;
        out.take_line(&l);
        let fed = Instant::now();
        *seq += 1;
        if done(&dac.writes()) {
            return fed;
        }
        assert!(Instant::now() < deadline, "not written while fed: {:?}", dac.writes());
        std::thread::sleep(Duration::from_millis(20));
    }
}

#[test]
fn a_stalled_feed_drops_the_line_and_a_new_value_raises_it() {
    let dac = Dac::start("labjack", None);
    let out = AnalogOutput::start(&AnalogConfig::labjack(&dac.addr(), 1.0)).unwrap();
    dac.wait_for("valid low at connect", fio0(0));
    // Lines 20 ms apart, then none: stale after 1.5 frame periods (stale_sets = 1).
    let mut seq = 0;
    let fed = feed_until(&out, &dac, &mut seq, 1.0, |w| w.iter().any(fio0(1)));
    let w = dac.wait_until("valid low after the stall", |w| count(w, fio0(0)) >= 2 && w.last().is_some_and(fio0(0)));
    println!(
        "valid line dropped {:.0} ms after the last line (frame period 20 ms, stale after 30 ms; includes the device's recording)",
        fed.elapsed().as_secs_f64() * 1e3
    );
    assert!(count(&w, is_dac) >= 1 && w.iter().filter(|w| is_dac(w)).all(|w| f32_abcd(w) == 1.0), "{w:?}");
    // Hold: nothing written after the line dropped.
    let drop_at = w.len() - 1;
    std::thread::sleep(Duration::from_millis(300));
    assert_eq!(dac.writes().len(), w.len(), "{:?}", dac.writes());
    // The feed resumes: the new value, then the line high again.
    feed_until(&out, &dac, &mut seq, 1.5, |w| w[drop_at..].iter().any(fio0(1)));
    let w = dac.writes();
    let first_new = w.iter().position(|w| is_dac(w) && f32_abcd(w) == 1.5).expect("the new value");
    let high_again = drop_at + w[drop_at..].iter().position(fio0(1)).unwrap();
    assert!(first_new < high_again, "{w:?}");
}

#[test]
fn generic_modules_get_counts_in_their_type_and_word_order() {
    let dac = Dac::start("generic", None);
    // ±10 V module as i16 counts (3276.7 counts/V), valid on coil 3.
    let cfg = AnalogConfig {
        device: DeviceMap::Generic,
        register: Some(8),
        data_type: Some(ValueType::I16),
        scale: 3276.7,
        offset: 0.0,
        range_v: Some([-10.0, 10.0]),
        valid_output: Some(DigitalOutput::Coil(3)),
        ..AnalogConfig::labjack(&dac.addr(), 2.0)
    };
    let mut out = AnalogOutput::start(&never_stale(cfg)).unwrap();
    let coil = |on: u16| move |w: &Write| w.fc == 5 && w.address == 3 && w.values == [on];
    dac.wait_for("coil low at connect", coil(0));
    let at8 = |w: &Write| w.fc == 16 && w.address == 8;
    let w = feed_one_by_one(&out, &dac, &[1.0, -2.0, 7.0], at8);
    let raw: Vec<i16> = w.iter().filter(|w| at8(w)).map(|w| w.values[0] as i16).collect();
    // 2 V/mm: 2 V → 6553 counts, -4 V → -13107, 14 V clamped to 10 V → 32767.
    assert_eq!(raw, vec![6553, -13107, 32767], "{w:?}");
    dac.wait_for("coil high", coil(1));
    out.shutdown();
    drop(dac);

    // f32 volts, low word first, a u16 line register.
    let dac = Dac::start("generic", None);
    let cfg = AnalogConfig {
        device: DeviceMap::Generic,
        register: Some(20),
        data_type: Some(ValueType::F32),
        word_order: WordOrder::Cdab,
        scale: 1.0,
        range_v: Some([0.0, 10.0]),
        valid_output: Some(DigitalOutput::Register(40)),
        ..AnalogConfig::labjack(&dac.addr(), 0.5)
    };
    let mut out = AnalogOutput::start(&never_stale(cfg)).unwrap();
    let at20 = |w: &Write| w.fc == 16 && w.address == 20;
    let w = feed_one_by_one(&out, &dac, &[3.0], at20);
    let v = w.iter().find(|w| at20(w)).unwrap();
    assert_eq!(f32::from_bits(((v.values[1] as u32) << 16) | v.values[0] as u32), 1.5, "CDAB: {v:?}");
    dac.wait_for("line register high", |w| w.fc == 6 && w.address == 40 && w.values == [1]);
    out.shutdown();
}

#[test]
fn a_device_that_disappears_is_reconnected_with_the_line_low_first() {
    let dac = Dac::start("labjack", None);
    let port = dac.port;
    let cfg = never_stale(AnalogConfig { timeout_ms: 300.0, ..AnalogConfig::labjack(&dac.addr(), 1.0) });
    let mut out = AnalogOutput::start(&cfg).unwrap();
    feed_one_by_one(&out, &dac, &[1.0], is_dac);
    dac.wait_for("valid high", fio0(1));
    drop(dac);
    // Values keep coming while the device is away; none of them blocks take_line.
    let deadline = Instant::now() + Duration::from_secs(30);
    let mut k = 1;
    while out.status().fault.is_none() {
        let l = line(k, Some(2.0));
        out.take_line(&l);
        k += 1;
        assert!(Instant::now() < deadline, "the outage was not noticed");
        std::thread::sleep(Duration::from_millis(20));
    }
    let fault = out.status().fault.unwrap();
    assert!(fault.contains(&port.to_string()), "{fault}");
    std::thread::sleep(Duration::from_millis(800)); // a few retries, one outage
    let dac = Dac::on("labjack", port);
    let l = line(k, Some(2.5));
    out.take_line(&l);
    let w = dac.wait_for("the value after the return", |w| is_dac(w) && f32_abcd(w) == 2.5);
    assert!(fio0(0)(&w[0]), "the line low before anything else: {w:?}");
    let w = dac.wait_for("valid high again", fio0(1));
    assert!(w.iter().position(is_dac) < w.iter().position(fio0(1)), "{w:?}");
    // The device logs a write before it answers: the status follows once the answer is read.
    let deadline = Instant::now() + Duration::from_secs(10);
    let mut s = out.status();
    while !(s.connected && s.fault.is_none()) && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(10));
        s = out.status();
    }
    assert!(s.connected && s.fault.is_none(), "{s:?}");
    assert_eq!(s.outages, 1, "retries within one outage count once: {s:?}");
    out.shutdown();
}

#[test]
fn a_device_answering_an_exception_keeps_the_line_low() {
    // The DAC register is not in this device's map.
    let dac = Dac::start("labjack", Some(1000));
    let mut out = AnalogOutput::start(&never_stale(AnalogConfig::labjack(&dac.addr(), 1.0))).unwrap();
    dac.wait_for("valid low at connect", fio0(0));
    let deadline = Instant::now() + Duration::from_secs(30);
    let mut k = 0;
    let fault = loop {
        let l = line(k, Some(1.0));
        out.take_line(&l);
        k += 1;
        if let Some(f) = out.status().fault {
            break f;
        }
        assert!(Instant::now() < deadline, "the exception was not reported");
        std::thread::sleep(Duration::from_millis(20));
    };
    assert!(fault.contains("exception") && fault.contains("1000"), "{fault}");
    std::thread::sleep(Duration::from_millis(700)); // reconnects: the line low again each time
    let w = dac.writes();
    assert!(!w.iter().any(fio0(1)), "never valid while the value cannot be written: {w:?}");
    assert!(!w.iter().any(is_dac), "no value accepted: {w:?}");
    assert_eq!(out.status().outages, 1, "{:?}", out.status());
    out.shutdown();
}

// ----------------------------------------------------------------------------------------
// Config errors, located by key and line.

const BASE: &str = r#"
[[camera]]
name = "left"
source = "sim"
width = 640
height = 480
fx = 500.0
fy = 500.0
cx = 319.5
cy = 239.5

[background]
family = "tag25h9"
size_mm = 60.0
[[background.tag]]
id = 3
corners_mm = [[0.0, 0.0, 0.0], [60.0, 0.0, 0.0], [60.0, 0.0, 60.0], [0.0, 0.0, 60.0]]

[specimen]
family = "tag36h11"
size_mm = 30.0
[[specimen.tag]]
id = 0
role = "support"
[[specimen.tag]]
id = 7
role = "midspan"

[utm]
address = "192.0.2.10:502"
[utm.load]
register = 4

[output.analog]
address = "192.0.2.20:502"
device = "labjack-t"
volts_per_mm = 0.5
range_v = [0.0, 5.0]
"#;

fn parse(text: &str) -> Result<Config, tagdeflect::config::ConfigError> {
    Config::from_toml_str(text, Path::new("/lab/rig.toml"))
}

#[test]
fn analog_config_errors_name_their_key_and_line() {
    let c = parse(BASE).expect("the base config loads");
    assert_eq!(c.output.analog.as_ref().unwrap().valid_line(), Some(DigitalOutput::Register(2000)));
    let cases = [
        ("address = \"192.0.2.20:502\"", "address = \"192.0.2.10:502\"", "output.analog.address", "UTM"),
        ("address = \"192.0.2.20:502\"", "address = \"dac.lab\"", "output.analog.address", "IP:PORT"),
        ("range_v = [0.0, 5.0]", "range_v = [0.0, 10.0]", "output.analog.range_v", "0 to 5 V"),
        ("range_v = [0.0, 5.0]", "range_v = [6.0, 5.0]", "output.analog.range_v", "0 to 5 V"),
        ("volts_per_mm = 0.5", "volts_per_mm = 0.0", "output.analog.volts_per_mm", "non-zero"),
        ("device = \"labjack-t\"", "device = \"labjack-t\"\non_invalid = \"safe\"", "on_invalid", "safe voltage"),
        ("device = \"labjack-t\"", "device = \"labjack-t\"\non_invalid = 7.0", "output.analog.on_invalid", "outside"),
        ("device = \"labjack-t\"", "device = \"holding-registers\"\nrange_v = [-10.0, 10.0]", "output.analog.register", "holding register"),
        (
            "device = \"labjack-t\"",
            "device = \"holding-registers\"\nregister = 0\ndata_type = \"u16\"\nscale = 20000.0\nrange_v = [0.0, 10.0]",
            "output.analog.scale",
            "outside the range",
        ),
        ("device = \"labjack-t\"", "device = \"labjack-t\"\ngauge = \"cmod\"", "output.analog.gauge", "[[gauge]]"),
    ];
    for (from, to, key, msg) in cases {
        let text = if to.contains("range_v") && from != "range_v = [0.0, 5.0]" {
            BASE.replacen("range_v = [0.0, 5.0]\n", "", 1).replacen(from, to, 1)
        } else {
            BASE.replacen(from, to, 1)
        };
        let e = parse(&text).expect_err(to);
        assert!(e.key.as_deref().is_some_and(|k| k.ends_with(key)), "{to}: key {:?} ({e})", e.key);
        assert!(e.message.contains(msg), "{to}: {e}");
        assert!(e.line.is_some(), "{to}: no line ({e})");
    }
}

/// The loop closed in simulation on the *voltage*. The same loop as the
/// register loop (`control::a_pi_controller_…`: the simulated machine, a C1609-like crack,
/// the camera lost for 1 s), the PI controller reading the LabJack's DAC0 volts (converted
/// back with volts_per_mm/offset_v) and its valid line FIO0 instead of the control output's
/// registers: the rate within ±10 % outside the first second after the crack and the loss,
/// the stroke held and the valid line low through the loss.
#[test]
fn a_pi_controller_on_the_dac_voltage_holds_the_rate_through_a_crack_and_a_lost_camera() {
    crate::control::closed_loop(crate::control::LoopSource::Analog);
}

/// `tagdeflect check --config` on the demo rig with `[output.analog]` set to `analog`.
fn check_with(analog: AnalogConfig, write_test: bool) -> (Option<i32>, String) {
    let tmp = tempfile::tempdir().unwrap();
    let mut cfg = Config::demo();
    cfg.output.analog = Some(analog);
    let path = tmp.path().join("rig.toml");
    std::fs::write(&path, cfg.to_toml_string()).unwrap();
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_tagdeflect"));
    cmd.args(["check", "--config"]).arg(&path);
    if write_test {
        cmd.arg("--write-test");
    }
    let o = cmd.output().expect("run tagdeflect check");
    let text = format!("{}\n{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
    (o.status.code(), text)
}

/// `check` reports the analog device: reachable and its identity (the LabJack's product ID and
/// serial number from LabJack's map; a generic module's configured register), writes nothing
/// unless asked, and with `--write-test` writes the valid line low then the safe value and
/// reads it back; a device that is not there is a warning naming it.
#[test]
fn check_reports_the_analog_device_and_writes_only_when_asked() {
    let dac = Dac::start("labjack", None);
    let lj = AnalogConfig { on_invalid: OnInvalid::Volts(0.5), ..AnalogConfig::labjack(&dac.addr(), 1.0) };
    let (code, out) = check_with(lj.clone(), false);
    assert_eq!(code, Some(0), "{out}");
    assert!(out.contains(&format!("analog output {}: reachable; LabJack T7, serial number 470012345", dac.addr())), "{out}");
    assert!(out.contains("nothing written"), "{out}");
    let (code, out) = check_with(lj, true);
    assert_eq!(code, Some(0), "{out}");
    assert!(out.contains("safe value 0.5000 V written and read back"), "{out}");
    // Only the second run wrote, and only the line low then the safe value (all writes
    // arrive in order, so none came from the first run).
    let w = dac.wait_until("the test write", |w| w.iter().any(is_dac));
    assert_eq!(w.len(), 2, "{w:?}");
    assert!(fio0(0)(&w[0]) && is_dac(&w[1]) && f32_abcd(&w[1]) == 0.5, "{w:?}");

    let generic = Dac::start("generic", None);
    let g = AnalogConfig {
        device: DeviceMap::Generic,
        register: Some(8),
        data_type: Some(ValueType::I16),
        scale: 3276.7,
        range_v: Some([-10.0, 10.0]),
        ..AnalogConfig::labjack(&generic.addr(), 1.0)
    };
    let (code, out) = check_with(g, true);
    assert_eq!(code, Some(0), "{out}");
    assert!(out.contains("reachable; holding register 8 reads [0]"), "{out}");
    // "hold": the test write is a zero value's voltage (offset_v = 0 V: 0 counts).
    assert!(out.contains("safe value 0.0000 V written and read back ([0])"), "{out}");
    let w = generic.wait_until("the test write", |w| w.iter().any(|w| w.fc == 16 && w.address == 8));
    assert_eq!(w.len(), 1, "no valid line configured, one write: {w:?}");

    let gone = format!("127.0.0.1:{}", unused_port());
    let (code, out) = check_with(AnalogConfig::labjack(&gone, 1.0), false);
    assert_eq!(code, Some(0), "a silent device is a warning: {out}");
    assert!(out.contains(&format!("warning: analog output {gone}: cannot connect")), "{out}");
}

/// Lines that arrive every 20 ms but carry values exposed 1.18 s before (the sinks' thread held
/// up) never raise the valid line: the analog output ages its value from exposure, as the
/// control output does; the same values exposed just now raise it.
#[test]
fn values_exposed_long_before_they_arrive_never_raise_the_valid_line() {
    let dac = Dac::start("labjack", None);
    let out = AnalogOutput::start(&AnalogConfig::labjack(&dac.addr(), 1.0)).unwrap();
    dac.wait_for("valid low at connect", fio0(0));
    for seq in 0..50u64 {
        let mut l = line(seq, Some(0.5));
        l.t_ns = tagdeflect_core::clock::now_epoch_ns() - 1_180_000_000;
        out.take_line(&l);
        std::thread::sleep(Duration::from_millis(20));
    }
    std::thread::sleep(Duration::from_millis(100));
    let w = dac.writes();
    assert_eq!(count(&w, fio0(1)), 0, "the valid line went high for values 1.18 s old: {w:?}");
    let mut seq = 50;
    feed_until(&out, &dac, &mut seq, 0.5, |w| w.iter().any(fio0(1)));
}

/// A lab test run under `[output.analog]` (the pymodbus LabJack) carries its control figures
/// into its folder (`control.json`) and its report prints them ("Control output", report.json's
/// `control`), as the device saw them: every line of the test's feed counted, each value the
/// device acknowledged found among the device's DAC writes of the test's values, the latency's
/// median not below the device's own receipt times from exposure; `report DIR` gives the same.
#[test]
fn a_test_under_the_analog_output_reports_its_control_figures_as_the_device_saw_them() {
    use crate::http::{post, small_rig, tagdeflect_test, Daemon};
    let dac = Dac::start("labjack", None);
    let dir = tempfile::tempdir().unwrap();
    let params = tagdeflect_sim::SimParams { load_law: tagdeflect_sim::LoadLaw::Softening, frame_sets: 600, ..small_rig() };
    let mut cfg = crate::common::beam_rig_config(&params);
    // The small rig's σ is tens of µm: valid up to 1 mm.
    let analog =
        AnalogConfig { offset_v: 1.0, on_invalid: OnInvalid::Volts(0.5), max_sigma_mm: 1.0, ..AnalogConfig::labjack(&dac.addr(), 2.0) };
    cfg.output.analog = Some(analog);
    let cfg_path = dir.path().join("rig.toml");
    std::fs::write(&cfg_path, cfg.to_toml_string()).unwrap();
    let tests_dir = dir.path().join("tests");
    let mut d =
        Daemon::start(&["demo", "--config", cfg_path.to_str().unwrap(), "--http", "127.0.0.1:0", "--tests", tests_dir.to_str().unwrap()]);
    let addr = d.addr(); // once it serves: the token is written by then
    let token_file = tests_dir.join(".token");
    let auth = format!("Bearer {}", std::fs::read_to_string(&token_file).unwrap().trim());
    let body = serde_json::json!({"specimen": "A1", "operator": "A. Tester", "standard": "astm-c1609"});
    let headers = [("Content-Type", "application/json"), ("Authorization", auth.as_str())];
    let (code, answer) = post(addr, "/api/test/start", &headers, body.to_string().as_bytes());
    assert_eq!(code, 200, "{answer}");
    let id = serde_json::from_str::<serde_json::Value>(&answer).unwrap()["id"].as_str().unwrap().to_string();
    let deadline = Instant::now() + Duration::from_secs(120);
    while d.lines().iter().filter(|(_, l)| l.test.as_ref().is_some_and(|t| t.id == id)).count() < 40 {
        assert!(Instant::now() < deadline, "the test's lines did not come");
        std::thread::sleep(Duration::from_millis(100));
    }
    let stopped = tagdeflect_test(addr, &token_file, &["stop"]);
    assert_eq!(d.stop(), Some(0));
    let folder = PathBuf::from(stopped["folder"].as_str().unwrap());
    check_the_control_figures(&folder, &dac, &id);
}

/// The checks of the test above on its stopped folder.
fn check_the_control_figures(folder: &Path, dac: &Dac, id: &str) {
    let control = crate::report_folder::read_json(&folder.join("control.json"));
    assert_eq!(control["test"], id, "{control}");
    let o = &control["outputs"][0];
    assert_eq!((o["kind"].as_str(), o["gauge"].as_str()), (Some("analog"), Some("net_deflection")), "{o}");
    assert_eq!(o["scaling"], serde_json::json!({"volts_per_mm": 2.0, "offset_v": 1.0, "range_v": [0.0, 5.0], "safe_v": 0.5}), "{o}");
    // Every line of the test reached the output.
    let feed: Vec<FeedLine> =
        std::fs::read_to_string(folder.join("feed.jsonl")).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    let n = |k: &str| o[k].as_u64().unwrap_or_else(|| panic!("{k}: {o}"));
    assert_eq!(n("frame_sets"), feed.len() as u64, "{o}");
    // The values acknowledged are among the device's writes of the test's values (2 V/mm from
    // 1 V) received from the test's first exposure to 2 s after its last; a value outside the
    // test (not counted from the test's zero) may equal one of them to the nanometre by chance,
    // rarely: a few such are allowed.
    let volts_of: std::collections::HashMap<u32, i64> =
        feed.iter().filter_map(|l| l.net_deflection_mm.map(|v| ((1.0 + 2.0 * v) as f32).to_bits()).zip(Some(l.t_ns))).collect();
    let (first_s, last_s) = (feed[0].t_ns as f64 * 1e-9, feed[feed.len() - 1].t_ns as f64 * 1e-9 + 2.0);
    let in_test = |w: &&Write| is_dac(w) && w.t >= first_s && w.t <= last_s;
    let seen: Vec<(f64, i64)> =
        dac.writes().iter().filter(in_test).filter_map(|w| volts_of.get(&f32_abcd(w).to_bits()).map(|t_ns| (w.t, *t_ns))).collect();
    let (valid, written) = (n("valid_sets"), n("values_written"));
    assert!(written >= 20, "{o}");
    assert!(written <= seen.len() as u64 && seen.len() as u64 <= written + 3, "{} device writes of the test's values: {o}", seen.len());
    // A value is written only when valid (a valid one may be replaced, or found stale by the
    // time the device's task runs on a loaded machine).
    assert!(written <= valid + 1, "{o}");
    let share = crate::report_folder::read_json(&folder.join("report/report.json"))["control"]["outputs"][0]["valid_share"].as_f64();
    // Read back from report.json by serde_json, whose default float parsing may land one ulp
    // off the value written (its `float_roundtrip` feature is not on): equal within 1e-12.
    let expected = valid as f64 / feed.len() as f64;
    assert!(share.is_some_and(|s| (s - expected).abs() <= 1e-12), "valid share {share:?}, expected {expected}");
    // The latency: acknowledged after the device received the write.
    let mut received_ms: Vec<f64> = seen.iter().map(|(t, t_ns)| t * 1e3 - *t_ns as f64 * 1e-6).collect();
    received_ms.sort_by(f64::total_cmp);
    let lat = &o["latency"];
    let f = |k: &str| lat[k].as_f64().unwrap_or_else(|| panic!("{k}: {lat}"));
    assert_eq!(lat["values"].as_u64(), Some(written), "{lat}");
    assert!(f("p50_ms") >= received_ms[received_ms.len() / 2] - 5.0, "{lat} against the device's receipts {received_ms:?}");
    assert!(f("p50_ms") > 0.0 && f("p50_ms") <= f("p99_ms") && f("p99_ms") <= f("max_ms"), "{lat}");
    println!(
        "test under control: {} sets, valid {:.1} %, exposure → acknowledged {lat}; the device's receipts p50 {:.1} ms",
        feed.len(),
        valid as f64 / feed.len() as f64 * 1e2,
        received_ms[received_ms.len() / 2]
    );
    let dyn_ = &control["dynamics"];
    assert_eq!(
        dyn_["sines"].as_array().map(|s| s.iter().map(|s| s["freq_hz"].as_f64().unwrap()).collect::<Vec<_>>()),
        Some(vec![0.1, 0.5, 2.0])
    );
    // The report prints the section, and `report DIR` gives the same.
    let html = std::fs::read_to_string(folder.join("report/report.html")).unwrap();
    let share_text = format!("{:.1} % of the test's frame sets", valid as f64 / feed.len() as f64 * 1e2);
    assert!(html.contains("<h2>Control output</h2>") && html.contains("Exposure → write acknowledged (live)"), "no section in report.html");
    assert!(html.contains(&share_text), "the valid share {share_text}");
    let again = crate::report_folder::report_dir(folder, &folder.parent().unwrap().join("again"));
    assert_eq!(again["control"], crate::report_folder::read_json(&folder.join("report/report.json"))["control"]);
}
