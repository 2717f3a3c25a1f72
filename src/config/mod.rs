//! The configuration file (SPEC "Configuration"), checked once, whole, when it is read.
//!
//! Every section belongs to the component that uses it — its type and its checks live there
//! (`[[camera]]`, `[world]`, `[background]`, `[specimen]` in `tagdeflect_core`; `[sync]` and
//! `[utm]` in `tagdeflect_io`; `[measure]`, `[[gauge]]`, `[clock_check]` in
//! `tagdeflect_estimate`; `[output]` with `[output.mqtt]` in `tagdeflect_sinks`; `[report]` in
//! `tagdeflect_report`; `[sim]` in `tagdeflect_sim`). This module only assembles them:
//!
//! 1. **read** ([`MAX_CONFIG_BYTES`] at most) and parse the TOML into the sections *as
//!    written* (`raw.rs`); a syntax or type error is located by line and key there;
//! 2. **check** each section with its component's own `validate`/`resolve` (a problem is a key
//!    path and a message, [`tagdeflect_core::Problem`]), then the checks that span sections
//!    (`validate.rs`): nothing may fail later than `tagdeflect check` would;
//! 3. **locate** a problem: the one [`locate::Locator`] turns its key path into the line it is
//!    written on ([`ConfigError`]: file, line, key, message).
//!
//! A config built in code (the simulated rig, `demo`) is written as TOML and read back through
//! the same steps ([`Config::from_sim`]). [`Config::to_toml_string`] writes a config back
//! (recordings carry the config in force); it always writes resolved intrinsics, so a
//! recording does not depend on calibration files next to the original config.

use std::fmt;
use std::path::{Path, PathBuf};

pub mod locate;
mod raw;
mod schema;
mod validate;

pub use schema::*;

/// A recording opened with the program's whole config.
pub type Recording = tagdeflect_io::recording::Recording<Config>;
pub use tagdeflect_core::text_file::{read_text_limited, MAX_CONFIG_BYTES};

// The sections' types, where the rest of the program (and its tests) find them.
pub use tagdeflect_core::beam::BeamConfig;
pub use tagdeflect_core::calibration_file::{calibration_file_path, load_calibration, parse_calibration, CalibrationError};
pub use tagdeflect_core::camera_config::{CameraConfig, CameraSource, MAX_FPS, MIN_FPS, RESERVED_NAMES};
pub use tagdeflect_core::rig::{BackgroundConfig, BackgroundTag, SpecimenConfig, SpecimenTag, TagRole, WorldConfig};
pub use tagdeflect_estimate::measure_config::MeasureConfig;
pub use tagdeflect_io::sync::{SyncConfig, MAX_TOLERANCE_MS};
pub use tagdeflect_io::utm::config::{
    RegisterConfig, RegisterKind, UtmAddress, UtmConfig, ValueType, WordOrder, MAX_POLL_HZ, MAX_TIMEOUT_MS, MIN_POLL_HZ,
};
pub use tagdeflect_sinks::output::OutputConfig;

/// A configuration problem, located in its file.
#[derive(Debug, thiserror::Error)]
pub struct ConfigError {
    /// The file the problem is in.
    pub file: PathBuf,
    /// 1-based line, when known.
    pub line: Option<usize>,
    /// Dotted key path, e.g. `camera[1].name`.
    pub key: Option<String>,
    /// What is wrong and what is expected.
    pub message: String,
}

impl fmt::Display for ConfigError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}", self.file.display())?;
        if let Some(line) = self.line {
            write!(f, ":{line}")?;
        }
        if let Some(key) = &self.key {
            write!(f, ": `{key}`")?;
        }
        write!(f, ": {}", self.message)
    }
}

impl Config {
    /// Reads and validates a config file; relative paths are relative to its folder.
    pub fn load(path: &Path) -> Result<Config, ConfigError> {
        let text = read_text_limited(path).map_err(|e| ConfigError {
            file: path.to_path_buf(),
            line: None,
            key: None,
            message: format!("cannot read the config file: {e}"),
        })?;
        Self::from_toml_str(&text, path)
    }

    /// Parses and validates config text. `path` names the file in errors and anchors
    /// relative paths (calibration files).
    pub fn from_toml_str(text: &str, path: &Path) -> Result<Config, ConfigError> {
        let raw = raw::parse(text, path)?;
        let base = path.parent().unwrap_or(Path::new("."));
        validate::config(raw, base).map_err(|p| {
            let loc = locate::Locator::new(text);
            ConfigError { file: path.to_path_buf(), line: loc.line(&p.key), key: Some(p.key), message: p.message }
        })
    }

    /// Writes the config as TOML (resolved intrinsics inline).
    pub fn to_toml_string(&self) -> String {
        toml::to_string(self).expect("config serialises")
    }

    /// A config built in code (the simulated rig, `demo`), checked as a file would be: it
    /// is written as TOML and read back, so it passes every check of [`Config::load`].
    /// `name` stands for the file in errors.
    pub fn checked(self, name: &str) -> Result<Config, ConfigError> {
        Self::from_toml_str(&self.to_toml_string(), Path::new(name))
    }
}

#[cfg(feature = "sim")]
impl Config {
    /// The config of the simulated rig of `params`: its cameras, tags, beam and gauges, and
    /// `[sim]` = the parameters; checked as a file would be.
    pub fn from_sim(rig: &tagdeflect_sim::SimRig) -> Config {
        let params = rig.params();
        let s = rig.sections();
        let config = Config {
            world: s.world,
            sync: s.sync,
            cameras: s.cameras,
            background: s.background,
            specimen: s.specimen,
            utm: None,
            output: OutputConfig::default(),
            report: None,
            measure: MeasureConfig::default(),
            sim: Some(params.clone()),
            gauges: s.gauges,
            clock_check: None,
            verification: None,
            calibration_files: Vec::new(),
        };
        config.checked("<simulated rig>").expect("the simulated rig's config is valid")
    }

    /// The built-in demo rig: three simulated 640x480 cameras at 5 fps and a simulated UTM
    /// served over Modbus TCP on loopback (f32 load at input register 0, f32 stroke at 2).
    pub fn demo() -> Config {
        let params = tagdeflect_sim::live_rig::demo_params();
        let rig = tagdeflect_sim::SimRig::new(&params).expect("demo parameters are valid");
        let mut config = Config::from_sim(&rig);
        config.utm = Some(tagdeflect_sim::live_rig::demo_utm());
        config.checked("<demo>").expect("the demo config is valid")
    }
}
