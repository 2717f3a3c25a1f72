//! `[output.analog]`: the control signal as a voltage on a networked DAQ's analog output,
//! written over Modbus TCP (docs/control.md "Analog output").

use std::net::SocketAddr;

use serde::{Deserialize, Serialize};
use tagdeflect_core::Problem;
use tagdeflect_io::utm::codec::encode;
use tagdeflect_io::utm::config::{RegisterConfig, RegisterKind, ValueType, WordOrder};

use crate::signal::{SignalRule, NET_DEFLECTION};

/// LabJack T-series: DAC0 is FLOAT32 volts at address 1000, DAC1 at 1002 (LabJack Modbus map).
pub const LABJACK_DAC0: u16 = 1000;
/// LabJack T-series: FIO0 is a UINT16 at address 2000 (FIO1 2001, ...), 0 or 1.
pub const LABJACK_FIO0: u16 = 2000;
/// Output range of the T-series DACs, V.
pub const LABJACK_RANGE_V: (f64, f64) = (0.0, 5.0);
/// Largest |voltage| accepted for a holding-register module, V.
pub const MAX_ABS_V: f64 = 100.0;
/// A holding-register module's output range when `range_v` is not given, V.
pub const HOLDING_RANGE_V: (f64, f64) = (-10.0, 10.0);

/// The device's register map (SPEC `device`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum DeviceMap {
    /// LabJack T4/T7/T8: DAC`channel` as FLOAT32 volts; the valid line on FIO0 by default.
    #[serde(rename = "labjack-t")]
    LabjackT,
    /// A holding-register module (ADAM-6224, WAGO 750-5xx, ioLogik ...): `register`,
    /// `data_type`, `scale` (counts per volt), `offset` (counts), `word_order`.
    #[serde(rename = "holding-registers")]
    Generic,
}

/// What the analog output does while the value is invalid or stale, and at stop (SPEC
/// `on_invalid`: `"hold"` or a safe voltage).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub enum OnInvalid {
    /// `"hold"`: keep the last value written (the valid line tells the controller).
    #[default]
    Hold,
    /// A number: go to this safe voltage, V.
    Volts(f64),
}

impl OnInvalid {
    /// The safe voltage, when one is configured.
    pub fn safe_v(self) -> Option<f64> {
        match self {
            OnInvalid::Hold => None,
            OnInvalid::Volts(v) => Some(v),
        }
    }
}

impl Serialize for OnInvalid {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        match self {
            OnInvalid::Hold => s.serialize_str("hold"),
            OnInvalid::Volts(v) => s.serialize_f64(*v),
        }
    }
}

impl<'de> Deserialize<'de> for OnInvalid {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        #[derive(Deserialize)]
        #[serde(untagged)]
        enum Raw {
            Word(String),
            Volts(f64),
        }
        let bad = || serde::de::Error::custom("expected \"hold\" or a safe voltage (a number of volts)");
        match Raw::deserialize(d).map_err(|_| bad())? {
            Raw::Volts(v) => Ok(OnInvalid::Volts(v)),
            Raw::Word(w) if w == "hold" => Ok(OnInvalid::Hold),
            Raw::Word(_) => Err(bad()),
        }
    }
}

/// The digital "data valid" line: a holding register written 0/1 (function 6) or a coil
/// (function 5).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum DigitalOutput {
    /// A holding register written 1 (valid) or 0.
    Register(u16),
    /// A coil written on (valid) or off.
    Coil(u16),
}

/// One register written once after each connect (the device's own watchdog set-up).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RegisterWrite {
    /// 0-based holding register.
    pub register: u16,
    /// Its type.
    #[serde(default)]
    pub data_type: ValueType,
    /// Word order of 32-bit types.
    #[serde(default)]
    pub word_order: WordOrder,
    /// The value written.
    pub value: f64,
}

