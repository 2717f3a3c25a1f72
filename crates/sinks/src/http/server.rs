//! The server: where the page is served ([`HttpOptions`], [`wanted`]) and
//! the axum server on the pipeline's runtime ([`serve`], [`HttpServer`]).

use std::collections::{BTreeMap, HashMap};
use std::future::Future;
use std::net::{IpAddr, SocketAddr};
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use tokio::sync::{Notify, OwnedSemaphorePermit, Semaphore};

use tagdeflect_core::listen::parse_listen_addr;

use super::{routes, HttpError, LiveView};

/// Where `demo` serves the page unless told otherwise (and `[output] http`'s usual value).
pub const DEFAULT_ADDR: &str = "127.0.0.1:8080";
/// The port of [`DEFAULT_ADDR`] (and of the address examples in messages).
pub const DEFAULT_PORT: u16 = 8080;

/// Where to serve the page.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct HttpOptions {
    /// The address to listen on (port 0: any free port; the bound address is printed).
    pub addr: SocketAddr,
    /// Failing to listen is an error (else a warning and the run goes on without the page:
    /// `demo`'s default address may be taken by another program).
    pub required: bool,
}

/// Where a live run serves the page: `opts` (the command line) first, else `[output] http`
/// (validated when the config was loaded: a taken address is then an error).
pub fn wanted(configured: Option<&str>, opts: Option<HttpOptions>) -> Option<HttpOptions> {
    opts.or_else(|| configured.and_then(|a| parse_listen_addr(a, DEFAULT_PORT).ok()).map(|addr| HttpOptions { addr, required: true }))
}

/// Connections served at once at most; one more is closed at once (counted, logged). The
/// page needs two per viewer (`/events` and the fetches): 64 viewers, and the daemon's own
/// files — recorder, feed, cameras — keep their room under the unit's `LimitNOFILE`.
pub const MAX_CONNECTIONS: usize = 128;
/// `/events` streams one address may hold at most: a quarter of [`MAX_CONNECTIONS`]. A new
/// stream beyond it closes that address's own oldest stream; so one client (a script, a
/// browser with dozens of tabs) cannot close everyone else's streams. Behind a reverse proxy
/// every viewer has the proxy's address: 32 viewers then share it.
pub const MAX_STREAMS_PER_ADDRESS: usize = MAX_CONNECTIONS / 4;

/// Connections that serve `/events` streams, oldest first, with their peer's address. A
/// stream beyond its address's share ([`MAX_STREAMS_PER_ADDRESS`]) closes that address's
/// oldest; when every connection slot is taken, a new connection closes the oldest stream of
/// the address holding the most (its page's `EventSource` reconnects) instead of being
/// refused: a crowd of streams — 128 tabs, or someone opening them on purpose — never shuts
/// out the control API or the page's own fetches, nor another viewer's stream.
#[derive(Default)]
pub(super) struct Streams {
    next: AtomicU64,
    open: Mutex<BTreeMap<u64, (IpAddr, Arc<Notify>)>>,
    evicted: AtomicU64,
}

