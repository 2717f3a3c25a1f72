//! `[output.control]`: the deflection as a control signal (SPEC "Control output").

use serde::{Deserialize, Serialize};
use std::net::SocketAddr;
use tagdeflect_core::listen::{parse_listen_addr, ListenAddrError};

/// `[output.control]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ControlConfig {
    /// Address of the Modbus TCP server (a listen address, `tagdeflect_core::listen`; loopback
    /// unless set otherwise).
    pub modbus: String,
    /// The value served: `"net_deflection"` (the feed's `net_deflection_mm`) or the name of
    /// a `[[gauge]]`.
    #[serde(default = "default_gauge")]
    pub gauge: String,
    /// The value is valid only while its 1-σ is below this, mm.
    #[serde(default = "default_max_sigma")]
    pub max_sigma_mm: f64,
    /// (extension) The value turns invalid once its tags were not solved in this many
    /// consecutive frame sets, or no frame set came for this many frame periods (plus one).
    #[serde(default = "default_stale_sets")]
    pub stale_sets: u32,
}

use crate::signal::SignalRule;
pub use crate::signal::NET_DEFLECTION;

/// The port of the address examples in messages (SPEC's `127.0.0.1:5020`).
pub const EXAMPLE_PORT: u16 = 5020;

fn default_gauge() -> String {
    NET_DEFLECTION.to_string()
}
fn default_max_sigma() -> f64 {
    0.01
}
fn default_stale_sets() -> u32 {
    1
}

impl ControlConfig {
    /// The control output on `modbus` with every other key at its default.
    pub fn on(modbus: &str) -> ControlConfig {
        ControlConfig {
            modbus: modbus.to_string(),
            gauge: default_gauge(),
            max_sigma_mm: default_max_sigma(),
            stale_sets: default_stale_sets(),
        }
    }

    /// The server's address.
    pub fn addr(&self) -> Result<SocketAddr, ListenAddrError> {
        parse_listen_addr(&self.modbus, EXAMPLE_PORT)
    }

    /// Checks the section against the configured `[[gauge]]` names `gauges` (the served
    /// `gauge` must be one of them, so the check needs that other section: not a plain
    /// `validate`). Keys relative to `[output.control]`.
    pub fn validate_against(&self, gauges: &[String]) -> Result<(), tagdeflect_core::Problem> {
        use tagdeflect_core::Problem;
        self.addr().map_err(|e| Problem::new("modbus", e.to_string()))?;
        self.rule().validate(gauges)
    }

    /// The signal's rule of this section (`crate::signal`).
    pub fn rule(&self) -> SignalRule {
        SignalRule { gauge: self.gauge.clone(), max_sigma_mm: self.max_sigma_mm, stale_sets: self.stale_sets }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn checks_name_the_key() {
        let c = ControlConfig::on("127.0.0.1:5020");
        assert!(c.validate_against(&[]).is_ok());
        let bad = ControlConfig { modbus: "localhost".into(), ..c.clone() };
        assert_eq!(bad.validate_against(&[]).unwrap_err().key, "modbus");
        let bad = ControlConfig { gauge: "cmod".into(), ..c.clone() };
        assert_eq!(bad.validate_against(&[]).unwrap_err().key, "gauge");
        assert!(bad.validate_against(&["cmod".into()]).is_ok());
        let bad = ControlConfig { max_sigma_mm: 0.0, ..c.clone() };
        assert_eq!(bad.validate_against(&[]).unwrap_err().key, "max_sigma_mm");
        let bad = ControlConfig { stale_sets: 0, ..c };
        assert_eq!(bad.validate_against(&[]).unwrap_err().key, "stale_sets");
    }
}
