//! The one Modbus TCP server of the workspace (tokio-modbus underneath): the control output
//! (`tagdeflect_sinks::control_output`), the simulated UTM ([`crate::utm::sim_server`]) and the
//! simulated testing machine (`tagdeflect_sim::machine`) each say only how they answer a
//! request ([`Answer`]); listening, accepting and stopping are here.
//!
//! The server guards itself the same way for all of them: every connection is tracked, so that
//! stopping the server ([`ModbusServer`] dropped, or its task aborted) closes every open
//! connection too (tokio-modbus runs each connection in a task of its own, which would
//! otherwise outlive the listener); Nagle is off on every connection (a register read is a
//! few bytes); every request is checked on the byte stream before tokio-modbus's decoder
//! sees it (`frame_check`: the MBAP header, and a PDU's counts against its length): a
//! malformed one — function 0x0F with quantity 65 535 and no bytes panicked tokio-modbus
//! 0.15's codec — gets the exception "illegal data value" and its connection is closed,
//! logged once per 10 s with the count; clients' connections are logged once per 10 s with their count;
//! at most [`MAX_CONNECTIONS`] are open at once (more are closed at once, logged once
//! per 10 s); an accept error (out of file descriptors) is logged and retried with backoff
//! instead of ending the server. A read's range is checked by [`read_range`] (count 1 to [`MAX_READ`], inside the
//! served block) where a server serves a block of registers.

use std::collections::HashMap;
use std::future::{ready, Future};
use std::io;
use std::net::{Shutdown, SocketAddr};
use std::ops::Range;
use std::pin::Pin;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::Duration;

use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::task::JoinHandle;
use tokio_modbus::server::tcp::Server;
use tokio_modbus::{ExceptionCode, Request, Response};

mod frame_check;

/// Most registers one read may ask for (the Modbus limit).
pub const MAX_READ: u16 = 125;

/// Connections a server keeps open at once; more are closed at once (a flood of clients
/// would otherwise take every file descriptor of the daemon).
pub const MAX_CONNECTIONS: usize = 64;

/// The first wait after a failed accept; doubled after each failure up to
/// [`ACCEPT_RETRY_MAX`].
const ACCEPT_RETRY_MIN: Duration = Duration::from_millis(100);
/// The longest wait after a failed accept.
const ACCEPT_RETRY_MAX: Duration = Duration::from_secs(5);
/// Refused connections and accept errors are logged at most once per this time.
const LOG_EVERY: Duration = Duration::from_secs(10);

/// Counts events and says when to log them: the first, then once per [`LOG_EVERY`] (with the
/// count since the last line).
#[derive(Default)]
struct Throttle(Mutex<(Option<std::time::Instant>, u64)>);

impl Throttle {
    /// Counts one event; `Some(count)` when it is to be logged.
    fn hit(&self) -> Option<u64> {
        let mut g = self.0.lock().unwrap_or_else(|p| p.into_inner());
        g.1 += 1;
        let now = std::time::Instant::now();
        if g.0.is_some_and(|t| now.duration_since(t) < LOG_EVERY) {
            return None;
        }
        g.0 = Some(now);
        Some(std::mem::take(&mut g.1))
    }
}

/// How a server answers: one request, its response or an exception.
pub trait Answer: Send + Sync + 'static {
    /// The answer to `req`.
    fn answer(&self, req: &Request<'_>) -> Result<Response, ExceptionCode>;

    /// How long to hold the answer back before it is sent (`None`: at once); a fault
    /// injection's silence (the simulated UTM's outage).
    fn hold(&self) -> Option<Duration> {
        None
    }
}

/// The registers `start .. start + count` of a block of `registers`, or the exception a read
/// outside it gets: "illegal data value" for a count of 0 or above [`MAX_READ`], "illegal data
/// address" past the block's end.
pub fn read_range(start: u16, count: u16, registers: usize) -> Result<Range<usize>, ExceptionCode> {
    if count == 0 || count > MAX_READ {
        return Err(ExceptionCode::IllegalDataValue);
    }
    let (start, count) = (start as usize, count as usize);
    if start + count > registers {
        return Err(ExceptionCode::IllegalDataAddress);
    }
    Ok(start..start + count)
}

/// What the server's log lines call it (`"control output"`, `"simulated UTM"`) and at which
/// level a client's connection is logged.
#[derive(Debug, Clone, Copy)]
pub struct ServerName {
    /// The server's name in log lines.
    pub name: &'static str,
    /// A client's connection is logged at INFO (else DEBUG).
    pub clients_at_info: bool,
}

/// A running Modbus TCP server; stops (closing its connections) when dropped.
#[derive(Debug)]
pub struct ModbusServer {
    addr: SocketAddr,
    /// The server's task (`None` once handed out by [`ModbusServer::into_task`]).
    handle: Option<JoinHandle<()>>,
}