/// `[output.analog]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AnalogConfig {
    /// The device, `IP:PORT` (never the UTM's address).
    pub address: String,
    /// Modbus unit id.
    #[serde(default = "default_unit")]
    pub unit_id: u8,
    /// `"labjack-t"` or `"holding-registers"`.
    pub device: DeviceMap,
    /// LabJack: the DAC (0 or 1).
    #[serde(default)]
    pub channel: u8,
    /// Generic: the first holding register of the value.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub register: Option<u16>,
    /// Generic: `u16`, `i16` or `f32` (`i32`, `u32` too).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub data_type: Option<ValueType>,
    /// Generic: raw counts per volt.
    #[serde(default = "one")]
    pub scale: f64,
    /// Generic: raw counts at 0 V.
    #[serde(default)]
    pub offset: f64,
    /// Generic: word order of 32-bit types.
    #[serde(default)]
    pub word_order: WordOrder,
    /// The value written: `"net_deflection"` or a `[[gauge]]`.
    #[serde(default = "default_gauge")]
    pub gauge: String,
    /// The value is valid only while its 1-σ is below this, mm.
    #[serde(default = "default_max_sigma")]
    pub max_sigma_mm: f64,
    /// Frame sets without the value before it is stale (the control output's rule).
    #[serde(default = "default_stale_sets")]
    pub stale_sets: u32,
    /// Volts per mm of the value (1 by default).
    #[serde(default = "one")]
    pub volts_per_mm: f64,
    /// Volts at a value of 0.
    #[serde(default)]
    pub offset_v: f64,
    /// The lowest and highest voltage written (the output is clamped); the device's range
    /// when absent (LabJack 0–5 V, a holding-register module ±10 V).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub range_v: Option<[f64; 2]>,
    /// The valid line (LabJack: FIO0 when absent; generic: none when absent).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub valid_output: Option<DigitalOutput>,
    /// `"hold"` (default) or a safe voltage (also written at stop).
    #[serde(default)]
    pub on_invalid: OnInvalid,
    /// Per-request timeout, ms.
    #[serde(default = "default_timeout_ms")]
    pub timeout_ms: f64,
    /// Registers written once after each connect: the device's watchdog (none by default).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub watchdog_writes: Vec<RegisterWrite>,
    /// LabJack: set the device's own watchdog up to trip after this many seconds without a
    /// write (valid line low, the safe voltage when set; `labjack_watchdog`). None: not set.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub labjack_watchdog_s: Option<u32>,
}

fn default_unit() -> u8 {
    1
}
fn one() -> f64 {
    1.0
}
fn default_gauge() -> String {
    NET_DEFLECTION.to_string()
}
fn default_max_sigma() -> f64 {
    0.01
}
fn default_stale_sets() -> u32 {
    1
}
fn default_timeout_ms() -> f64 {
    500.0
}

impl RegisterWrite {
    /// The holding register(s) this write goes to, the value written as it is.
    pub fn register_config(&self) -> RegisterConfig {
        RegisterConfig {
            register: self.register,
            kind: RegisterKind::Holding,
            value_type: self.data_type,
            word_order: self.word_order,
            scale: 1.0,
            offset: 0.0,
        }
    }
}

impl AnalogConfig {
    /// A LabJack T-series at `address` at `volts_per_mm`, 0–5 V, every other key at its default.
    pub fn labjack(address: &str, volts_per_mm: f64) -> AnalogConfig {
        AnalogConfig {
            address: address.to_string(),
            unit_id: default_unit(),
            device: DeviceMap::LabjackT,
            channel: 0,
            register: None,
            data_type: None,
            scale: 1.0,
            offset: 0.0,
            word_order: WordOrder::Abcd,
            gauge: default_gauge(),
            max_sigma_mm: default_max_sigma(),
            stale_sets: default_stale_sets(),
            volts_per_mm,
            offset_v: 0.0,
            range_v: None,
            valid_output: None,
            on_invalid: OnInvalid::Hold,
            timeout_ms: default_timeout_ms(),
            watchdog_writes: Vec::new(),
            labjack_watchdog_s: None,
        }
    }

    /// The device's address.
    pub fn addr(&self) -> Result<SocketAddr, Problem> {
        self.address.parse().map_err(|_| Problem::new("address", format!("\"{}\" is not IP:PORT (e.g. \"192.0.2.20:502\")", self.address)))
    }

    /// The signal's rule of this section (`crate::signal`, the control output's).
    pub fn rule(&self) -> SignalRule {
        SignalRule { gauge: self.gauge.clone(), max_sigma_mm: self.max_sigma_mm, stale_sets: self.stale_sets }
    }

    /// The value's register(s): address, type, word order (raw = volts × scale + offset).
    pub fn value_register(&self) -> RegisterConfig {
        let (register, value_type, word_order) = match self.device {
            DeviceMap::LabjackT => (LABJACK_DAC0 + 2 * self.channel as u16, ValueType::F32, WordOrder::Abcd),
            DeviceMap::Generic => (self.register.unwrap_or(0), self.data_type.unwrap_or_default(), self.word_order),
        };
        RegisterConfig { register, kind: RegisterKind::Holding, value_type, word_order, scale: 1.0, offset: 0.0 }
    }

