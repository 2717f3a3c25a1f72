//! `tagdeflect check` of the analog output's device: reachable, its identity, and — only when
//! asked (`check --write-test`) — a test write of the safe state (docs/control.md "Checking
//! the device").
//!
//! Identity: a LabJack T-series answers its product ID (`PRODUCT_ID`, address 60000, FLOAT32:
//! 4 = T4, 7 = T7, 8 = T8) and serial number (`SERIAL_NUMBER`, 60028, UINT32), as LabJack's
//! Modbus map gives them (also LabJack's own example `Examples/Basic/eReadAddresses.py` of
//! labjack-ljm-python); a holding-register module is read at the value's configured register.

use tagdeflect_io::utm::config::ValueType;

use super::config::{AnalogConfig, DeviceMap};
use super::device::{Device, DeviceFault};

/// LabJack T-series: `PRODUCT_ID`, FLOAT32.
pub const LABJACK_PRODUCT_ID: u16 = 60000;
/// LabJack T-series: `SERIAL_NUMBER`, UINT32.
pub const LABJACK_SERIAL_NUMBER: u16 = 60028;

/// What the device said.
#[derive(Debug, Clone, PartialEq)]
pub enum Identity {
    /// A LabJack T-series: its product ID (4, 7, 8) and serial number.
    Labjack {
        /// `PRODUCT_ID`.
        product_id: f32,
        /// `SERIAL_NUMBER`.
        serial: u32,
    },
    /// A holding-register module: the raw words of the value's register(s).
    Generic {
        /// The register read.
        register: u16,
        /// Its words.
        words: Vec<u16>,
    },
}

impl std::fmt::Display for Identity {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Identity::Labjack { product_id, serial } => {
                let model = match *product_id as i32 {
                    4 | 7 | 8 if product_id.fract() == 0.0 => format!("T{}", *product_id as i32),
                    _ => format!("an unknown product ID {product_id}"),
                };
                write!(f, "LabJack {model}, serial number {serial}")
            }
            Identity::Generic { register, words } => write!(f, "holding register {register} reads {words:?}"),
        }
    }
}

/// The test write (`check --write-test`): the valid line low, then the safe voltage.
#[derive(Debug, Clone, PartialEq)]
pub struct WriteTest {
    /// The voltage written: `on_invalid`'s, or the voltage of a zero value (`offset_v`,
    /// clamped) when `on_invalid = "hold"`.
    pub volts: f64,
    /// The value's register(s) read back after the write.
    pub read_back: Vec<u16>,
    /// Whether the read-back equals the written words.
    pub matches: bool,
}

/// The device's answer to `check`.
#[derive(Debug, Clone, PartialEq)]
pub struct Probe {
    /// What it is.
    pub identity: Identity,
    /// The test write, when asked.
    pub write_test: Option<WriteTest>,
}

impl AnalogConfig {
    /// The safe voltage of the test write: `on_invalid`'s, else a zero value's.
    pub fn test_write_v(&self) -> f64 {
        self.on_invalid.safe_v().unwrap_or_else(|| self.volts_of(0.0))
    }
}

/// Connects, reads the identity and, with `write_test`, writes the safe state (the valid line
/// low first). Nothing else is written.
pub async fn probe(config: &AnalogConfig, write_test: bool) -> Result<Probe, DeviceFault> {
    let addr = config.addr().map_err(|p| DeviceFault::Connect { addr: ([0, 0, 0, 0], 0).into(), detail: p.to_string() })?;
    let mut device = Device::new(config, addr);
    device.connect().await?;
    let identity = match config.device {
        DeviceMap::LabjackT => {
            let p = device.read_holding(LABJACK_PRODUCT_ID, 2).await?;
            let s = device.read_holding(LABJACK_SERIAL_NUMBER, 2).await?;
            Identity::Labjack {
                product_id: f32::from_bits(((p[0] as u32) << 16) | p[1] as u32),
                serial: ((s[0] as u32) << 16) | s[1] as u32,
            }
        }
        DeviceMap::Generic => {
            let reg = config.value_register();
            Identity::Generic { register: reg.register, words: device.read_holding(reg.register, words_of(reg.value_type)).await? }
        }
    };
    let write_test = if write_test { Some(test_write(&mut device, config).await?) } else { None };
    device.drop_connection();
    Ok(Probe { identity, write_test })
}

async fn test_write(device: &mut Device, config: &AnalogConfig) -> Result<WriteTest, DeviceFault> {
    if let Some(line) = config.valid_line() {
        device.write_line(line, false).await?;
    }
    let volts = config.test_write_v();
    let reg = config.value_register();
    device.write_value(&reg, config.raw_of(volts)).await?;
    let read_back = device.read_holding(reg.register, words_of(reg.value_type)).await?;
    let written = tagdeflect_io::utm::codec::encode(&reg, config.raw_of(volts)).unwrap_or_default();
    Ok(WriteTest { volts, matches: read_back == written, read_back })
}

fn words_of(t: ValueType) -> u16 {
    match t {
        ValueType::U16 | ValueType::I16 => 1,
        _ => 2,
    }
}
