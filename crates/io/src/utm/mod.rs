//! The testing machine (UTM): samples, their interpolation, the Modbus TCP client and the
//! simulated UTM server.

pub mod codec;
pub mod modbus;
pub mod relay;
pub mod sim_server;

pub use codec::{decode, encode, DecodeError, EncodeError};
pub use modbus::{run_poller, PollerError, UtmEvent};
pub use sim_server::{serve_sim_utm, start_sim_utm, SimUtm, UtmModel};
pub use tagdeflect_core::utm_sample::{UtmHistory, UtmSample};

pub mod config;
pub use config::*;
