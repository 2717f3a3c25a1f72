//! `[output]`: where `run` and `demo` send what they make.

use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

use tagdeflect_core::feed_rotation::FeedRotation;
use tagdeflect_core::frame::FrameFormat;
#[cfg(feature = "http")]
use tagdeflect_core::listen::parse_listen_addr;
use tagdeflect_core::Problem;

/// `[output]`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OutputConfig {
    /// Append the feed to this file; `-` = stdout.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub feed: Option<String>,
    /// (extension) `[output.feed_rotation]`: when the feed file is rotated and what is kept
    /// (by default a new file past 2000 MB and at each new UTC day, nothing deleted; see
    /// `tagdeflect_core::feed_rotation`).
    #[serde(default, skip_serializing_if = "FeedRotation::is_default")]
    pub feed_rotation: FeedRotation,
    /// Save a recording of the run in a new timestamped sub-folder of this folder.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub record: Option<PathBuf>,
    /// (extension) How recorded frames are written: `"png"` (default; half the disk) or
    /// `"pgm"` (raw; no CPU spent encoding — for high frame rates on a small box).
    #[serde(default, skip_serializing_if = "is_default_format")]
    pub record_format: FrameFormat,
    /// (extension) Record each test's frames and UTM samples into its folder (`frames/`, a
    /// recording `replay` reads; see `lab_test::frames`), in `record_format`.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub record_tests: bool,
    /// (extension) The free space kept under the tests folder for the lines, MB (10⁶ bytes):
    /// below it a test's frames stop (said once, `test.json` `frames_stopped`); default
    /// [`RECORD_TESTS_RESERVE_MB`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub record_tests_reserve_mb: Option<f64>,
    /// Serve the live page and endpoints on this address (a listen address,
    /// `tagdeflect_core::listen`; see `sinks::http`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub http: Option<String>,
    /// `[output.control]`: the configured gauge as a control signal on a read-only Modbus
    /// TCP server (see `sinks::control_output`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub control: Option<crate::control_output::ControlConfig>,
    /// `[output.analog]`: the same signal as a voltage on a networked DAQ's analog output,
    /// written over Modbus TCP (see `sinks::analog_output`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub analog: Option<crate::analog_output::AnalogConfig>,
    /// (extension) Host names the live page answers to besides IP addresses, `localhost` and
    /// this machine's own name (a request naming any other host is refused: DNS rebinding).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub http_hosts: Vec<String>,
    /// Keep each test (SPEC "Tests") in its own folder `<tests>/<test id>/`; enables the
    /// control API on the `http` address.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tests: Option<PathBuf>,
    /// The control API's bearer token, read from this file (first line); without it a random
    /// token is made at start, printed once and written to `<tests>/.token` (mode 0600).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub http_token_file: Option<PathBuf>,
    /// (extension, docs/audit.md) The control API's users, each with their own token and role
    /// (`tagdeflect user add`); without it the one shared token of `http_token_file` is taken.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub users_file: Option<PathBuf>,
    /// `[output.auto_test]`: start and stop tests from the load and the standard's end
    /// (see `sinks::lab_test::auto`; off without the table).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub auto_test: Option<crate::lab_test::auto::AutoTestConfig>,
    /// `[output.mqtt]`: publish the feed to an MQTT broker (never written back: a
    /// recording carries no broker address or credentials).
    #[serde(default, skip_serializing)]
    pub mqtt: Option<MqttSection>,
}

/// `[output.mqtt]` as this build takes it: the MQTT publisher's section with the `mqtt`
/// feature; without it the table is kept as written (a config of a full build still loads;
/// `run` then refuses to start, naming the feature).
#[cfg(feature = "mqtt")]
pub type MqttSection = crate::mqtt::MqttConfig;
/// `[output.mqtt]` as this build takes it (built without the `mqtt` feature).
#[cfg(not(feature = "mqtt"))]
pub type MqttSection = serde_json::Value;

/// Default free space kept for the lines under the tests folder when a test's frames are
/// recorded: ~7 h of the main feed at 3 × 30 fps with 9 tags (~6.8 GB a day) and the test's own
/// lines, yet ~22 s of frames at 3 × 1080p, 30 fps (the frames stop well before the lines suffer).
pub const RECORD_TESTS_RESERVE_MB: f64 = 2000.0;

impl OutputConfig {
    /// `record_tests_reserve_mb` (or its default) in bytes.
    pub fn record_tests_reserve_bytes(&self) -> u64 {
        (self.record_tests_reserve_mb.unwrap_or(RECORD_TESTS_RESERVE_MB) * 1e6) as u64
    }