impl ModbusServer {
    /// Binds `bind` (port 0: a free one) and serves `answer` on the current tokio runtime.
    pub async fn bind(bind: SocketAddr, name: ServerName, answer: Arc<dyn Answer>) -> io::Result<ModbusServer> {
        ModbusServer::serve(TcpListener::bind(bind).await?, name, answer)
    }

    /// Serves `answer` on `listener` on the current tokio runtime.
    pub fn serve(listener: TcpListener, name: ServerName, answer: Arc<dyn Answer>) -> io::Result<ModbusServer> {
        let addr = listener.local_addr()?;
        let service = Arc::new(Service(answer));
        let handle = tokio::spawn(async move {
            let conns = Connections::default();
            let _close_all = CloseOnDrop(conns.clone());
            let (refused, connected) = (Throttle::default(), Throttle::default());
            let on_connected = |stream: TcpStream, peer: SocketAddr| {
                if conns.count() >= MAX_CONNECTIONS {
                    // Dropped: closed at once. Logged once per `LOG_EVERY`, with the count.
                    if let Some(n) = refused.hit() {
                        tracing::warn!(%peer, "{}: {MAX_CONNECTIONS} connections open: {n} connection(s) refused", name.name);
                    }
                    return ready(Ok(None));
                }
                if name.clients_at_info {
                    // The first, then one line per `LOG_EVERY` with the count: 1 000 clients
                    // (a scan, a flood of malformed frames) are not 1 000 lines.
                    if let Some(n) = connected.hit() {
                        tracing::info!(%peer, "{}: client connected ({n} since the last such line)", name.name);
                    }
                } else {
                    tracing::debug!(%peer, "{}: client connected", name.name);
                }
                let _ = stream.set_nodelay(true);
                ready(conns.track(stream, peer, name).map(|s| Some((service.clone(), s))))
            };
            let label = name.name;
            let on_error = move |e: io::Error| tracing::debug!("{label}: connection ended: {e}");
            let server = Server::new(listener);
            let (failed, mut wait) = (Throttle::default(), ACCEPT_RETRY_MIN);
            // An accept error (out of file descriptors, a connection aborted before it was
            // taken) ends tokio-modbus's loop: logged, waited out with backoff, and served on.
            while let Err(e) = server.serve(&on_connected, on_error).await {
                if let Some(n) = failed.hit() {
                    tracing::error!("{} on {addr}: accept failed ({n} time(s)): {e}; retrying", name.name);
                }
                tokio::time::sleep(wait).await;
                wait = (wait * 2).min(ACCEPT_RETRY_MAX);
            }
        });
        Ok(ModbusServer { addr, handle: Some(handle) })
    }

    /// Where it listens.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// Returns when the server stops by itself (its listener failed).
    pub async fn stopped(&mut self) {
        if let Some(h) = self.handle.as_mut() {
            let _ = h.await;
        }
    }

    /// The server's task, for a caller that keeps the task instead: the server then runs until
    /// the task is aborted (which closes its connections too).
    pub fn into_task(mut self) -> JoinHandle<()> {
        self.handle.take().expect("a server's task is handed out once")
    }
}

impl Drop for ModbusServer {
    fn drop(&mut self) {
        if let Some(h) = &self.handle {
            h.abort();
        }
    }
}

/// An [`Answer`] as tokio-modbus calls it.
struct Service(Arc<dyn Answer>);

impl tokio_modbus::server::Service for Service {
    type Request = Request<'static>;
    type Response = Response;
    type Exception = ExceptionCode;
    type Future = Pin<Box<dyn Future<Output = Result<Response, ExceptionCode>> + Send>>;

    fn call(&self, req: Self::Request) -> Self::Future {
        match self.0.hold() {
            Some(hold) => {
                let answer = self.0.answer(&req);
                Box::pin(async move {
                    tokio::time::sleep(hold).await;
                    answer
                })
            }
            None => Box::pin(ready(self.0.answer(&req))),
        }
    }
}

/// Open connections, so that stopping the server also closes them.
#[derive(Clone, Default)]
struct Connections {
    next: Arc<AtomicU64>,
    open: Arc<Mutex<HashMap<u64, std::net::TcpStream>>>,
    /// Malformed requests refused (logged once per [`LOG_EVERY`]).
    refused: Arc<Throttle>,
}

impl Connections {
    fn track(&self, stream: TcpStream, peer: SocketAddr, name: ServerName) -> io::Result<Tracked> {
        let std = stream.into_std()?;
        let dup = std.try_clone()?;
        let inner = TcpStream::from_std(std)?;
        let id = self.next.fetch_add(1, Ordering::Relaxed);
        if let Ok(mut open) = self.open.lock() {
            open.insert(id, dup);
        }
        Ok(Tracked { inner, id, conns: self.clone(), gate: Gate::default(), peer, name })
    }