impl Streams {
    fn open(&self) -> std::sync::MutexGuard<'_, BTreeMap<u64, (IpAddr, Arc<Notify>)>> {
        self.open.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Closes the oldest stream of the address holding the most streams (the oldest such
    /// address's on a tie); false when no stream is open.
    fn evict_oldest(&self) -> bool {
        let mut open = self.open();
        let mut held: HashMap<IpAddr, (usize, u64)> = HashMap::new();
        for (k, (ip, _)) in open.iter() {
            held.entry(*ip).or_insert((0, *k)).0 += 1;
        }
        // The most streams; among equals, the one whose oldest stream is oldest.
        let Some((_, (_, key))) = held.into_iter().max_by_key(|(_, (n, first))| (*n, std::cmp::Reverse(*first))) else { return false };
        let Some((ip, close)) = open.remove(&key) else { return false };
        drop(open);
        close.notify_one();
        let n = self.evicted.fetch_add(1, Ordering::Relaxed) + 1;
        if n.is_power_of_two() {
            tracing::warn!(evicted = n, %ip, "live page: {MAX_CONNECTIONS} connections open; the oldest /events stream of the address holding the most was closed to make room");
        }
        true
    }

    /// Makes room for one more stream of `ip` within its share: closes its oldest beyond it.
    fn within_share(open: &mut BTreeMap<u64, (IpAddr, Arc<Notify>)>, ip: IpAddr, evicted: &AtomicU64) {
        let mine: Vec<u64> = open.iter().filter(|(_, (i, _))| *i == ip).map(|(k, _)| *k).collect();
        for k in mine.iter().take((mine.len() + 1).saturating_sub(MAX_STREAMS_PER_ADDRESS)) {
            if let Some((_, close)) = open.remove(k) {
                close.notify_one();
                let n = evicted.fetch_add(1, Ordering::Relaxed) + 1;
                if n.is_power_of_two() {
                    tracing::warn!(evicted = n, %ip, "live page: {ip} holds {MAX_STREAMS_PER_ADDRESS} /events streams, its share; its oldest was closed for its new one");
                }
            }
        }
    }
}

/// A connection as its requests see it (in their extensions): `/events` marks it as a
/// stream, which a new connection may close when all slots are taken.
#[derive(Clone)]
pub(super) struct Conn {
    streams: Arc<Streams>,
    close: Arc<Notify>,
    key: Arc<Mutex<Option<u64>>>,
    peer: IpAddr,
}

impl Conn {
    /// This connection now serves a stream of events (its address's oldest closed when it
    /// already holds its share).
    pub fn streaming(&self) {
        let k = self.streams.next.fetch_add(1, Ordering::Relaxed);
        let mut open = self.streams.open();
        Streams::within_share(&mut open, self.peer, &self.streams.evicted);
        open.insert(k, (self.peer, self.close.clone()));
        drop(open);
        *self.key.lock().unwrap_or_else(|e| e.into_inner()) = Some(k);
    }

    /// The connection ended: no longer a stream.
    fn ended(&self) {
        if let Some(k) = self.key.lock().unwrap_or_else(|e| e.into_inner()).take() {
            self.streams.open().remove(&k);
        }
    }
}

/// A client has this long to send a request's headers (a connection that sends nothing, or
/// half a header, is closed: `slowloris`).
pub const HEADER_TIMEOUT: Duration = Duration::from_secs(10);
/// A kept-alive connection with no request in flight is closed after this long (a request
/// being answered — a stop making a long test's report and PDF takes minutes — keeps it open).
pub const IDLE_TIMEOUT: Duration = Duration::from_secs(30);

/// The response headers every answer carries: the page runs only its own script and styles,
/// loads nothing from elsewhere, and cannot be framed.
const CSP: &str = "default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self' data: blob:; connect-src 'self'; \
                   object-src 'none'; base-uri 'none'; frame-ancestors 'none'; form-action 'self'";

/// The running server; stops (closing every connection) when dropped.
pub struct HttpServer {
    /// The bound address.
    pub addr: SocketAddr,
    handle: tokio::task::JoinHandle<()>,
}

impl Drop for HttpServer {
    fn drop(&mut self) {
        self.handle.abort();
    }
}

/// The names a request's `Host` may carry besides IP literals and `localhost`: this machine's
/// host name (and `NAME.local`), and `extra` (`[output] http_hosts`). Any other name is a
/// page of another site whose name was pointed at this machine (DNS rebinding): refused.
#[derive(Debug, Clone)]
pub struct AllowedHosts(Vec<String>);

impl AllowedHosts {
    /// This machine's names and `extra`.
    pub fn new(extra: &[String]) -> Self {
        let mut names: Vec<String> = extra.iter().map(|h| h.trim().to_ascii_lowercase()).collect();
        if let Ok(h) = std::fs::read_to_string("/proc/sys/kernel/hostname") {
            let h = h.trim().to_ascii_lowercase();
            if !h.is_empty() {
                names.push(format!("{h}.local"));
                names.push(h);
            }
        }
        AllowedHosts(names)
    }

