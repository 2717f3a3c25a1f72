//! The live page in the graph: built from `[output] http` or the command line, shown every
//! source and UTM event, fed every finished line as a sink. Without the `http` feature the
//! page is absent and every hook does nothing.

use std::path::Path;
use std::sync::Arc;

use anyhow::Result;
use tagdeflect_io::sources::SourceEvent;
use tagdeflect_io::utm::UtmEvent;
use tagdeflect_sinks::recorder::RecorderStatus;
use tagdeflect_sinks::LineSink;

use crate::config::Config;

#[cfg(feature = "http")]
pub use tagdeflect_sinks::http::HttpOptions;

/// Where to serve the live page (built without the `http` feature: there is none, and no
/// value of this type exists).
#[cfg(not(feature = "http"))]
#[derive(Debug, Clone, Copy)]
pub enum HttpOptions {}

/// The live page of a run, if it has one.
#[derive(Default)]
pub struct Page {
    #[cfg(feature = "http")]
    view: Option<Arc<tagdeflect_sinks::http::LiveView>>,
    #[cfg(feature = "http")]
    _server: Option<tagdeflect_sinks::http::HttpServer>,
}

impl Page {
    /// Serves the page when `opts` (the command line) or `[output] http` asks for it; a
    /// taken address is an error when the page is required.
    #[cfg_attr(not(feature = "http"), allow(unused_variables))]
    pub async fn start(config: &Config, opts: Option<HttpOptions>, mode: &'static str) -> Result<Page> {
        #[cfg(feature = "http")]
        {
            use tagdeflect_sinks::http;
            let Some(o) = http::wanted(config.output.http.as_deref(), opts) else { return Ok(Page::default()) };
            let view = http::LiveView::new(&config.rig_info(), mode);
            let server = http::serve(o, http::AllowedHosts::new(&config.output.http_hosts), view.clone()).await?;
            Ok(Page { view: Some(view), _server: server })
        }
        #[cfg(not(feature = "http"))]
        Ok(Page::default())
    }

    /// Whether a page is served.
    pub fn is_served(&self) -> bool {
        #[cfg(feature = "http")]
        return self._server.is_some();
        #[cfg(not(feature = "http"))]
        false
    }

    /// Shows a source event (frames, drops, lost cameras) and hands it back.
    pub fn observe(&self, ev: Option<SourceEvent>) -> Option<SourceEvent> {
        #[cfg(feature = "http")]
        return tagdeflect_sinks::http::observe(self.view.as_deref(), ev);
        #[cfg(not(feature = "http"))]
        ev
    }

    /// Serves the tests' control API; false when no page is served (nowhere to serve it).
    #[cfg_attr(not(feature = "http"), allow(unused_variables))]
    pub fn set_control(&self, tests: Arc<tagdeflect_sinks::lab_test::LabTests>, token: String) -> bool {
        #[cfg(feature = "http")]
        if let (Some(v), true) = (&self.view, self.is_served()) {
            v.set_control(tests, token);
            return true;
        }
        false
    }

    /// A handle for other tasks (the UTM forwarder).
    pub fn handle(&self) -> PageHandle {
        PageHandle {
            #[cfg(feature = "http")]
            view: self.view.clone(),
        }
    }

    /// Shows the MQTT publisher's delivery to the archive (its lag) on the status and `/metrics`.
    #[cfg(feature = "mqtt")]
    #[cfg_attr(not(feature = "http"), allow(unused_variables))]
    pub fn on_mqtt(&self, stats: Arc<tagdeflect_sinks::mqtt::MqttStats>) {
        #[cfg(feature = "http")]
        if let Some(v) = &self.view {
            v.set_mqtt(stats);
        }
    }

    /// Shows the recording's folder and state.
    #[cfg_attr(not(feature = "http"), allow(unused_variables))]
    pub fn on_recording(&self, dir: &Path, status: Arc<RecorderStatus>) {
        #[cfg(feature = "http")]
        if let Some(v) = &self.view {
            v.on_recording(dir, status);
        }
    }

    /// The run's input is consumed (a replay): the page says so.
    pub fn on_finished(&self) {
        #[cfg(feature = "http")]
        if let Some(v) = &self.view {
            v.on_finished();
        }
    }

    /// The page as a sink of finished lines.
    pub fn sink(&self) -> Result<Option<Box<dyn LineSink>>> {
        #[cfg(feature = "http")]
        if let Some(v) = &self.view {
            return Ok(Some(Box::new(v.tap()?)));
        }
        Ok(None)
    }
}

/// The page as another task sees it.
#[derive(Clone)]
pub struct PageHandle {
    #[cfg(feature = "http")]
    view: Option<Arc<tagdeflect_sinks::http::LiveView>>,
}

impl PageHandle {
    /// Shows a UTM event.
    #[cfg_attr(not(feature = "http"), allow(unused_variables))]
    pub fn on_utm(&self, ev: &UtmEvent) {
        #[cfg(feature = "http")]
        if let Some(v) = &self.view {
            v.on_utm(ev);
        }
    }
}