    fn count(&self) -> usize {
        self.open.lock().map_or(0, |o| o.len())
    }

    fn close_all(&self) {
        if let Ok(mut open) = self.open.lock() {
            for (_, s) in open.drain() {
                let _ = s.shutdown(Shutdown::Both);
            }
        }
    }
}

/// Closes every tracked connection when the server task ends or is aborted.
struct CloseOnDrop(Connections);

impl Drop for CloseOnDrop {
    fn drop(&mut self) {
        self.0.close_all();
    }
}

/// A served connection; forgets its duplicate handle when the connection task ends. What it
/// reads passes its [`Gate`] first.
struct Tracked {
    inner: TcpStream,
    id: u64,
    conns: Connections,
    gate: Gate,
    peer: SocketAddr,
    name: ServerName,
}

/// The bytes of a connection between the socket and tokio-modbus's decoder: only whole,
/// checked frames pass ([`frame_check::scan`]); after a malformed one the reader sees the
/// end of the stream.
#[derive(Default)]
struct Gate {
    /// Bytes received: the first `passed` checked, the rest a frame not yet whole.
    inbox: Vec<u8>,
    passed: usize,
    /// The frame after the passed ones, refused: answered and the stream ended once those
    /// are read.
    refused: Option<frame_check::Refusal>,
    ended: bool,
}

impl Tracked {
    /// Refuses a malformed request: its exception reply (best effort: a few bytes into an
    /// idle socket), one log line per [`LOG_EVERY`] with the count.
    fn refuse(&mut self, r: frame_check::Refusal) {
        if !r.reply.is_empty() {
            let _ = self.inner.try_write(&r.reply);
        }
        if let Some(n) = self.conns.refused.hit() {
            let (name, peer) = (self.name.name, self.peer);
            tracing::warn!(%peer, "{name}: refused a malformed request ({}); its connection closed ({n} since the last such line)", r.why);
        }
    }
}

impl Drop for Tracked {
    fn drop(&mut self) {
        if let Ok(mut open) = self.conns.open.lock() {
            open.remove(&self.id);
        }
    }
}

impl AsyncRead for Tracked {
    fn poll_read(mut self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &mut ReadBuf<'_>) -> Poll<io::Result<()>> {
        loop {
            let g = &mut self.gate;
            if g.passed > 0 {
                let n = g.passed.min(buf.remaining());
                buf.put_slice(&g.inbox[..n]);
                g.inbox.drain(..n);
                g.passed -= n;
                return Poll::Ready(Ok(()));
            }
            if let Some(r) = g.refused.take() {
                // The frames before it were read and answered (tokio-modbus reads again only
                // after it sent the last answer): its exception now, then the end.
                g.ended = true;
                self.refuse(r);
            }
            if self.gate.ended {
                return Poll::Ready(Ok(()));
            }
            let mut chunk = [0u8; 1024];
            let mut read = ReadBuf::new(&mut chunk);
            std::task::ready!(Pin::new(&mut self.inner).poll_read(cx, &mut read))?;
            let g = &mut self.gate;
            if read.filled().is_empty() {
                // The client closed: a partial frame left is dropped with it.
                g.ended = true;
                continue;
            }
            g.inbox.extend_from_slice(read.filled());
            let s = frame_check::scan(&g.inbox);
            g.passed = s.passed;
            if s.refused.is_some() {
                g.inbox.truncate(s.passed);
                g.refused = s.refused;
            }
        }
    }
}