    /// Whether `host` (a `Host` header: name or IP, with or without the port) names this server.
    pub fn allows(&self, host: &str) -> bool {
        let host = host.trim();
        let name = if let Some(rest) = host.strip_prefix('[') {
            // [IPv6]:PORT
            return rest.split_once(']').is_some_and(|(ip, _)| ip.parse::<std::net::Ipv6Addr>().is_ok());
        } else {
            match host.rsplit_once(':') {
                Some((n, port)) if port.chars().all(|c| c.is_ascii_digit()) => n,
                _ => host,
            }
        };
        name.parse::<std::net::IpAddr>().is_ok()
            || name.eq_ignore_ascii_case("localhost")
            || self.0.iter().any(|a| a.eq_ignore_ascii_case(name))
    }
}

/// Starts serving `view` on the current tokio runtime. Prints `live page: http://ADDR/` on
/// stderr with the bound address. When the address cannot be listened on: an error if
/// `opts.required`, else a warning and `None`.
///
/// The server guards itself: at most [`MAX_CONNECTIONS`] connections, [`HEADER_TIMEOUT`] for
/// a request's headers, [`IDLE_TIMEOUT`] for an idle kept-alive connection, a `Host` that
/// names this server ([`AllowedHosts`]), and a Content-Security-Policy on every answer.
pub async fn serve(opts: HttpOptions, hosts: AllowedHosts, view: Arc<LiveView>) -> Result<Option<HttpServer>, HttpError> {
    let listener = match tokio::net::TcpListener::bind(opts.addr).await {
        Ok(l) => l,
        Err(source) if opts.required => return Err(HttpError::Bind { addr: opts.addr, source }),
        Err(e) => {
            tracing::warn!("cannot serve the live page on {}: {e}; going on without it (choose another with --http ADDR)", opts.addr);
            return Ok(None);
        }
    };
    let addr = listener.local_addr()?;
    if !addr.ip().is_loopback() {
        tracing::warn!(%addr, "the live page is served beyond this machine (no authentication): put it behind the lab's proxy or use an SSH tunnel");
    }
    let app = guarded(routes::router(view.clone()), hosts, view.clone());
    let handle = tokio::spawn(accept_loop(listener, app, view));
    eprintln!("live page: http://{addr}/");
    tracing::info!(%addr, "live page and metrics served");
    Ok(Some(HttpServer { addr, handle }))
}

/// The router behind the `Host` check, with the security headers on every answer.
fn guarded(router: axum::Router, hosts: AllowedHosts, view: Arc<LiveView>) -> axum::Router {
    use axum::http::{header, HeaderValue, StatusCode};
    use axum::response::IntoResponse;
    let hosts = Arc::new(hosts);
    router.layer(axum::middleware::from_fn(move |req: axum::extract::Request, next: axum::middleware::Next| {
        let hosts = hosts.clone();
        let view = view.clone();
        async move {
            let host = req.headers().get(header::HOST).map(|h| h.to_str().unwrap_or("\u{fffd}").to_string());
            let mut resp = match host {
                Some(h) if !hosts.allows(&h) => {
                    let n = view.metrics.http_refused.inc() + 1;
                    if n.is_power_of_two() {
                        tracing::warn!(host = %h, refused = n, "live page: a request for another host name refused (DNS rebinding?); add the name to [output] http_hosts if it is this machine's");
                    }
                    (StatusCode::MISDIRECTED_REQUEST, format!("Host \"{h}\" does not name this server: add it to [output] http_hosts\n")).into_response()
                }
                _ => next.run(req).await,
            };
            let hd = resp.headers_mut();
            // A route with a policy of its own (a report's page) keeps it.
            hd.entry(header::CONTENT_SECURITY_POLICY).or_insert(HeaderValue::from_static(CSP));
            hd.insert(header::X_CONTENT_TYPE_OPTIONS, HeaderValue::from_static("nosniff"));
            hd.insert(header::REFERRER_POLICY, HeaderValue::from_static("no-referrer"));
            resp
        }
    }))
}

/// Accepts connections while fewer than [`MAX_CONNECTIONS`] are open (when all are, the
/// oldest `/events` stream of the address holding the most is closed to make room, else the
/// new one is refused); serves each
/// with the header and idle timeouts.
async fn accept_loop(listener: tokio::net::TcpListener, app: axum::Router, view: Arc<LiveView>) {
    let slots = Arc::new(Semaphore::new(MAX_CONNECTIONS));
    let streams = Arc::new(Streams::default());
    let mut accept_errors = 0u64;
    loop {
        let (stream, peer) = match listener.accept().await {
            Ok(x) => x,
            Err(e) => {
                // Out of file descriptors, or the like: wait, never spin.
                accept_errors += 1;
                if accept_errors.is_power_of_two() {
                    tracing::warn!(errors = accept_errors, "live page: cannot accept a connection: {e}");
                }
                tokio::time::sleep(Duration::from_millis(100)).await;
                continue;
            }
        };
        let Some(slot) = slot_for(&slots, &streams).await else {
            let n = view.metrics.http_refused.inc() + 1;
            if n.is_power_of_two() {
                tracing::warn!(%peer, refused = n, "live page: {MAX_CONNECTIONS} connections open; a new one was closed");
            }
            drop(stream);
            continue;
        };
        let conn = Conn { streams: streams.clone(), close: Arc::new(Notify::new()), key: Arc::default(), peer: peer.ip() };
        tokio::spawn(serve_connection(stream, peer, app.clone(), conn, slot));
    }
}

/// A connection slot: a free one, else the one the oldest stream held (closed for it).
async fn slot_for(slots: &Arc<Semaphore>, streams: &Streams) -> Option<OwnedSemaphorePermit> {
    if let Ok(s) = slots.clone().try_acquire_owned() {
        return Some(s);
    }
    if !streams.evict_oldest() {
        return None;
    }
    tokio::time::timeout(Duration::from_secs(2), slots.clone().acquire_owned()).await.ok()?.ok()
}

/// Serves one connection until it ends or, when it is a stream, is closed for a newer one.
async fn serve_connection(stream: tokio::net::TcpStream, peer: SocketAddr, app: axum::Router, conn: Conn, slot: OwnedSemaphorePermit) {
    let _slot = slot;
    // The peer's address (a refused token is logged with it) and the connection's handle.
    let ext = conn.clone();
    let with_peer = tower::util::MapRequestLayer::new(move |mut req: axum::extract::Request<hyper::body::Incoming>| {
        req.extensions_mut().insert(axum::extract::ConnectInfo(peer));
        req.extensions_mut().insert(ext.clone());
        req
    });
    let busy = Arc::new(AtomicUsize::new(0));
    let app = app.layer(axum::middleware::from_fn({
        let busy = busy.clone();
        move |req: axum::extract::Request, next: axum::middleware::Next| {
            let in_flight = InFlight::enter(busy.clone());
            async move {
                let answer = next.run(req).await;
                drop(in_flight);
                answer
            }
        }
    }));
    let service = hyper_util::service::TowerToHyperService::new(tower::Layer::layer(&with_peer, app));
    let io = IdleTimeout::new(stream, IDLE_TIMEOUT, busy);
    let mut http = hyper::server::conn::http1::Builder::new();
    http.timer(hyper_util::rt::TokioTimer::new()).header_read_timeout(HEADER_TIMEOUT).keep_alive(true);
    tokio::select! {
        r = http.serve_connection(hyper_util::rt::TokioIo::new(io), service) => {
            if let Err(e) = r {
                tracing::debug!(%peer, "live page connection: {e}");
            }
        }
        _ = conn.close.notified() => tracing::debug!(%peer, "live page: stream closed to make room for a new connection"),
    }
    conn.ended();
}

/// A request of a connection being answered (its handler has not returned yet): counted in
/// the connection's `busy` while it lives.
struct InFlight(Arc<AtomicUsize>);

impl InFlight {
    fn enter(busy: Arc<AtomicUsize>) -> Self {
        busy.fetch_add(1, Ordering::SeqCst);
        Self(busy)
    }
}

impl Drop for InFlight {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::SeqCst);
    }
}

