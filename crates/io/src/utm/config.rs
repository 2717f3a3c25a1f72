//! `[utm]`: the testing machine over Modbus TCP, and its registers.

use serde::{Deserialize, Serialize};
use std::fmt;

use tagdeflect_core::Problem;

/// Lowest UTM polling rate accepted, Hz.
pub const MIN_POLL_HZ: f64 = 0.01;
/// Highest UTM polling rate accepted, Hz.
pub const MAX_POLL_HZ: f64 = 1000.0;
/// Longest Modbus request timeout accepted, ms.
pub const MAX_TIMEOUT_MS: f64 = 60_000.0;

/// `utm.address`: a Modbus TCP peer or the built-in simulated UTM, parsed once here. Written
/// back as the same string.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum UtmAddress {
    /// The built-in simulated UTM (`"sim"`).
    Sim,
    /// `host:port` of a Modbus TCP server (checked by [`UtmConfig::validate`]).
    Tcp(String),
}

impl UtmAddress {
    /// True for the simulated UTM.
    pub fn is_sim(&self) -> bool {
        matches!(self, UtmAddress::Sim)
    }
}

impl fmt::Display for UtmAddress {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            UtmAddress::Sim => f.write_str("sim"),
            UtmAddress::Tcp(a) => f.write_str(a),
        }
    }
}

impl From<&str> for UtmAddress {
    fn from(s: &str) -> Self {
        if s == "sim" {
            UtmAddress::Sim
        } else {
            UtmAddress::Tcp(s.to_string())
        }
    }
}

impl Serialize for UtmAddress {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(&self.to_string())
    }
}

impl<'de> Deserialize<'de> for UtmAddress {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        Ok(UtmAddress::from(String::deserialize(d)?.as_str()))
    }
}

/// `[utm]`: the testing machine over Modbus TCP.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct UtmConfig {
    /// `host:port`, or `sim` for the built-in simulated UTM.
    pub address: UtmAddress,
    /// Modbus unit (slave) id.
    #[serde(default = "default_unit")]
    pub unit: u8,
    /// Polling rate, Hz.
    #[serde(default = "default_poll_hz")]
    pub poll_hz: f64,
    /// Per-request timeout, ms (extension; the Modbus client has none of its own).
    #[serde(default = "default_timeout_ms")]
    pub timeout_ms: f64,
    /// The load channel, kN.
    pub load: RegisterConfig,
    /// The stroke channel, mm.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stroke: Option<RegisterConfig>,
}

fn default_unit() -> u8 {
    1
}
fn default_poll_hz() -> f64 {
    50.0
}
fn default_timeout_ms() -> f64 {
    200.0
}

/// One Modbus value: `value = raw * scale + offset`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RegisterConfig {
    /// 0-based register address.
    pub register: u16,
    /// Input or holding register (both only ever read).
    #[serde(default)]
    pub kind: RegisterKind,
    /// Value type.
    #[serde(rename = "type", default)]
    pub value_type: ValueType,
    /// Word order of 32-bit types.
    #[serde(default)]
    pub word_order: WordOrder,
    /// Scale applied to the raw value.
    #[serde(default = "one")]
    pub scale: f64,
    /// Offset added after scaling.
    #[serde(default)]
    pub offset: f64,
}

fn one() -> f64 {
    1.0
}

/// Modbus register table.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum RegisterKind {
    /// Input registers (function 4).
    #[default]
    Input,
    /// Holding registers (function 3), read only.
    Holding,
}

/// Modbus value type.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ValueType {
    /// IEEE 754 single, two registers.
    #[default]
    F32,
    /// Signed 16-bit, one register.
    I16,
    /// Unsigned 16-bit, one register.
    U16,
    /// Signed 32-bit, two registers.
    I32,
    /// Unsigned 32-bit, two registers.
    U32,
}

impl ValueType {
    /// Number of 16-bit registers the type spans.
    pub fn registers(self) -> u16 {
        match self {
            ValueType::I16 | ValueType::U16 => 1,
            _ => 2,
        }
    }
}

/// Byte/word order of 32-bit values, named by the order of bytes A (most significant) .. D.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub enum WordOrder {
    /// Big endian, high word first (`ABCD` or `big`).
    #[default]
    #[serde(rename = "ABCD", alias = "big")]
    Abcd,
    /// Low word first (`CDAB` or `little`).
    #[serde(rename = "CDAB", alias = "little")]
    Cdab,
    /// High word first, bytes swapped in each word.
    #[serde(rename = "BADC")]
    Badc,
    /// Fully little endian.
    #[serde(rename = "DCBA")]
    Dcba,
}

impl UtmConfig {
    /// Checks `[utm]`; keys relative to it.
    pub fn validate(&self) -> Result<(), Problem> {
        if let UtmAddress::Tcp(a) = &self.address {
            if a.parse::<std::net::SocketAddr>().is_err() && !a.contains(':') {
                return Err(Problem::new("address", format!("\"{a}\" is not host:port (e.g. \"192.0.2.10:502\") or \"sim\"")));
            }
        }
        if !(self.poll_hz.is_finite() && (MIN_POLL_HZ..=MAX_POLL_HZ).contains(&self.poll_hz)) {
            return Err(Problem::new("poll_hz", format!("must be from {MIN_POLL_HZ} to {MAX_POLL_HZ} Hz, got {}", self.poll_hz)));
        }
        if !(self.timeout_ms.is_finite() && self.timeout_ms >= 1.0 && self.timeout_ms <= MAX_TIMEOUT_MS) {
            return Err(Problem::new("timeout_ms", format!("must be from 1 to {MAX_TIMEOUT_MS} milliseconds, got {}", self.timeout_ms)));
        }
        for (name, r) in [("load", Some(&self.load)), ("stroke", self.stroke.as_ref())] {
            if let Some(r) = r {
                if !(r.scale.is_finite() && r.offset.is_finite()) || r.scale == 0.0 {
                    return Err(Problem::new(format!("{name}.scale"), "scale must be a non-zero finite number and offset finite"));
                }
                if r.register as u32 + r.value_type.registers() as u32 > 65536 {
                    return Err(Problem::new(format!("{name}.register"), "register address out of range"));
                }
            }
        }
        Ok(())
    }
}
