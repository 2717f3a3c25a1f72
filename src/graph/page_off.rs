//! The live page's hooks in a build without the `http` feature: there is no page, no value of
//! [`HttpOptions`] exists, and every hook does nothing (`page.rs` stands here with the feature).

use std::path::Path;
use std::sync::Arc;

use anyhow::Result;
use tagdeflect_io::sources::SourceEvent;
use tagdeflect_io::utm::UtmEvent;
use tagdeflect_sinks::recorder::RecorderStatus;
use tagdeflect_sinks::LineSink;

use crate::config::Config;

/// Where to serve the live page: in this build there is none, and no value of this type exists.
#[derive(Debug, Clone, Copy)]
pub enum HttpOptions {}

/// `--http ADDR`: refused, there is no page in this build.
pub fn parse_http_addr(s: &str) -> Result<std::net::SocketAddr, String> {
    Err(format!("{s}: this build has no live page (it needs the `http` feature)"))
}

/// No page to serve: `None`.
pub fn http_options(_addr: Option<std::net::SocketAddr>, _required: bool) -> Option<HttpOptions> {
    None
}

/// No default page address in this build.
pub fn default_addr() -> Option<std::net::SocketAddr> {
    None
}

/// No page errors in this build.
pub fn is_bad_input(_e: &(dyn std::error::Error + 'static)) -> bool {
    false
}

/// The live page of a run: none in this build.
#[derive(Default)]
pub struct Page;

impl Page {
    /// No page (`[output] http` is refused when the config is checked).
    pub async fn start(_config: &Config, _opts: Option<HttpOptions>, _mode: &'static str) -> Result<Page> {
        Ok(Page)
    }

    /// Whether a page is served: never.
    pub fn is_served(&self) -> bool {
        false
    }

    /// Hands a source event back.
    pub fn observe(&self, ev: Option<SourceEvent>) -> Option<SourceEvent> {
        ev
    }

    /// No page to serve the tests' control API on.
    pub fn set_control(&self, _tests: Arc<tagdeflect_sinks::lab_test::LabTests>, _auth: tagdeflect_core::users::Credentials) -> bool {
        false
    }

    /// A handle for other tasks.
    pub fn handle(&self) -> PageHandle {
        PageHandle
    }

    /// Nothing shows the MQTT publisher's delivery.
    #[cfg(feature = "mqtt")]
    pub fn on_mqtt(&self, _stats: Arc<tagdeflect_sinks::mqtt::MqttStats>) {}

    /// Nothing shows the recording.
    pub fn on_recording(&self, _dir: &Path, _status: Arc<RecorderStatus>) {}

    /// Nothing to say the input is consumed.
    pub fn on_finished(&self) {}

    /// No sink.
    pub fn sink(&self) -> Result<Option<Box<dyn LineSink>>> {
        Ok(None)
    }
}

/// The page as another task sees it: none.
#[derive(Clone)]
pub struct PageHandle;

impl PageHandle {
    /// Nothing shows a UTM event.
    pub fn on_utm(&self, _ev: &UtmEvent) {}
}
