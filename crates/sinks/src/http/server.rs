//! The server: where the page is served ([`HttpOptions`], [`parse_addr`], [`wanted`]) and
//! the axum server on the pipeline's runtime ([`serve`], [`HttpServer`]).

use std::net::SocketAddr;
use std::sync::Arc;

use super::{routes, HttpError, LiveView};

/// Where `demo` serves the page unless told otherwise (and `[output] http`'s usual value).
pub const DEFAULT_ADDR: &str = "127.0.0.1:8080";

/// Where to serve the page.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct HttpOptions {
    /// The address to listen on (port 0: any free port; the bound address is printed).
    pub addr: SocketAddr,
    /// Failing to listen is an error (else a warning and the run goes on without the page:
    /// `demo`'s default address may be taken by another program).
    pub required: bool,
}

/// Parses a listen address: `IP:PORT`, `[IPv6]:PORT` or `localhost:PORT`.
pub fn parse_addr(s: &str) -> Result<SocketAddr, String> {
    let bad = || format!("\"{s}\" is not a listen address: expected IP:PORT, e.g. \"{DEFAULT_ADDR}\" (loopback) or \"0.0.0.0:8080\"");
    if let Ok(a) = s.parse::<SocketAddr>() {
        return Ok(a);
    }
    match s.rsplit_once(':') {
        Some(("localhost", port)) => port.parse::<u16>().map(|p| SocketAddr::from(([127, 0, 0, 1], p))).map_err(|_| bad()),
        _ => Err(bad()),
    }
}

/// Where a live run serves the page: `opts` (the command line) first, else `[output] http`
/// (validated when the config was loaded: a taken address is then an error).
pub fn wanted(configured: Option<&str>, opts: Option<HttpOptions>) -> Option<HttpOptions> {
    opts.or_else(|| configured.and_then(|a| parse_addr(a).ok()).map(|addr| HttpOptions { addr, required: true }))
}

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

/// Starts serving `view` on the current tokio runtime. Prints `live page: http://ADDR/` on
/// stderr with the bound address. When the address cannot be listened on: an error if
/// `opts.required`, else a warning and `None`.
pub async fn serve(opts: HttpOptions, view: Arc<LiveView>) -> Result<Option<HttpServer>, HttpError> {
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
    let app = routes::router(view);
    let handle = tokio::spawn(async move {
        if let Err(e) = axum::serve(listener, app).await {
            tracing::error!("live page: {e}");
        }
    });
    eprintln!("live page: http://{addr}/");
    tracing::info!(%addr, "live page and metrics served");
    Ok(Some(HttpServer { addr, handle }))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn addresses() {
        assert_eq!(parse_addr("127.0.0.1:8080").unwrap(), SocketAddr::from(([127, 0, 0, 1], 8080)));
        assert_eq!(parse_addr("localhost:9000").unwrap(), SocketAddr::from(([127, 0, 0, 1], 9000)));
        assert!(parse_addr("[::1]:0").unwrap().ip().is_loopback());
        for bad in ["8080", "127.0.0.1", "127.0.0.1:99999", "lab-pc:80", ""] {
            assert!(parse_addr(bad).unwrap_err().contains("not a listen address"), "{bad}");
        }
    }
}
