//! The tests' HTTP API (SPEC "Tests", there called the control API — not to be mistaken for
//! the control output, [`crate::control_output`]): `GET /api/test` open to the page's readers,
//! `POST /api/test/{start,stop,mark,zero,sign,reanalyse}` for whoever holds a token whose role
//! may do it (the one shared token: every action; `[output] users_file`: each user's own token
//! and role, [`tagdeflect_core::users`]; a role that may not: 403 naming the role needed), and
//! `GET /api/audit?test=ID` (the audit trail names users: any user's token). Each action done is
//! appended to the tests folder's audit log with the user and role (`crate::lab_test::audit`).
//!
//! A POST is refused unless all of these hold, in this order: the body is at most
//! [`MAX_BODY`] bytes (413); it does not come from another site — an `Origin` header must name
//! this server's own `Host`, and `Sec-Fetch-Site`, when sent, must not be `cross-site` (403);
//! a body, when there is one, is `application/json` (415: a form of another site cannot send
//! that without a preflight, which this server never grants); `Authorization: Bearer <token>`
//! is a known token (the shared token compared in constant time; a user's token hashed once
//! and compared with every user's hash, without stopping at a match). The right token is never refused, whatever others
//! sent before it: a client behind the lab's reverse proxy (one address for everyone) cannot be
//! locked out by someone else's wrong tokens. A wrong one is answered 401 (logged with the
//! peer's address) until its address sent [`MAX_FAILURES`] wrong tokens within
//! [`FAILURE_WINDOW`], or all addresses together [`MAX_FAILURES_ALL`] (rotating addresses): then
//! 429 with `Retry-After`, and one log line per window instead of one per guess. No GET changes
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

use tagdeflect_core::users::{Actor, Credentials};

use super::LiveView;
use crate::lab_test::{CrackRequest, LabTests, Stopped, TestError};

/// Largest POST body taken, bytes.
pub const MAX_BODY: usize = 16 * 1024;
/// Wrong tokens from one address within [`FAILURE_WINDOW`] before it is refused outright.
pub const MAX_FAILURES: u32 = 5;
/// The window of [`MAX_FAILURES`].
pub const FAILURE_WINDOW: Duration = Duration::from_secs(60);

/// Wrong tokens from all addresses together within [`FAILURE_WINDOW`] before every wrong one is
/// answered 429.
pub const MAX_FAILURES_ALL: u32 = 20;
/// Addresses whose wrong tokens are counted at most (the oldest window is dropped first).
const MAX_TRACKED_PEERS: usize = 4096;

/// Wrong tokens per address and from all together, each counted in a window from its first.
#[derive(Default)]
struct Failures {
    per_peer: HashMap<IpAddr, (u32, Instant)>,
    all: (u32, Option<Instant>),
}

/// The tests behind the API, whose tokens it takes, and the wrong tokens per peer and in all.
pub(crate) struct TestApi {
    tests: Arc<LabTests>,
    auth: Credentials,
    failures: Mutex<Failures>,
}

impl TestApi {
    pub(crate) fn new(tests: Arc<LabTests>, auth: Credentials) -> Self {
        TestApi { tests, auth, failures: Mutex::new(Failures::default()) }
    }

    /// The folder the tests are kept in.
    pub(crate) fn tests_dir(&self) -> &std::path::Path {
        self.tests.dir()
    }
}

/// The POSTs of the control API (a role is checked for these; another name is answered 400).
const COMMANDS: [&str; 9] = ["start", "stop", "mark", "zero", "crack", "method", "specimens", "sign", "reanalyse"];

/// `GET /api/audit?test=ID`: the audit log's chain state and entries (of one test, or all).
/// The trail names users: any user's token is needed (the wrong-token limits apply).
pub(crate) async fn audit(
    State(view): State<Arc<LiveView>>,
    ConnectInfo(peer): ConnectInfo<SocketAddr>,
    headers: HeaderMap,
    axum::extract::Query(q): axum::extract::Query<HashMap<String, String>>,
) -> Response {
    let Some(api) = view.test_api.get() else {
        return answer(StatusCode::NOT_FOUND, "no tests here: configure [output] tests (or run with --tests DIR)");
    };
    if let Err(refused) = check_token(api, &headers, peer, "GET") {
        return refused;
    }
    let tests = api.tests.clone();
    match tokio::task::spawn_blocking(move || tests.audit_entries(q.get("test").map(String::as_str))).await {
        Ok(Ok(v)) => Json(v).into_response(),
        Ok(Err(e)) => answer(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()),
        Err(e) => answer(StatusCode::INTERNAL_SERVER_ERROR, format!("reading the audit log failed: {e}")),
    }
}

