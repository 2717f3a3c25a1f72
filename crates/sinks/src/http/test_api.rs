//! The tests' HTTP API (SPEC "Tests", there called the control API — not to be mistaken for
//! the control output, [`crate::control_output`]): `GET /api/test` open to the page's readers,
//! `POST /api/test/{start,stop,mark,zero}` for whoever holds the token.
//!
//! A POST is refused unless all of these hold, in this order: the body is at most
//! [`MAX_BODY`] bytes (413); it does not come from another site — an `Origin` header must name
//! this server's own `Host`, and `Sec-Fetch-Site`, when sent, must not be `cross-site` (403);
//! a body, when there is one, is `application/json` (415: a form of another site cannot send
//! that without a preflight, which this server never grants); the peer has not failed the
//! token [`MAX_FAILURES`] times in the last minute (429); `Authorization: Bearer <token>`
//! matches (401, compared in constant time, logged with the peer's address). No GET changes
//! anything.

use std::collections::HashMap;
use std::net::{IpAddr, SocketAddr};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use axum::body::Bytes;
use axum::extract::{ConnectInfo, State};
use axum::http::{header, HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::Json;

use super::LiveView;
use crate::lab_test::{LabTests, TestError, TestMeta};

/// Largest POST body taken, bytes.
pub const MAX_BODY: usize = 16 * 1024;
/// Wrong tokens from one address within [`FAILURE_WINDOW`] before it is refused outright.
pub const MAX_FAILURES: u32 = 5;
/// The window of [`MAX_FAILURES`].
pub const FAILURE_WINDOW: Duration = Duration::from_secs(60);

/// The tests behind the API, the token, and the wrong tokens per peer.
pub(crate) struct TestApi {
    tests: Arc<LabTests>,
    token: String,
    failures: Mutex<HashMap<IpAddr, (u32, Instant)>>,
}

impl TestApi {
    pub(crate) fn new(tests: Arc<LabTests>, token: String) -> Self {
        TestApi { tests, token, failures: Mutex::new(HashMap::new()) }
    }
}

fn answer(code: StatusCode, message: impl Into<String>) -> Response {
    (code, Json(serde_json::json!({"error": message.into()}))).into_response()
}

/// `GET /api/test`.
pub(crate) async fn status(State(view): State<Arc<LiveView>>) -> Response {
    match view.test_api.get() {
        Some(c) => Json(c.tests.status()).into_response(),
        None => Json(serde_json::json!({"state": "off", "why": "no [output] tests (or --tests DIR) configured"})).into_response(),
    }
}

/// `GET /api/tests`: the day's stopped tests' curves (the page draws them in grey).
pub(crate) async fn earlier(State(view): State<Arc<LiveView>>) -> Response {
    let tests = view.test_api.get().map(|c| c.tests.earlier()).unwrap_or_default();
    Json(serde_json::json!({ "tests": tests })).into_response()
}

/// `POST /api/test/{command}`.
pub(crate) async fn command(
    State(view): State<Arc<LiveView>>,
    ConnectInfo(peer): ConnectInfo<SocketAddr>,
    axum::extract::Path(cmd): axum::extract::Path<String>,
    headers: HeaderMap,
    body: Bytes,
) -> Response {
    let Some(api) = view.test_api.get() else {
        return answer(StatusCode::NOT_FOUND, "no tests here: configure [output] tests (or run with --tests DIR)");
    };
    if body.len() > MAX_BODY {
        return answer(StatusCode::PAYLOAD_TOO_LARGE, format!("a body of at most {MAX_BODY} bytes"));
    }
    if let Some(why) = cross_origin(&headers) {
        tracing::warn!(%peer, "control API: a cross-origin request refused ({why})");
        return answer(StatusCode::FORBIDDEN, format!("cross-origin request refused: {why}"));
    }
    let json =
        headers.get(header::CONTENT_TYPE).and_then(|v| v.to_str().ok()).is_some_and(|v| v.trim_start().starts_with("application/json"));
    if !body.is_empty() && !json {
        return answer(StatusCode::UNSUPPORTED_MEDIA_TYPE, "the body must be application/json");
    }
    if let Some(refused) = check_token(api, &headers, peer) {
        return refused;
    }
    let tests = api.tests.clone();
    let run = move || -> Result<serde_json::Value, TestError> {
        let parse = |what: &str| -> Result<serde_json::Value, TestError> {
            if body.is_empty() {
                return Ok(serde_json::Value::Object(Default::default()));
            }
            serde_json::from_slice(&body).map_err(|e| TestError::Bad(format!("{what}: the body is not JSON: {e}")))
        };
        match cmd.as_str() {
            "start" => {
                let meta: TestMeta = serde_json::from_value(parse("start")?).map_err(|e| TestError::Bad(format!("start: {e}")))?;
                tests.start(meta)
            }
            "stop" => tests.stop().map(|s| serde_json::json!({"id": s.id, "folder": s.folder})),
            "mark" => {
                let v = parse("mark")?;
                let note = match v.get("note") {
                    None | Some(serde_json::Value::Null) => None,
                    Some(serde_json::Value::String(s)) => Some(s.clone()),
                    Some(other) => return Err(TestError::Bad(format!("mark: \"note\" must be text, not {other}"))),
                };
                tests.mark(note)
            }
            "zero" => tests.zero(),
            other => Err(TestError::Bad(format!("no command \"{}\": start, stop, mark or zero", other.escape_debug()))),
        }
    };
    // `stop` waits for the sinks and writes the folder: never on the server's threads.
    match tokio::task::spawn_blocking(run).await {
        Ok(Ok(v)) => Json(v).into_response(),
        Ok(Err(TestError::Conflict(m))) => answer(StatusCode::CONFLICT, m),
        Ok(Err(TestError::Bad(m))) => answer(StatusCode::BAD_REQUEST, m),
        Ok(Err(TestError::Io(m))) => {
            tracing::error!("control API: {m}");
            answer(StatusCode::INTERNAL_SERVER_ERROR, m)
        }
        Err(e) => answer(StatusCode::INTERNAL_SERVER_ERROR, format!("the command failed: {e}")),
    }
}

/// Why a request comes from another site, if it does.
fn cross_origin(headers: &HeaderMap) -> Option<String> {
    let text = |h: header::HeaderName| headers.get(h).map(|v| v.to_str().unwrap_or("\u{fffd}").to_string());
    if let Some(site) = headers.get("sec-fetch-site").and_then(|v| v.to_str().ok()) {
        if site.eq_ignore_ascii_case("cross-site") {
            return Some("Sec-Fetch-Site: cross-site".into());
        }
    }
    let origin = text(header::ORIGIN)?;
    let host = text(header::HOST).unwrap_or_default();
    let origin_host = origin.split_once("://").map(|(_, h)| h.trim_end_matches('/')).unwrap_or("");
    if origin_host.is_empty() || !origin_host.eq_ignore_ascii_case(&host) {
        return Some(format!("Origin {origin} is not this server ({host})"));
    }
    None
}

/// The token check with its rate limit; `Some(answer)` when refused.
fn check_token(api: &TestApi, headers: &HeaderMap, peer: SocketAddr) -> Option<Response> {
    let mut failures = api.failures.lock().unwrap_or_else(|p| p.into_inner());
    let now = Instant::now();
    failures.retain(|_, (_, since)| now.duration_since(*since) < FAILURE_WINDOW);
    if failures.get(&peer.ip()).is_some_and(|(n, _)| *n >= MAX_FAILURES) {
        return Some(answer(StatusCode::TOO_MANY_REQUESTS, format!("too many wrong tokens from {}: wait a minute", peer.ip())));
    }
    let given = headers.get(header::AUTHORIZATION).and_then(|v| v.to_str().ok()).and_then(|v| v.strip_prefix("Bearer ")).map(str::trim);
    if given.is_some_and(|g| constant_time_eq(g.as_bytes(), api.token.as_bytes())) {
        return None;
    }
    let entry = failures.entry(peer.ip()).or_insert((0, now));
    entry.0 += 1;
    tracing::warn!(%peer, failures = entry.0, "control API: a POST with {} token refused", if given.is_some() { "a wrong" } else { "no" });
    Some(answer(
        StatusCode::UNAUTHORIZED,
        "a POST needs Authorization: Bearer <token> (the daemon printed it at start, or see http_token_file)",
    ))
}

fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    if a.len() != b.len() {
        return false;
    }
    a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cross_origin_requests_are_told_apart() {
        let mut h = HeaderMap::new();
        h.insert(header::HOST, "127.0.0.1:8080".parse().unwrap());
        assert_eq!(cross_origin(&h), None, "no Origin: a command-line client");
        h.insert(header::ORIGIN, "http://127.0.0.1:8080".parse().unwrap());
        assert_eq!(cross_origin(&h), None, "the page itself");
        h.insert(header::ORIGIN, "http://evil.example".parse().unwrap());
        assert!(cross_origin(&h).is_some());
        h.insert(header::ORIGIN, "null".parse().unwrap());
        assert!(cross_origin(&h).is_some());
        let mut h = HeaderMap::new();
        h.insert("sec-fetch-site", "cross-site".parse().unwrap());
        assert!(cross_origin(&h).is_some());
        assert!(constant_time_eq(b"abc", b"abc") && !constant_time_eq(b"abc", b"abd") && !constant_time_eq(b"ab", b"abc"));
    }
}
