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
/// Largest |voltage| accepted for a generic module, V.
pub const MAX_ABS_V: f64 = 100.0;

/// The device's register map.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum DeviceMap {
    /// LabJack T4/T7/T8: DAC`dac` as FLOAT32 volts; the valid line on FIO0 by default.
    #[serde(rename = "labjack-t")]
    LabjackT,
    /// A holding-register module (ADAM-6224, WAGO 750-5xx, ioLogik ...): `register`,
    /// `data_type`, `scale` (counts per volt), `offset` (counts), `word_order`.
    #[serde(rename = "generic")]
    Generic,
}

/// What the analog output does while the value is invalid or stale.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum OnInvalid {
    /// Keep the last value written (the valid line tells the controller).
    #[default]
    Hold,
    /// Write `safe_v`.
    Safe,
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
    pub device: String,
    /// Modbus unit id.
    #[serde(default = "default_unit")]
    pub unit_id: u8,
    /// `"labjack-t"` or `"generic"`.
    pub map: DeviceMap,
    /// LabJack: the DAC (0 or 1).
    #[serde(default)]
    pub dac: u8,
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
    /// Volts per mm of the value.
    pub volts_per_mm: f64,
    /// Volts at a value of 0.
    #[serde(default)]
    pub offset_v: f64,
    /// Lowest voltage written (the output is clamped).
    pub min_v: f64,
    /// Highest voltage written.
    pub max_v: f64,
    /// The valid line (LabJack: FIO0 when absent; generic: none when absent).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub valid_output: Option<DigitalOutput>,
    /// `"hold"` (default) or `"safe"`.
    #[serde(default)]
    pub on_invalid: OnInvalid,
    /// The safe value, V (with `on_invalid = "safe"`; also written at stop).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub safe_v: Option<f64>,
    /// Per-request timeout, ms.
    #[serde(default = "default_timeout_ms")]
    pub timeout_ms: f64,
    /// Registers written once after each connect: the device's watchdog (none by default).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub watchdog_writes: Vec<RegisterWrite>,
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

impl AnalogConfig {
    /// A LabJack T-series on `device` at `volts_per_mm`, 0–5 V, every other key at its default.
    pub fn labjack(device: &str, volts_per_mm: f64) -> AnalogConfig {
        AnalogConfig {
            device: device.to_string(),
            unit_id: default_unit(),
            map: DeviceMap::LabjackT,
            dac: 0,
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
            min_v: LABJACK_RANGE_V.0,
            max_v: LABJACK_RANGE_V.1,
            valid_output: None,
            on_invalid: OnInvalid::Hold,
            safe_v: None,
            timeout_ms: default_timeout_ms(),
            watchdog_writes: Vec::new(),
        }
    }

    /// The device's address.
    pub fn addr(&self) -> Result<SocketAddr, Problem> {
        self.device.parse().map_err(|_| Problem::new("device", format!("\"{}\" is not IP:PORT (e.g. \"192.0.2.20:502\")", self.device)))
    }

    /// The signal's rule of this section (`crate::signal`, the control output's).
    pub fn rule(&self) -> SignalRule {
        SignalRule { gauge: self.gauge.clone(), max_sigma_mm: self.max_sigma_mm, stale_sets: self.stale_sets }
    }

    /// The value's register(s): address, type, word order (raw = volts × scale + offset).
    pub fn value_register(&self) -> RegisterConfig {
        let (register, value_type, word_order) = match self.map {
            DeviceMap::LabjackT => (LABJACK_DAC0 + 2 * self.dac as u16, ValueType::F32, WordOrder::Abcd),
            DeviceMap::Generic => (self.register.unwrap_or(0), self.data_type.unwrap_or_default(), self.word_order),
        };
        RegisterConfig { register, kind: RegisterKind::Holding, value_type, word_order, scale: 1.0, offset: 0.0 }
    }

    /// Raw counts of `volts` as written (LabJack: volts).
    pub fn raw_of(&self, volts: f64) -> f64 {
        match self.map {
            DeviceMap::LabjackT => volts,
            DeviceMap::Generic => volts * self.scale + self.offset,
        }
    }

    /// The volts written for a value: `offset_v + volts_per_mm × value`, clamped.
    pub fn volts_of(&self, value: f64) -> f64 {
        (self.offset_v + self.volts_per_mm * value).clamp(self.min_v, self.max_v)
    }