/// A connection that fails (and so is closed) when nothing has been read or written for
/// `limit` while no request is being answered (`busy`, counted by [`InFlight`]) and no response
/// is being streamed — an idle kept-alive client. A stream of events (`/events`, kept alive
/// every 15 s by the server) writes, and so stays open; a request whose answer takes longer
/// than `limit` (a stop making a long test's report) is not cut off.
struct IdleTimeout {
    inner: tokio::net::TcpStream,
    limit: Duration,
    sleep: std::pin::Pin<Box<tokio::time::Sleep>>,
    busy: Arc<AtomicUsize>,
}

impl IdleTimeout {
    fn new(inner: tokio::net::TcpStream, limit: Duration, busy: Arc<AtomicUsize>) -> Self {
        Self { inner, limit, sleep: Box::pin(tokio::time::sleep(limit)), busy }
    }
    fn touch(&mut self) {
        let at = tokio::time::Instant::now() + self.limit;
        self.sleep.as_mut().reset(at);
    }
}

impl tokio::io::AsyncRead for IdleTimeout {
    fn poll_read(
        mut self: std::pin::Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
        buf: &mut tokio::io::ReadBuf<'_>,
    ) -> std::task::Poll<std::io::Result<()>> {
        use std::task::Poll;
        let before = buf.filled().len();
        match std::pin::Pin::new(&mut self.inner).poll_read(cx, buf) {
            Poll::Ready(r) => {
                if buf.filled().len() > before {
                    self.touch();
                }
                Poll::Ready(r)
            }
            Poll::Pending => loop {
                match self.sleep.as_mut().poll(cx) {
                    // A request is being answered: not idle; look again a limit later.
                    Poll::Ready(()) if self.busy.load(Ordering::SeqCst) > 0 => self.touch(),
                    Poll::Ready(()) => {
                        return Poll::Ready(Err(std::io::Error::new(std::io::ErrorKind::TimedOut, "idle connection closed")))
                    }
                    Poll::Pending => return Poll::Pending,
                }
            },
        }
    }
}