    /// Raw counts of `volts` as written (LabJack: volts).
    pub fn raw_of(&self, volts: f64) -> f64 {
        match self.device {
            DeviceMap::LabjackT => volts,
            DeviceMap::Generic => volts * self.scale + self.offset,
        }
    }

    /// The output range, V: `range_v`, else the device's.
    pub fn range(&self) -> (f64, f64) {
        match (self.range_v, self.device) {
            (Some([lo, hi]), _) => (lo, hi),
            (None, DeviceMap::LabjackT) => LABJACK_RANGE_V,
            (None, DeviceMap::Generic) => HOLDING_RANGE_V,
        }
    }

    /// The volts written for a value: `offset_v + volts_per_mm × value`, clamped.
    pub fn volts_of(&self, value: f64) -> f64 {
        let (lo, hi) = self.range();
        (self.offset_v + self.volts_per_mm * value).clamp(lo, hi)
    }

    /// The valid line (LabJack's FIO0 by default).
    pub fn valid_line(&self) -> Option<DigitalOutput> {
        match (self.valid_output, self.device) {
            (Some(d), _) => Some(d),
            (None, DeviceMap::LabjackT) => Some(DigitalOutput::Register(LABJACK_FIO0)),
            (None, DeviceMap::Generic) => None,
        }
    }

    /// Checks the section; `gauges` are the `[[gauge]]` names, `utm` the `[utm]` address.
    /// Keys relative to `[output.analog]`.
    pub fn validate(&self, gauges: &[String], utm: Option<&str>) -> Result<(), Problem> {
        let addr = self.addr()?;
        if let Some(u) = utm.filter(|u| same_device(addr, u)) {
            return Err(Problem::new(
                "address",
                format!("{addr} is the UTM's address ({u}): nothing is ever written to the testing machine"),
            ));
        }
        self.rule().validate(gauges)?;
        self.check_map()?;
        self.check_volts()?;
        if !(self.timeout_ms.is_finite() && (1.0..=60_000.0).contains(&self.timeout_ms)) {
            return Err(Problem::new("timeout_ms", format!("{}: expected 1 to 60000 ms", self.timeout_ms)));
        }
        for (i, w) in self.watchdog_writes.iter().enumerate() {
            encode(&w.register_config(), w.value).map_err(|e| Problem::new(format!("watchdog_writes[{i}].value"), e.to_string()))?;
        }
        match (self.labjack_watchdog_s, self.device) {
            (Some(_), DeviceMap::Generic) => Err(Problem::new(
                "labjack_watchdog_s",
                "a LabJack key: a holding-register module's watchdog is set up with watchdog_writes",
            )),
            (Some(s), _) if !(1..=86_400).contains(&s) => {
                Err(Problem::new("labjack_watchdog_s", format!("{s}: expected 1 to 86400 s (the device counts whole seconds)")))
            }
            _ => Ok(()),
        }
    }

    /// The map's own keys.
    fn check_map(&self) -> Result<(), Problem> {
        match self.device {
            DeviceMap::LabjackT => {
                for (key, set) in [("register", self.register.is_some()), ("data_type", self.data_type.is_some())] {
                    if set {
                        return Err(Problem::new(
                            key,
                            "the LabJack T-series map writes DAC0/DAC1 as FLOAT32 volts: choose the DAC with `channel`",
                        ));
                    }
                }
                if self.channel > 1 {
                    return Err(Problem::new("channel", format!("{}: the T-series have DAC0 and DAC1", self.channel)));
                }
            }
            DeviceMap::Generic => {
                if self.register.is_none() {
                    return Err(Problem::new("register", "a holding-register module needs the value's holding register"));
                }
                if self.data_type.is_none() {
                    return Err(Problem::new("data_type", "a holding-register module needs the value's type (u16, i16 or f32)"));
                }
                if !(self.scale.is_finite() && self.scale != 0.0 && self.offset.is_finite()) {
                    return Err(Problem::new("scale", "counts per volt must be a non-zero finite number and offset finite"));
                }
            }
        }
        Ok(())
    }