/// `GET /api/user`: who holds the token given (`{"user", "role"}`): the page names the
/// reviewer who signs. Any user's token (the wrong-token limits apply).
pub(crate) async fn user(State(view): State<Arc<LiveView>>, ConnectInfo(peer): ConnectInfo<SocketAddr>, headers: HeaderMap) -> Response {
    let Some(api) = view.test_api.get() else {
        return answer(StatusCode::NOT_FOUND, "no tests here: configure [output] tests (or run with --tests DIR)");
    };
    match check_token(api, &headers, peer, "GET") {
        Ok(actor) => Json(serde_json::json!({"user": actor.user, "role": actor.role})).into_response(),
        Err(refused) => refused,
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
    let actor = match check_token(api, &headers, peer, "POST") {
        Ok(actor) => actor,
        Err(refused) => return refused,
    };
    if let (true, Err(why)) = (COMMANDS.contains(&cmd.as_str()), actor.role.may(&cmd)) {
        tracing::warn!(%peer, user = %actor.user, "control API: {why}");
        return answer(StatusCode::FORBIDDEN, why);
    }
    let tests = api.tests.clone();
    let run = move || -> Result<serde_json::Value, TestError> {
        let parse = |what: &str| -> Result<serde_json::Value, TestError> {
            if body.is_empty() {
                return Ok(serde_json::Value::Object(Default::default()));
            }
            serde_json::from_slice(&body).map_err(|e| TestError::Bad(format!("{what}: the body is not JSON: {e}")))
        };
        let by = || Some(actor.user.clone());
        let logged = |v: serde_json::Value, action: &str, detail: serde_json::Value| {
            tests.audit(&actor, action, v.get("id").and_then(|i| i.as_str()), detail).map(|_| v)
        };
        match cmd.as_str() {
            "start" => {
                let body = parse("start")?;
                let detail = body.clone();
                logged(tests.start_request(body, by())?, "start", detail)
            }
            "stop" => {
                let s = stop(&tests, parse("stop")?, by())?;
                tests.audit_stop(&actor, &s)?;
                Ok(serde_json::json!({"id": s.id, "folder": s.folder, "report_error": s.report_error}))
            }
            "crack" => {
                let body = parse("crack")?;
                let detail = body.clone();
                let c = serde_json::from_value(body).map_err(|e| TestError::Bad(format!("crack: {e}")))?;
                logged(tests.crack(c)?, "crack", detail)
            }
            "sign" | "reanalyse" => {
                let v = parse(&cmd)?;
                let text =
                    |k: &str| v.get(k).and_then(|t| t.as_str()).ok_or_else(|| TestError::Bad(format!("{cmd}: \"{k}\" (text) is needed")));
                match cmd.as_str() {
                    "sign" => tests.sign(&actor, text("test")?, text("meaning")?),
                    _ => tests.reanalyse(&actor, text("test")?, text("reason")?),
                }
            }
            "mark" => {
                let v = parse("mark")?;
                let note = match v.get("note") {
                    None | Some(serde_json::Value::Null) => None,
                    Some(serde_json::Value::String(s)) => Some(s.clone()),
                    Some(other) => return Err(TestError::Bad(format!("mark: \"note\" must be text, not {other}"))),
                };
                let detail = serde_json::json!({ "note": note });
                logged(tests.mark_by(note, by())?, "mark", detail)
            }
            "zero" => logged(tests.zero_by(by())?, "zero", serde_json::json!({})),
            other => {
                Err(TestError::Bad(format!("no command \"{}\": start, stop, mark, zero, crack, sign or reanalyse", other.escape_debug())))
            }
        }
    };
    // `stop` waits for the sinks and writes the folder: never on the server's threads.
    respond(tokio::task::spawn_blocking(run).await)
}

/// The answer to a command run on a blocking thread.
fn respond(done: Result<Result<serde_json::Value, TestError>, tokio::task::JoinError>) -> Response {
    match done {
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

/// `POST /api/test/stop`: the body may hold the operator's crack entry (`{"crack": {...}}`,
/// entered before the stop); the answer says when the report could not be made.
fn stop(tests: &LabTests, body: serde_json::Value, user: Option<String>) -> Result<Stopped, TestError> {
    let serde_json::Value::Object(mut fields) = body else { return Err(TestError::Bad("stop: the body is a JSON object".into())) };
    let crack = fields.remove("crack");
    if let Some(k) = fields.keys().next() {
        return Err(TestError::Bad(format!("stop: unknown field `{k}`, expected `crack`")));
    }
    if let Some(c) = crack.filter(|c| !c.is_null()) {
        let c: CrackRequest = serde_json::from_value(c).map_err(|e| TestError::Bad(format!("stop: crack: {e}")))?;
        tests.crack(c)?;
    }
    tests.stop_by(user)
}

/// `GET /api/methods`: the test methods (shipped and the lab's) and the config's beam.
pub(crate) async fn methods(State(view): State<Arc<LiveView>>) -> Response {
    // Without tests: nothing to choose, said as `GET /api/test` says it (the page asks anyway).
    let Some(api) = view.test_api.get() else {
        return Json(serde_json::json!({"state": "off", "methods": [], "beam_mm": {}})).into_response();
    };
    let tests = api.tests.clone();
    respond(tokio::task::spawn_blocking(move || Ok(tests.methods())).await)
}

/// Largest specimen table taken, bytes (`POST /api/specimens`).
pub const MAX_SPECIMENS_BODY: usize = 256 * 1024;

/// `GET /api/specimens`: the table entered beforehand, each row tested or not, and the next.
pub(crate) async fn specimens(State(view): State<Arc<LiveView>>) -> Response {
    let Some(api) = view.test_api.get() else {
        return Json(serde_json::json!({"state": "off", "specimens": [], "next": null})).into_response();
    };
    let tests = api.tests.clone();
    respond(tokio::task::spawn_blocking(move || tests.specimens()).await)
}

/// `POST /api/specimens`: imports a table, `text/csv` or `application/json`, token-guarded like
/// the test commands, at most [`MAX_SPECIMENS_BODY`] bytes; every row checked, the first bad
/// one named by row and column (400).
pub(crate) async fn import_specimens(
    State(view): State<Arc<LiveView>>,
    ConnectInfo(peer): ConnectInfo<SocketAddr>,
    headers: HeaderMap,
    body: Bytes,
) -> Response {
    let Some(api) = view.test_api.get() else {
        return answer(StatusCode::NOT_FOUND, "no tests here: configure [output] tests (or run with --tests DIR)");
    };
    if body.len() > MAX_SPECIMENS_BODY {
        return answer(StatusCode::PAYLOAD_TOO_LARGE, format!("a table of at most {MAX_SPECIMENS_BODY} bytes"));
    }
    if let Some(why) = cross_origin(&headers) {
        tracing::warn!(%peer, "control API: a cross-origin request refused ({why})");
        return answer(StatusCode::FORBIDDEN, format!("cross-origin request refused: {why}"));
    }
    let kind = headers.get(header::CONTENT_TYPE).and_then(|v| v.to_str().ok()).unwrap_or("").trim_start().to_ascii_lowercase();
    let csv = kind.starts_with("text/csv");
    if !csv && !kind.starts_with("application/json") {
        return answer(StatusCode::UNSUPPORTED_MEDIA_TYPE, "the table must be text/csv or application/json");
    }
    let actor = match check_token(api, &headers, peer, "POST") {
        Ok(actor) => actor,
        Err(refused) => return refused,
    };
    if let Err(why) = actor.role.may("specimens") {
        tracing::warn!(%peer, user = %actor.user, "control API: {why}");
        return answer(StatusCode::FORBIDDEN, why);
    }
    let tests = api.tests.clone();
    respond(
        tokio::task::spawn_blocking(move || {
            let rows = crate::lab_test::parse_specimens(&body, csv)?;
            let ids: Vec<String> = rows.iter().map(|r| r.id.clone()).collect();
            let v = tests.import_specimens(rows)?;
            tests.audit(&actor, "specimens", None, serde_json::json!({ "ids": ids }))?;
            Ok(v)
        })
        .await,
    )
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

/// The token check with its rate limit: who holds the token, or the answer when refused.
fn check_token(api: &TestApi, headers: &HeaderMap, peer: SocketAddr, method: &str) -> Result<Actor, Response> {
    let given = headers.get(header::AUTHORIZATION).and_then(|v| v.to_str().ok()).and_then(|v| v.strip_prefix("Bearer ")).map(str::trim);
    if let Some(actor) = given.and_then(|g| api.auth.find(g)) {
        return Ok(actor);
    }
    Err(refuse(api, given.is_some(), peer, method))
}

/// Counts a wrong (or missing) token of `peer` and answers it: 401, or 429 past the limits.
fn refuse(api: &TestApi, given: bool, peer: SocketAddr, method: &str) -> Response {
    let mut f = api.failures.lock().unwrap_or_else(|p| p.into_inner());
    let now = Instant::now();
    f.per_peer.retain(|_, (_, since)| now.duration_since(*since) < FAILURE_WINDOW);
    if f.all.1.is_some_and(|since| now.duration_since(since) >= FAILURE_WINDOW) {
        f.all = (0, None);
    }
    if f.per_peer.len() >= MAX_TRACKED_PEERS && !f.per_peer.contains_key(&peer.ip()) {
        let oldest = f.per_peer.iter().min_by_key(|(_, (_, t))| *t).map(|(ip, _)| *ip);
        oldest.map(|ip| f.per_peer.remove(&ip));
    }
    let mine = f.per_peer.entry(peer.ip()).or_insert((0, now));
    mine.0 += 1;
    let n_peer = mine.0;
    let all = f.all.0 + 1;
    f.all = (all, Some(f.all.1.unwrap_or(now)));
    let what = if given { "a wrong" } else { "no" };
    if n_peer > MAX_FAILURES || all > MAX_FAILURES_ALL {
        // Logged at the first refusal of a window (per address, and for all), not per guess.
        if n_peer == MAX_FAILURES + 1 || all == MAX_FAILURES_ALL + 1 {
            tracing::warn!(%peer, failures = n_peer, failures_all = all, "control API: too many wrong tokens: answered 429 for a minute (the right token still passes)");
        }
        let mut r = answer(StatusCode::TOO_MANY_REQUESTS, "too many wrong tokens: wait a minute (the right token is always taken)");
        r.headers_mut().insert(header::RETRY_AFTER, header::HeaderValue::from_static("60"));
        return r;
    }
    tracing::warn!(%peer, failures = n_peer, "control API: a {method} with {what} token refused");
    answer(
        StatusCode::UNAUTHORIZED,
        "a POST needs Authorization: Bearer <token> (the daemon printed it at start, or see http_token_file; with users_file: your own token)",
    )
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
    }

    #[test]
    fn the_right_token_is_never_refused_and_wrong_ones_are_limited_per_address_and_in_all() {
        let dir = tempfile::tempdir().unwrap();
        let tests = LabTests::new(dir.path(), String::new(), Vec::new(), None).unwrap();
        let api = TestApi::new(tests, Credentials::Shared("right".into()));
        let with = |token: &str| {
            let mut h = HeaderMap::new();
            h.insert(header::AUTHORIZATION, format!("Bearer {token}").parse().unwrap());
            h
        };
        let code = |token: &str, ip: [u8; 4]| {
            check_token(&api, &with(token), SocketAddr::from((ip, 40000)), "POST").map_or_else(|r| r.status(), |_| StatusCode::OK)
        };
        // One address (a reverse proxy): 5 wrong tokens answered 401, then 429; the right one passes.
        let proxy = [10, 0, 0, 1];
        for _ in 0..MAX_FAILURES {
            assert_eq!(code("wrong", proxy), StatusCode::UNAUTHORIZED);
        }
        assert_eq!(code("wrong", proxy), StatusCode::TOO_MANY_REQUESTS);
        assert_eq!(code("right", proxy), StatusCode::OK, "the operator's stop passes the lockout");
        // Rotating addresses: one wrong token each; past the budget of all, 429 for every wrong one.
        let mut unauthorized = 0;
        for k in 0..100u8 {
            if code("guess", [127, 0, 1, k]) == StatusCode::UNAUTHORIZED {
                unauthorized += 1;
            }
        }
        // The proxy's 6 wrong tokens count in all too: 20 in all within the window.
        assert_eq!(unauthorized, MAX_FAILURES_ALL - MAX_FAILURES - 1, "at most {MAX_FAILURES_ALL} wrong tokens get a 401 within a window");
        assert_eq!(code("right", [127, 0, 2, 1]), StatusCode::OK);
        assert_eq!(code("right", proxy), StatusCode::OK);
    }
}
