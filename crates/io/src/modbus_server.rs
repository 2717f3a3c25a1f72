//! The one Modbus TCP server of the workspace (tokio-modbus underneath): the control output
//! (`tagdeflect_sinks::control_output`), the simulated UTM ([`crate::utm::sim_server`]) and the
//! simulated testing machine (`tagdeflect_sim::machine`) each say only how they answer a
//! request ([`Answer`]); listening, accepting and stopping are here.
//!
//! The server guards itself the same way for all of them: every connection is tracked, so that
//! stopping the server ([`ModbusServer`] dropped, or its task aborted) closes every open
//! connection too (tokio-modbus runs each connection in a task of its own, which would
//! otherwise outlive the listener); Nagle is off on every connection (a register read is a
//! few bytes); malformed frames are tokio-modbus's to refuse (the connection ends, logged at
//! DEBUG). A read's range is checked by [`read_range`] (count 1 to [`MAX_READ`], inside the
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

/// Most registers one read may ask for (the Modbus limit).
pub const MAX_READ: u16 = 125;

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
            let on_connected = |stream: TcpStream, peer: SocketAddr| {
                if name.clients_at_info {
                    tracing::info!(%peer, "{}: client connected", name.name);
                } else {
                    tracing::debug!(%peer, "{}: client connected", name.name);
                }
                let _ = stream.set_nodelay(true);
                ready(conns.track(stream).map(|s| Some((service.clone(), s))))
            };
            let label = name.name;
            let on_error = move |e: io::Error| tracing::debug!("{label}: connection ended: {e}");
            if let Err(e) = Server::new(listener).serve(&on_connected, on_error).await {
                tracing::error!("{} on {addr}: accept failed: {e}", name.name);
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
}

impl Connections {
    fn track(&self, stream: TcpStream) -> io::Result<Tracked> {
        let std = stream.into_std()?;
        let dup = std.try_clone()?;
        let inner = TcpStream::from_std(std)?;
        let id = self.next.fetch_add(1, Ordering::Relaxed);
        if let Ok(mut open) = self.open.lock() {
            open.insert(id, dup);
        }
        Ok(Tracked { inner, id, conns: self.clone() })
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

/// A served connection; forgets its duplicate handle when the connection task ends.
struct Tracked {
    inner: TcpStream,
    id: u64,
    conns: Connections,
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
        Pin::new(&mut self.inner).poll_read(cx, buf)
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
}