    /// Checks `[output]` but `[output.mqtt]` (`http`: an address the live page can serve) and
    /// returns it with relative `feed`, `record`, `tests` and `http_token_file` paths made
    /// relative to `base`; keys relative to `[output]`.
    pub fn resolve(mut self, base: &Path) -> Result<OutputConfig, Problem> {
        if let Some(h) = &self.http {
            #[cfg(feature = "http")]
            parse_listen_addr(h, crate::http::DEFAULT_PORT).map_err(|e| Problem::new("http", e.to_string()))?;
            #[cfg(not(feature = "http"))]
            return Err(Problem::new("http", format!("\"{h}\": this build has no live page: build with the `http` feature")));
        }
        self.check_http_hosts()?;
        self.feed_rotation.validate().map_err(|p| p.within("feed_rotation"))?;
        if let Some(r) = self.record_tests_reserve_mb.filter(|r| !(r.is_finite() && (0.0..=1e9).contains(r))) {
            return Err(Problem::new("record_tests_reserve_mb", format!("{r} MB: 0 (no reserve) to 1000000000")));
        }
        for p in [&mut self.tests, &mut self.http_token_file, &mut self.users_file].into_iter().flatten() {
            if p.is_relative() {
                *p = base.join(&*p);
            }
        }
        self.check_token_file()?;
        if let Some(u) = &self.users_file {
            tagdeflect_core::users::Users::read(u).map_err(|e| Problem::new("users_file", e.to_string()))?;
        }
        if let Some(a) = &self.auto_test {
            a.validate().map_err(|p| p.within("auto_test"))?;
        }
        if let Some(r) = &self.record {
            if r.is_relative() {
                self.record = Some(base.join(r));
            }
        }
        if let Some(f) = &self.feed {
            if f != "-" && Path::new(f).is_relative() {
                self.feed = Some(base.join(f).to_string_lossy().into_owned());
            }
        }
        Ok(self)
    }

    /// `http_hosts`: host names only.
    fn check_http_hosts(&self) -> Result<(), Problem> {
        for (i, h) in self.http_hosts.iter().enumerate() {
            let ok = !h.is_empty() && h.len() <= 253 && h.chars().all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '.');
            if !ok {
                return Err(Problem::new(format!("http_hosts[{i}]"), format!("\"{h}\" is not a host name (letters, digits, `-` and `.`)")));
            }
        }
        Ok(())
    }

    /// A warning when `http_token_file` may be read or written by every user of the machine
    /// (mode `o+r` or `o+w`, e.g. 0644): the file and its mode. Read by the group (0640, the
    /// lab's group under the unit) is how lab users get the token, and is not warned of.
    pub fn token_file_warning(&self) -> Option<String> {
        use std::os::unix::fs::PermissionsExt;
        let t = self.http_token_file.as_ref()?;
        let mode = std::fs::metadata(t).ok()?.permissions().mode() & 0o7777;
        (mode & 0o006 != 0).then(|| {
            format!(
                "[output] http_token_file {}: mode {mode:04o} lets every user of this machine read (or write) the control token: `chmod 640` (the lab's group) or `chmod 600`",
                t.display()
            )
        })
    }

    /// `http_token_file` (already resolved): readable, a token of 16 characters or more first.
    fn check_token_file(&self) -> Result<(), Problem> {
        let Some(t) = &self.http_token_file else { return Ok(()) };
        match std::fs::read_to_string(t) {
            Ok(text) if text.lines().next().is_some_and(|l| l.trim().len() >= 16) => Ok(()),
            Ok(_) => {
                Err(Problem::new("http_token_file", format!("{}: the first line must hold a token of at least 16 characters", t.display())))
            }
            Err(e) => Err(Problem::new("http_token_file", format!("{}: {e}", t.display()))),
        }
    }

    /// Checks `[output.mqtt]` (the publisher's own checks) and returns `[output]` with its
    /// files resolved against `base`; keys relative to `[output]`.
    #[cfg_attr(not(feature = "mqtt"), allow(unused_mut))]
    pub fn resolve_mqtt(mut self, base: &Path) -> Result<OutputConfig, Problem> {
        #[cfg(feature = "mqtt")]
        if let Some(m) = self.mqtt.take() {
            self.mqtt = Some(m.resolve(base).map_err(|p| p.within("mqtt"))?);
        }
        #[cfg(not(feature = "mqtt"))]
        let _ = base;
        Ok(self)
    }
}

fn is_default_format(f: &FrameFormat) -> bool {
    *f == FrameFormat::default()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_token_file_every_user_may_read_is_warned_of_naming_file_and_mode() {
        use std::os::unix::fs::PermissionsExt;
        let dir = tempfile::tempdir().unwrap();
        let t = dir.path().join("token");
        std::fs::write(&t, "0123456789abcdef0123\n").unwrap();
        let out = OutputConfig { http_token_file: Some(t.clone()), ..OutputConfig::default() };
        for (mode, warned) in [(0o600, false), (0o640, false), (0o644, true), (0o602, true)] {
            std::fs::set_permissions(&t, std::fs::Permissions::from_mode(mode)).unwrap();
            let w = out.token_file_warning();
            assert_eq!(w.is_some(), warned, "{mode:o}: {w:?}");
            if let Some(w) = w {
                assert!(w.contains(&t.display().to_string()) && w.contains(&format!("mode {mode:04o}")), "{w}");
            }
        }
    }
}