impl AsyncWrite for Tracked {
    fn poll_write(mut self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &[u8]) -> Poll<io::Result<usize>> {
        Pin::new(&mut self.inner).poll_write(cx, buf)
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.inner).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.inner).poll_shutdown(cx)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_outside_the_block_are_exceptions() {
        assert_eq!(read_range(2, 3, 12), Ok(2..5));
        assert_eq!(read_range(0, 0, 12), Err(ExceptionCode::IllegalDataValue));
        assert_eq!(read_range(0, 126, 65536), Err(ExceptionCode::IllegalDataValue));
        assert_eq!(read_range(10, 3, 12), Err(ExceptionCode::IllegalDataAddress));
        assert_eq!(read_range(65535, 2, 65536), Err(ExceptionCode::IllegalDataAddress));
    }

    struct Fixed;

    impl Answer for Fixed {
        fn answer(&self, req: &Request<'_>) -> Result<Response, ExceptionCode> {
            match *req {
                Request::ReadInputRegisters(a, n) => Ok(Response::ReadInputRegisters(vec![7; read_range(a, n, 4)?.len()])),
                _ => Err(ExceptionCode::IllegalFunction),
            }
        }
    }

    #[tokio::test]
    async fn serves_and_closes_its_connections_when_stopped() {
        use tokio_modbus::client::Reader;
        let name = ServerName { name: "test server", clients_at_info: false };
        let server = ModbusServer::bind(SocketAddr::from(([127, 0, 0, 1], 0)), name, Arc::new(Fixed)).await.unwrap();
        let mut ctx = tokio_modbus::client::tcp::connect(server.addr()).await.unwrap();
        assert_eq!(ctx.read_input_registers(1, 3).await.unwrap(), Ok(vec![7; 3]));
        assert_eq!(ctx.read_input_registers(3, 2).await.unwrap(), Err(ExceptionCode::IllegalDataAddress));
        drop(server);
        tokio::time::sleep(Duration::from_millis(50)).await;
        assert!(ctx.read_input_registers(0, 1).await.is_err(), "the connection is closed with the server");
    }

    #[tokio::test]
    async fn connections_over_the_cap_are_closed_and_the_first_ones_served() {
        use tokio::io::AsyncReadExt;
        use tokio_modbus::client::Reader;
        let name = ServerName { name: "test server", clients_at_info: false };
        let server = ModbusServer::bind(SocketAddr::from(([127, 0, 0, 1], 0)), name, Arc::new(Fixed)).await.unwrap();
        let mut first = tokio_modbus::client::tcp::connect(server.addr()).await.unwrap();
        assert_eq!(first.read_input_registers(0, 1).await.unwrap(), Ok(vec![7]));
        let mut held = Vec::new();
        for _ in 1..MAX_CONNECTIONS {
            let mut c = tokio_modbus::client::tcp::connect(server.addr()).await.unwrap();
            assert_eq!(c.read_input_registers(0, 1).await.unwrap(), Ok(vec![7]), "served up to the cap");
            held.push(c);
        }
        // One more: closed by the server at once (end of stream, not a hang).
        let mut extra = TcpStream::connect(server.addr()).await.unwrap();
        let mut buf = [0u8; 8];
        let n = tokio::time::timeout(Duration::from_secs(30), extra.read(&mut buf)).await.expect("closed, not left hanging");
        assert!(matches!(n, Ok(0) | Err(_)), "{n:?}");
        assert_eq!(first.read_input_registers(1, 2).await.unwrap(), Ok(vec![7; 2]), "the open ones are still served");
        // A connection closed makes room again.
        drop(held.pop());
        let mut again = None;
        for _ in 0..100 {
            let mut c = tokio_modbus::client::tcp::connect(server.addr()).await.unwrap();
            if let Ok(Ok(v)) = c.read_input_registers(0, 1).await {
                again = Some(v);
                break;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        assert_eq!(again, Some(vec![7]));
    }

    /// Run in a child process under `prlimit --nofile` (see the next test): out of file
    /// descriptors, the server's accept fails; it is retried, and the client waiting in the
    /// backlog is served once descriptors are free again.
    #[tokio::test]
    async fn child_accept_errors_are_retried() {
        use tokio_modbus::client::Reader;
        if std::env::var_os("MODBUS_SERVER_CHILD").is_none() {
            return;
        }
        let name = ServerName { name: "test server", clients_at_info: false };
        let server = ModbusServer::bind(SocketAddr::from(([127, 0, 0, 1], 0)), name, Arc::new(Fixed)).await.unwrap();
        let addr = server.addr();
        // Take every descriptor, then free one for the client's own socket.
        let mut files = Vec::new();
        while let Ok(f) = std::fs::File::open("/dev/null") {
            files.push(f);
        }
        files.pop();
        let client = tokio::spawn(async move {
            let mut c = tokio_modbus::client::tcp::connect(addr).await.unwrap();
            c.read_input_registers(0, 2).await.unwrap()
        });
        tokio::time::sleep(Duration::from_millis(500)).await;
        assert!(!client.is_finished(), "not served while the server has no descriptor");
        drop(files);
        let got = tokio::time::timeout(Duration::from_secs(60), client).await.expect("served after the retry").unwrap();
        assert_eq!(got, Ok(vec![7; 2]));
        println!("CHILD OK");
    }

    #[test]
    fn accept_errors_are_retried_not_the_end_of_the_server() {
        let exe = std::env::current_exe().unwrap();
        let o = std::process::Command::new("prlimit")
            .arg("--nofile=64:64")
            .arg("--")
            .arg(exe)
            .args(["--exact", "modbus_server::tests::child_accept_errors_are_retried", "--nocapture", "--test-threads=1"])
            .env("MODBUS_SERVER_CHILD", "1")
            .env("TAGDEFLECT_LOG", "debug")
            .output()
            .expect("prlimit (util-linux)");
        let out = String::from_utf8_lossy(&o.stdout);
        assert!(o.status.success() && out.contains("CHILD OK"), "{out}\n{}", String::from_utf8_lossy(&o.stderr));
    }
}