    /// `volts_per_mm`, `offset_v`, the range, `safe_v`, and the range as raw counts.
    fn check_volts(&self) -> Result<(), Problem> {
        if !(self.volts_per_mm.is_finite() && self.volts_per_mm != 0.0) {
            return Err(Problem::new("volts_per_mm", format!("{}: expected a non-zero number", self.volts_per_mm)));
        }
        if !self.offset_v.is_finite() {
            return Err(Problem::new("offset_v", "expected a finite number of volts"));
        }
        let (lo, hi) = if self.device == DeviceMap::LabjackT { LABJACK_RANGE_V } else { (-MAX_ABS_V, MAX_ABS_V) };
        let (min_v, max_v) = self.range();
        for v in [min_v, max_v] {
            if !(v.is_finite() && (lo..=hi).contains(&v)) {
                return Err(Problem::new("range_v", format!("{v} V: the {:?} map outputs {lo} to {hi} V", self.device)));
            }
        }
        if min_v >= max_v {
            return Err(Problem::new("range_v", format!("[{min_v}, {max_v}]: the lowest voltage must be below the highest")));
        }
        if let Some(s) = self.on_invalid.safe_v() {
            if !(s.is_finite() && (min_v..=max_v).contains(&s)) {
                return Err(Problem::new("on_invalid", format!("{s} V is outside range_v = [{min_v}, {max_v}] V")));
            }
        }
        let reg = self.value_register();
        for v in [min_v, max_v] {
            encode(&reg, self.raw_of(v)).map_err(|e| Problem::new("scale", format!("{v} V: {e}")))?;
        }
        Ok(())
    }
}

/// True when `utm` (`[utm] address`) names the device at `addr`.
fn same_device(addr: SocketAddr, utm: &str) -> bool {
    match utm.parse::<SocketAddr>() {
        Ok(u) => u == addr,
        Err(_) => utm.rsplit_once(':').is_some_and(|(host, port)| {
            host.eq_ignore_ascii_case("localhost") && addr.ip().is_loopback() && port.parse() == Ok(addr.port())
        }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn checks_name_the_key() {
        let c = AnalogConfig::labjack("192.0.2.20:502", 0.5);
        assert!(c.validate(&[], Some("192.0.2.10:502")).is_ok());
        let key = |c: &AnalogConfig| c.validate(&[], Some("192.0.2.10:502")).unwrap_err().key;
        assert_eq!(key(&AnalogConfig { address: "192.0.2.10:502".into(), ..c.clone() }), "address");
        assert_eq!(key(&AnalogConfig { address: "dac.lab".into(), ..c.clone() }), "address");
        assert_eq!(c.validate(&[], Some("localhost:502")).map(|_| ()), Ok(()));
        let local = AnalogConfig { address: "127.0.0.1:502".into(), ..c.clone() };
        assert_eq!(local.validate(&[], Some("localhost:502")).unwrap_err().key, "address");
        assert_eq!(key(&AnalogConfig { range_v: Some([0.0, 10.0]), ..c.clone() }), "range_v");
        assert_eq!(key(&AnalogConfig { range_v: Some([4.0, 3.0]), ..c.clone() }), "range_v");
        assert_eq!(key(&AnalogConfig { on_invalid: OnInvalid::Volts(6.0), ..c.clone() }), "on_invalid");
        assert_eq!(key(&AnalogConfig { volts_per_mm: 0.0, ..c.clone() }), "volts_per_mm");
        assert_eq!(key(&AnalogConfig { gauge: "cmod".into(), ..c.clone() }), "gauge");
        assert_eq!(key(&AnalogConfig { channel: 2, ..c.clone() }), "channel");
        assert_eq!(key(&AnalogConfig { register: Some(3), ..c.clone() }), "register");
        let g = AnalogConfig {
            device: DeviceMap::Generic,
            register: Some(0),
            data_type: Some(ValueType::U16),
            scale: 3276.7,
            offset: 0.0,
            range_v: Some([0.0, 10.0]),
            ..c.clone()
        };
        assert!(g.validate(&[], None).is_ok());
        // -1 V is -3277 counts: outside u16.
        assert_eq!(key(&AnalogConfig { range_v: Some([-1.0, 10.0]), ..g.clone() }), "scale");
        assert_eq!(key(&AnalogConfig { data_type: None, ..g.clone() }), "data_type");
        assert_eq!(key(&AnalogConfig { register: None, ..g }), "register");
    }

    #[test]
    fn volts_are_scaled_offset_and_clamped() {
        let c = AnalogConfig { offset_v: 1.0, ..AnalogConfig::labjack("192.0.2.20:502", 0.5) };
        assert_eq!(c.volts_of(2.0), 2.0);
        assert_eq!(c.volts_of(100.0), 5.0);
        assert_eq!(c.volts_of(-100.0), 0.0);
        assert_eq!(c.value_register().register, 1000);
        assert_eq!(c.valid_line(), Some(DigitalOutput::Register(2000)));
    }
}
