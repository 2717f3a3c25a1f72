//! The live page in the graph (the `http` feature; without it `page_off.rs` stands here with
//! the same hooks, doing nothing): built from `[output] http` or the command line, shown every
//! source and UTM event, fed every finished line as a sink.

use std::path::Path;
use std::sync::Arc;

use anyhow::Result;
use tagdeflect_io::sources::SourceEvent;
use tagdeflect_io::utm::UtmEvent;
use tagdeflect_sinks::http;
use tagdeflect_sinks::recorder::RecorderStatus;
use tagdeflect_sinks::LineSink;

use crate::config::Config;

pub use tagdeflect_sinks::http::HttpOptions;

/// `--http ADDR` (a listen address, `tagdeflect_core::listen`; port 0: any free port).
pub fn parse_http_addr(s: &str) -> Result<std::net::SocketAddr, String> {
    tagdeflect_core::listen::parse_listen_addr(s, http::DEFAULT_PORT).map_err(|e| e.to_string())
}

/// `--http ADDR` as the graph takes it; `required`: a taken address is an error, not a warning.
pub fn http_options(addr: Option<std::net::SocketAddr>, required: bool) -> Option<HttpOptions> {
    addr.map(|addr| HttpOptions { addr, required })
}

/// Where `demo` serves its page when nothing else is said ([`http::DEFAULT_ADDR`], loopback).
pub fn default_addr() -> Option<std::net::SocketAddr> {
    Some(http::DEFAULT_ADDR.parse().expect("the default address parses"))
}

/// Whether `e` says the page's input is at fault (its address cannot be bound: exit 2).
pub fn is_bad_input(e: &(dyn std::error::Error + 'static)) -> bool {
    matches!(e.downcast_ref::<http::HttpError>(), Some(http::HttpError::Bind { .. }))
}

/// The live page of a run, if it has one.
#[derive(Default)]
pub struct Page {
    view: Option<Arc<http::LiveView>>,
    server: Option<http::HttpServer>,
}

impl Page {
    /// Serves the page when `opts` (the command line) or `[output] http` asks for it; a
    /// taken address is an error when the page is required.
    pub async fn start(config: &Config, opts: Option<HttpOptions>, mode: &'static str) -> Result<Page> {
        let Some(o) = http::wanted(config.output.http.as_deref(), opts) else { return Ok(Page::default()) };
        let view = http::LiveView::new(&config.rig_info(), mode);
        let server = http::serve(o, http::AllowedHosts::new(&config.output.http_hosts), view.clone()).await?;
        Ok(Page { view: Some(view), server })
    }

    /// Whether a page is served.
    pub fn is_served(&self) -> bool {
        self.server.is_some()
    }

    /// Shows a source event (frames, drops, lost cameras) and hands it back.
    pub fn observe(&self, ev: Option<SourceEvent>) -> Option<SourceEvent> {
        http::observe(self.view.as_deref(), ev)
    }

    /// Serves the tests' control API; false when no page is served (nowhere to serve it).
    pub fn set_control(&self, tests: Arc<tagdeflect_sinks::lab_test::LabTests>, auth: tagdeflect_core::users::Credentials) -> bool {
        if let (Some(v), true) = (&self.view, self.is_served()) {
            v.set_test_api(tests, auth);
            return true;
        }
        false
    }

    /// A handle for other tasks (the UTM forwarder).
    pub fn handle(&self) -> PageHandle {
        PageHandle { view: self.view.clone() }
    }

    /// Shows the MQTT publisher's delivery to the archive (its lag) on the status and `/metrics`.
    #[cfg(feature = "mqtt")]
    pub fn on_mqtt(&self, stats: Arc<tagdeflect_sinks::mqtt::MqttStats>) {
        if let Some(v) = &self.view {
            v.set_mqtt(stats);
        }
    }

    /// Shows the recording's folder and state.
    pub fn on_recording(&self, dir: &Path, status: Arc<RecorderStatus>) {
        if let Some(v) = &self.view {
            v.on_recording(dir, status);
        }
    }

    /// The run's input is consumed (a replay): the page says so.
    pub fn on_finished(&self) {
        if let Some(v) = &self.view {
            v.on_finished();
        }
    }

    /// The page as a sink of finished lines.
    pub fn sink(&self) -> Result<Option<Box<dyn LineSink>>> {
        match &self.view {
            Some(v) => Ok(Some(Box::new(v.tap()?))),
            None => Ok(None),
        }
    }
}

/// The page as another task sees it.
#[derive(Clone)]
pub struct PageHandle {
    view: Option<Arc<http::LiveView>>,
}

impl PageHandle {
    /// Shows a UTM event.
    pub fn on_utm(&self, ev: &UtmEvent) {
        if let Some(v) = &self.view {
            v.on_utm(ev);
        }
    }
}
