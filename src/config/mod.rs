//! The configuration file (SPEC "Configuration"), checked once, whole, when it is read.
//!
//! The flow of [`Config::load`]:
//!
//! 1. **read raw** (`raw.rs`): the file is read (at most [`MAX_CONFIG_BYTES`]) and parsed as
//!    TOML into *raw* structs that keep the source span of every value validation may
//!    complain about; a syntax or type error is located by line and key there;
//! 2. **deserialize the schema** (`schema.rs`, [`sim`], [`beam`]): tables that need no spans
//!    deserialize straight into their clean structs, with their defaults;
//! 3. **validate** (`validate.rs`): every limit of every consumer is checked with file, line
//!    and key ([`ConfigError`]), so nothing fails later than `tagdeflect check` would;
//! 4. **resolve calibration** ([`calibration`]): as each camera is checked, its intrinsics
//!    are taken inline or imported from its calibration file (OpenCV, Kalibr, ROS), relative
//!    to the config's folder.
//!
//! The result is the clean [`Config`] the rest of the program uses.
//! [`Config::to_toml_string`] writes a config back (recordings carry the config in force); it
//! always writes resolved intrinsics, so a recording does not depend on calibration files
//! next to the original config.

use std::path::Path;

pub mod beam;
pub mod calibration;
mod raw;
mod schema;
pub mod sim;
mod validate;

pub use beam::BeamConfig;
pub use calibration::{load_calibration, parse_calibration, CalibrationError};
pub(crate) use raw::read_text_limited;
pub use raw::{ConfigError, MAX_CONFIG_BYTES};
pub use schema::*;
pub use validate::{MAX_FPS, MAX_POLL_HZ, MAX_TIMEOUT_MS, MAX_TOLERANCE_MS, MIN_FPS, MIN_POLL_HZ, RESERVED_NAMES};

impl Config {
    /// Reads and validates a config file; relative paths are relative to its folder.
    pub fn load(path: &Path) -> Result<Config, ConfigError> {
        let text = raw::read(path)?;
        Self::from_toml_str(&text, path)
    }

    /// Parses and validates config text. `path` names the file in errors and anchors
    /// relative paths (calibration files).
    pub fn from_toml_str(text: &str, path: &Path) -> Result<Config, ConfigError> {
        let loc = raw::Locator { file: path, text };
        let raw = raw::parse(&loc)?;
        validate::config(&loc, raw)
    }

    /// Writes the config as TOML (resolved intrinsics inline).
    pub fn to_toml_string(&self) -> String {
        toml::to_string(self).expect("config serialises")
    }
}
