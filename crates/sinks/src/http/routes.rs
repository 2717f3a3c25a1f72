//! The endpoints (axum handlers) and the embedded page.

use axum::extract::{Path, State};
use axum::http::{header, StatusCode};
use axum::response::sse::{Event as SseEvent, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::{Json, Router};
use futures_util::stream::{self, Stream, StreamExt};
use std::convert::Infallible;
use std::sync::Arc;
use tokio::sync::broadcast::error::RecvError;

use super::view::{ClientGuard, Event, LiveView};

const INDEX_HTML: &str = include_str!("assets/index.html");
const APP_JS: &str = include_str!("assets/app.js");
const START_FORM_JS: &str = include_str!("assets/start_form.js");
const SPECIMENS_JS: &str = include_str!("assets/specimens.js");
const REVIEW_JS: &str = include_str!("assets/review.js");
const LIVE_CURVE_JS: &str = include_str!("assets/live_curve.js");
const APP_CSS: &str = include_str!("assets/app.css");
const UPLOT_JS: &str = include_str!("assets/vendor/uplot/uPlot.iife.min.js");
const UPLOT_CSS: &str = include_str!("assets/vendor/uplot/uPlot.min.css");
const UPLOT_LICENSE: &str = include_str!("assets/vendor/uplot/LICENSE");

/// Every route of the live page.
pub fn router(view: Arc<LiveView>) -> Router {
    Router::new()
        .route("/", get(|| async { asset("text/html; charset=utf-8", INDEX_HTML) }))
        .route("/assets/app.js", get(|| async { asset("text/javascript; charset=utf-8", APP_JS) }))
        .route("/assets/app.css", get(|| async { asset("text/css; charset=utf-8", APP_CSS) }))
        .route("/assets/uPlot.iife.min.js", get(|| async { asset("text/javascript; charset=utf-8", UPLOT_JS) }))
        .route("/assets/uPlot.min.css", get(|| async { asset("text/css; charset=utf-8", UPLOT_CSS) }))
        .route("/assets/uPlot.LICENSE.txt", get(|| async { asset("text/plain; charset=utf-8", UPLOT_LICENSE) }))
        .route("/events", get(events))
        .route("/api/status", get(status))
        .route("/camera/{file}", get(camera))
        .route("/metrics", get(metrics))
        .route("/api/test", get(super::test_api::status))
        .route("/api/tests", get(super::test_api::earlier))
        .route("/api/test/{command}", axum::routing::post(super::test_api::command))
        .route("/api/audit", get(super::test_api::audit))
        .route("/api/user", get(super::test_api::user))
        .route("/reports/{id}", get(super::report_files::report_index))
        .route("/reports/{id}/{file}", get(super::report_files::report_file))
        .route("/api/methods", get(super::test_api::methods))
        .route("/assets/start_form.js", get(|| async { asset("text/javascript; charset=utf-8", START_FORM_JS) }))
        .route("/assets/live_curve.js", get(|| async { asset("text/javascript; charset=utf-8", LIVE_CURVE_JS) }))
        .route("/assets/specimens.js", get(|| async { asset("text/javascript; charset=utf-8", SPECIMENS_JS) }))
        .route("/assets/review.js", get(|| async { asset("text/javascript; charset=utf-8", REVIEW_JS) }))
        .route(
            "/api/specimens",
            get(super::test_api::specimens)
                .post(super::test_api::import_specimens)
                .layer(axum::extract::DefaultBodyLimit::max(super::test_api::MAX_SPECIMENS_BODY)),
        )
        // Larger bodies are refused before they are read whole (the control API's limit).
        .layer(axum::extract::DefaultBodyLimit::max(super::test_api::MAX_BODY))
        .with_state(view)
}

fn asset(content_type: &'static str, body: &'static str) -> Response {
    ([(header::CONTENT_TYPE, content_type), (header::CACHE_CONTROL, "no-cache")], body).into_response()
}

async fn status(State(view): State<Arc<LiveView>>) -> Json<super::status::Status> {
    Json(super::status::status(&view))
}

async fn metrics(State(view): State<Arc<LiveView>>) -> Response {
    if let Some(d) = view.lock().recording.drops.as_ref() {
        view.metrics.recorder_dropped.set(d.dropped_frames() as i64);
    }
    #[cfg(feature = "mqtt")]
    if let Some(s) = view.mqtt.get() {
        use std::sync::atomic::Ordering::Relaxed;
        let m = &view.metrics;
        let v = |a: &std::sync::atomic::AtomicU64| i64::try_from(a.load(Relaxed)).unwrap_or(i64::MAX);
        m.mqtt_connected.set(v(&s.connected));
        m.archive_lag.set(v(&s.archive_lag));
        m.archive_confirmed.set(v(&s.archive_confirmed));
        m.mqtt_unconfirmed.set(v(&s.unconfirmed));
        m.mqtt_dropped.set(v(&s.dropped));
    }
    ([(header::CONTENT_TYPE, "application/openmetrics-text; version=1.0.0; charset=utf-8")], view.metrics.encode()).into_response()
}

async fn camera(State(view): State<Arc<LiveView>>, Path(file): Path<String>) -> Response {
    let Some(name) = file.strip_suffix(".jpg") else { return (StatusCode::NOT_FOUND, "expected /camera/NAME.jpg").into_response() };
    let Some(i) = view.config.camera_index(name) else {
        return (StatusCode::NOT_FOUND, format!("no camera named \"{name}\"")).into_response();
    };
    match view.snapshot(i) {
        Some(s) => ([(header::CONTENT_TYPE, "image/jpeg"), (header::CACHE_CONTROL, "no-store")], s.jpeg.as_ref().clone()).into_response(),
        None => (StatusCode::SERVICE_UNAVAILABLE, format!("no snapshot of camera \"{name}\" yet")).into_response(),
    }
}

/// `/events`: the backlog of feed lines, then every new line and snapshot notice. A client
/// that falls more than the broadcast's capacity behind skips ahead (counted).
/// Its connection is marked as a stream: the oldest stream is closed when a new connection
/// finds every slot taken (`server::Streams`).
async fn events(State(view): State<Arc<LiveView>>, ext: axum::http::Extensions) -> Sse<impl Stream<Item = Result<SseEvent, Infallible>>> {
    if let Some(conn) = ext.get::<super::server::Conn>() {
        conn.streaming();
    }
    let (backlog, rx) = view.subscribe();
    let guard = ClientGuard::new(view);
    let first = stream::iter(backlog.into_iter().map(|l| Ok(SseEvent::default().data(&*l))));
    let live = stream::unfold((rx, guard), |(mut rx, guard)| async move {
        loop {
            match rx.recv().await {
                Ok(Event::Line(l)) => return Some((Ok(SseEvent::default().data(&*l)), (rx, guard))),
                Ok(Event::Snapshot(s)) => return Some((Ok(SseEvent::default().event("snapshot").data(&*s)), (rx, guard))),
                Err(RecvError::Lagged(n)) => {
                    guard.0.metrics.http_events_lagged.inc_by(n);
                }
                Err(RecvError::Closed) => return None,
            }
        }
    });
    Sse::new(first.chain(live)).keep_alive(KeepAlive::default())
}