impl tokio::io::AsyncWrite for IdleTimeout {
    fn poll_write(
        mut self: std::pin::Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
        data: &[u8],
    ) -> std::task::Poll<std::io::Result<usize>> {
        let r = std::pin::Pin::new(&mut self.inner).poll_write(cx, data);
        if matches!(r, std::task::Poll::Ready(Ok(n)) if n > 0) {
            self.touch();
        }
        r
    }
    fn poll_flush(mut self: std::pin::Pin<&mut Self>, cx: &mut std::task::Context<'_>) -> std::task::Poll<std::io::Result<()>> {
        std::pin::Pin::new(&mut self.inner).poll_flush(cx)
    }
    fn poll_shutdown(mut self: std::pin::Pin<&mut Self>, cx: &mut std::task::Context<'_>) -> std::task::Poll<std::io::Result<()>> {
        std::pin::Pin::new(&mut self.inner).poll_shutdown(cx)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A connected pair of loopback sockets: (the server's end, the client's).
    async fn socket_pair() -> (tokio::net::TcpStream, tokio::net::TcpStream) {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.expect("bind");
        let client = tokio::net::TcpStream::connect(listener.local_addr().expect("addr")).await.expect("connect");
        (listener.accept().await.expect("accept").0, client)
    }

    #[tokio::test]
    async fn a_connection_is_not_idle_while_a_request_is_answered() {
        use tokio::io::AsyncReadExt;
        let limit = Duration::from_millis(100);
        let (server, _client) = socket_pair().await;
        let busy = Arc::new(AtomicUsize::new(0));
        let mut io = IdleTimeout::new(server, limit, busy.clone());
        let in_flight = InFlight::enter(busy.clone());
        let mut buf = [0u8; 8];
        // Four limits with a request in flight and nothing read or written: still open.
        let waited = tokio::time::timeout(limit * 4, io.read(&mut buf)).await;
        assert!(waited.is_err(), "closed while a request was answered: {waited:?}");
        drop(in_flight);
        assert_eq!(busy.load(Ordering::SeqCst), 0);
        // Answered: idle again, closed after a limit.
        let closed = tokio::time::timeout(limit * 20, io.read(&mut buf)).await.expect("closed when idle");
        assert_eq!(closed.expect_err("an idle connection fails").kind(), std::io::ErrorKind::TimedOut);
    }

    #[test]
    fn addresses() {
        let parse_addr = |s: &str| parse_listen_addr(s, DEFAULT_PORT).map_err(|e| e.to_string());
        assert_eq!(parse_addr("127.0.0.1:8080").unwrap(), SocketAddr::from(([127, 0, 0, 1], 8080)));
        assert_eq!(parse_addr("localhost:9000").unwrap(), SocketAddr::from(([127, 0, 0, 1], 9000)));
        assert!(parse_addr("[::1]:0").unwrap().ip().is_loopback());
        for bad in ["8080", "127.0.0.1", "127.0.0.1:99999", "lab-pc:80", ""] {
            assert!(parse_addr(bad).unwrap_err().contains("not a listen address"), "{bad}");
        }
    }

    #[test]
    fn host_names_of_this_server_only() {
        let hosts = AllowedHosts(vec!["lab-pc".into(), "lab-pc.local".into(), "rig3.lab.example".into()]);
        for ok in ["127.0.0.1:8080", "localhost:8080", "LOCALHOST", "[::1]:8080", "10.0.0.7", "lab-pc:8080", "rig3.lab.example:80"] {
            assert!(hosts.allows(ok), "{ok}");
        }
        for bad in ["evil.example:8080", "localhost.evil.example", "lab-pc.evil.example", "[evil]:80", "", "127.0.0.1.nip.io:8080"] {
            assert!(!hosts.allows(bad), "{bad}");
        }
    }

    #[test]
    fn a_taken_address_is_an_error_when_required_else_the_run_goes_on_without_the_page() {
        let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
        // Another program holds the port for the whole test.
        let held = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let addr = held.local_addr().unwrap();
        let specimen = tagdeflect_core::rig::SpecimenConfig {
            family: tagdeflect_core::tags::TagFamily::Tag36h11,
            size_mm: 30.0,
            tags: vec![],
            beam: None,
        };
        let rig = crate::rig_info::RigInfo {
            cameras: vec![],
            world: Default::default(),
            specimen,
            utm: None,
            cmod_gauge: None,
            rate_windows: Default::default(),
        };
        let hosts = AllowedHosts::new(&[]);
        let view = LiveView::new(&rig, "live");
        let optional = rt.block_on(serve(HttpOptions { addr, required: false }, hosts.clone(), view.clone()));
        assert!(matches!(optional, Ok(None)), "{:?}", optional.as_ref().map(|o| o.is_some()).map_err(|e| e.to_string()));
        let required = rt.block_on(serve(HttpOptions { addr, required: true }, hosts, view));
        let e = required.err().expect("a required page on a taken port is an error");
        assert!(e.to_string().contains(&format!("cannot serve the live page on {addr}")), "{e}");
        drop(held);
    }
}