    /// The valid line (LabJack's FIO0 by default).
    pub fn valid_line(&self) -> Option<DigitalOutput> {
        match (self.valid_output, self.map) {
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
                "device",
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
            let reg = RegisterConfig {
                register: w.register,
                kind: RegisterKind::Holding,
                value_type: w.data_type,
                word_order: w.word_order,
                scale: 1.0,
                offset: 0.0,
            };
            encode(&reg, w.value).map_err(|e| Problem::new(format!("watchdog_writes[{i}].value"), e.to_string()))?;
        }
        Ok(())
    }

    /// The map's own keys.
    fn check_map(&self) -> Result<(), Problem> {
        match self.map {
            DeviceMap::LabjackT => {
                for (key, set) in [("register", self.register.is_some()), ("data_type", self.data_type.is_some())] {
                    if set {
                        return Err(Problem::new(
                            key,
                            "the LabJack T-series map writes DAC0/DAC1 as FLOAT32 volts: choose the DAC with `dac`",
                        ));
                    }
                }
                if self.dac > 1 {
                    return Err(Problem::new("dac", format!("{}: the T-series have DAC0 and DAC1", self.dac)));
                }
            }
            DeviceMap::Generic => {
                if self.register.is_none() {
                    return Err(Problem::new("register", "a generic module needs the value's holding register"));
                }
                if self.data_type.is_none() {
                    return Err(Problem::new("data_type", "a generic module needs the value's type (u16, i16 or f32)"));
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
        let (lo, hi) = if self.map == DeviceMap::LabjackT { LABJACK_RANGE_V } else { (-MAX_ABS_V, MAX_ABS_V) };
        for (key, v) in [("min_v", self.min_v), ("max_v", self.max_v)] {
            if !(v.is_finite() && (lo..=hi).contains(&v)) {
                return Err(Problem::new(key, format!("{v} V: the {:?} map outputs {lo} to {hi} V", self.map)));
            }
        }
        if self.min_v >= self.max_v {
            return Err(Problem::new("max_v", format!("{} V is not above min_v = {} V", self.max_v, self.min_v)));
        }
        match (self.on_invalid, self.safe_v) {
            (OnInvalid::Safe, None) => return Err(Problem::new("safe_v", "on_invalid = \"safe\" needs the safe value in volts")),
            (_, Some(s)) if !(s.is_finite() && (self.min_v..=self.max_v).contains(&s)) => {
                return Err(Problem::new("safe_v", format!("{s} V is outside min_v..max_v = {}..{} V", self.min_v, self.max_v)));
            }
            _ => {}
        }
        let reg = self.value_register();
        for v in [self.min_v, self.max_v] {
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
        assert_eq!(key(&AnalogConfig { device: "192.0.2.10:502".into(), ..c.clone() }), "device");
        assert_eq!(key(&AnalogConfig { device: "dac.lab".into(), ..c.clone() }), "device");
        assert_eq!(c.validate(&[], Some("localhost:502")).map(|_| ()), Ok(()));
        let local = AnalogConfig { device: "127.0.0.1:502".into(), ..c.clone() };
        assert_eq!(local.validate(&[], Some("localhost:502")).unwrap_err().key, "device");
        assert_eq!(key(&AnalogConfig { max_v: 10.0, ..c.clone() }), "max_v");
        assert_eq!(key(&AnalogConfig { min_v: 4.0, max_v: 3.0, ..c.clone() }), "max_v");
        assert_eq!(key(&AnalogConfig { on_invalid: OnInvalid::Safe, ..c.clone() }), "safe_v");
        assert_eq!(key(&AnalogConfig { on_invalid: OnInvalid::Safe, safe_v: Some(6.0), ..c.clone() }), "safe_v");
        assert_eq!(key(&AnalogConfig { volts_per_mm: 0.0, ..c.clone() }), "volts_per_mm");
        assert_eq!(key(&AnalogConfig { gauge: "cmod".into(), ..c.clone() }), "gauge");
        assert_eq!(key(&AnalogConfig { dac: 2, ..c.clone() }), "dac");
        assert_eq!(key(&AnalogConfig { register: Some(3), ..c.clone() }), "register");
        let g = AnalogConfig {
            map: DeviceMap::Generic,
            register: Some(0),
            data_type: Some(ValueType::U16),
            scale: 3276.7,
            offset: 0.0,
            min_v: 0.0,
            max_v: 10.0,
            ..c.clone()
        };
        assert!(g.validate(&[], None).is_ok());
        // -1 V is -3277 counts: outside u16.
        assert_eq!(key(&AnalogConfig { min_v: -1.0, ..g.clone() }), "scale");
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
