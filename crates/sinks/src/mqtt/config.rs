//! `[output.mqtt]`: the publisher's section, its defaults and its checks.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use serde::{Deserialize, Serialize};

use tagdeflect_core::Problem;
use tagdeflect_wire::{check_level_name, check_topic_template, hostname, tls_config_for, BrokerUrl, WireError};

/// `[output.mqtt]`: publish the feed to an MQTT broker.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MqttConfig {
    /// `mqtt://host[:port]` (1883) or `mqtts://host[:port]` (TLS, 8883).
    pub url: String,
    /// Topic prefix; `{rig}` and `{test}` must each be a whole topic level.
    #[serde(default = "default_topic")]
    pub topic: String,
    /// This rig's name (default: the host name).
    #[serde(default = "default_rig")]
    pub rig: String,
    /// The test id; generated per run (`YYYYMMDDTHHMMSSZ-xxxx`, printed) when absent. A
    /// configured id used again (or a run restarted) gives the archive a second run of the
    /// test (its lines numbered from 0 again; `<test>#2` in `feed_lines`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub test: Option<String>,
    /// QoS of the feed lines (0, 1 or 2; 1 = at least once).
    #[serde(default = "default_qos")]
    pub qos: u8,
    /// MQTT client id (default `tagdeflect-<rig>`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub client_id: Option<String>,
    /// User name for the broker.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub username: Option<String>,
    /// Password for the broker (never written into recordings).
    #[serde(default, skip_serializing)]
    pub password: Option<String>,
    /// TLS: PEM file of the CA certificates that sign the broker's certificate (default:
    /// the system bundle `/etc/ssl/certs/ca-certificates.crt`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ca_file: Option<PathBuf>,
    /// TLS client authentication: PEM certificate chain (with `client_key`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub client_cert: Option<PathBuf>,
    /// TLS client authentication: PEM private key (with `client_cert`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub client_key: Option<PathBuf>,
    /// Feed lines kept in memory until the archive has confirmed them; beyond this the
    /// oldest leaves memory (read back from the feed file when it must be sent; without a
    /// feed file lost, and counted, if the broker never took it).
    #[serde(default = "default_buffer")]
    pub buffer_lines: usize,
    /// MQTT keep-alive, seconds.
    #[serde(default = "default_keep_alive")]
    pub keep_alive_s: u64,
    /// Seconds between refreshes of the retained status.
    #[serde(default = "default_status_interval")]
    pub status_interval_s: f64,
}

fn default_topic() -> String {
    "tagdeflect/{rig}/{test}".into()
}
fn default_rig() -> String {
    hostname()
}
fn default_qos() -> u8 {
    1
}
fn default_buffer() -> usize {
    10_000
}
fn default_keep_alive() -> u64 {
    15
}
fn default_status_interval() -> f64 {
    5.0
}

impl MqttConfig {
    /// Checks the section and returns it with its TLS file paths resolved against `base`
    /// (the config's folder). Keys relative to `[output.mqtt]`.
    pub fn resolve(mut self, base: &Path) -> Result<MqttConfig, Problem> {
        let url = BrokerUrl::parse(&self.url).map_err(|m| Problem::new("url", m.to_string()))?;
        self.check_names()?;
        self.check_numbers(&url)?;
        self.resolve_tls_files(base, &url)?;
        if url.tls {
            self.tls_config().map_err(|m| Problem::new("ca_file", m.to_string()))?;
        }
        Ok(self)
    }

    /// The topic template, the rig, the test id and the client id.
    fn check_names(&self) -> Result<(), Problem> {
        check_topic_template(&self.topic).map_err(|m| Problem::new("topic", m.to_string()))?;
        check_level_name("rig", &self.rig).map_err(|m| Problem::new("rig", m.to_string()))?;
        if let Some(t) = &self.test {
            check_level_name("test", t).map_err(|m| Problem::new("test", m.to_string()))?;
        }
        if self.qos > 2 {
            return Err(Problem::new("qos", format!("must be 0, 1 or 2, got {}", self.qos)));
        }
        if let Some(id) = &self.client_id {
            if id.is_empty() || id.len() > 256 {
                return Err(Problem::new("client_id", "must be 1 to 256 characters"));
            }
        }
        Ok(())
    }

    /// The credentials, the buffer, the keep-alive and the status interval.
    fn check_numbers(&self, url: &BrokerUrl) -> Result<(), Problem> {
        if self.password.is_some() && self.username.is_none() && url.username.is_none() {
            return Err(Problem::new("password", "a password needs a `username`"));
        }
        if self.buffer_lines == 0 {
            return Err(Problem::new("buffer_lines", "must be at least 1"));
        }
        if self.keep_alive_s < 5 || self.keep_alive_s > 3600 {
            return Err(Problem::new("keep_alive_s", format!("must be 5..3600 s, got {}", self.keep_alive_s)));
        }
        if !(self.status_interval_s.is_finite() && self.status_interval_s >= 0.1) {
            return Err(Problem::new("status_interval_s", "must be at least 0.1 s"));
        }
        Ok(())
    }

    /// The TLS files: only with `mqtts://`, a certificate with its key, paths relative to
    /// `base` made whole and readable.
    fn resolve_tls_files(&mut self, base: &Path, url: &BrokerUrl) -> Result<(), Problem> {
        let tls_keys = self.ca_file.is_some() || self.client_cert.is_some() || self.client_key.is_some();
        if tls_keys && !url.tls {
            return Err(Problem::new("url", "TLS options are set but the URL is not mqtts://"));
        }
        if self.client_cert.is_some() != self.client_key.is_some() {
            return Err(Problem::new("client_cert", "give both `client_cert` and `client_key`, or neither"));
        }
        for (key, p) in [("ca_file", &mut self.ca_file), ("client_cert", &mut self.client_cert), ("client_key", &mut self.client_key)] {
            if let Some(path) = p {
                if path.is_relative() {
                    *path = base.join(&*path);
                }
                if let Err(e) = std::fs::metadata(&*path) {
                    return Err(Problem::new(key, format!("cannot read {}: {e}", path.display())));
                }
            }
        }
        Ok(())
    }

    /// The rustls client configuration of this section's `mqtts://` connection.
    pub(crate) fn tls_config(&self) -> Result<Arc<rustls::ClientConfig>, WireError> {
        tls_config_for(self.ca_file.as_deref(), self.client_cert.as_deref(), self.client_key.as_deref())
    }
}
