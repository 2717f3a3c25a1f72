//! The live page and its endpoints (SPEC "Live page and endpoints", `[output] http`).
//!
//! ```text
//! solver thread ──SolverTap::publish (never waits)──▶ LiveView ──▶ axum server (tokio runtime)
//!   ├─ each feed line: JSON once, into a bounded broadcast (`/events`) + a decimated backlog
//!   ├─ status and metrics: small updates under short locks / atomics
//!   └─ at most one frame per camera per second ──try_send──▶ snapshot thread (JPEG)
//! assembler (frames, drops, lost cameras), UTM forwarder, recorder ──hooks──▶ LiveView
//! ```
//!
//! Endpoints: `/` the page (assets embedded in the binary, no network needed),
//! `/events` Server-Sent Events (`data:` = one feed line; `event: snapshot` = a new camera
//! snapshot), `/api/status` JSON (`status::Status`), `/camera/NAME.jpg` the latest
//! annotated snapshot, `/metrics` the OpenMetrics text exposition.
//!
//! A slow or stalled client never holds the measurement back: the broadcast keeps the last
//! `EVENT_BUFFER` events and a client that falls further behind skips ahead (counted in
//! `tagdeflect_http_events_lagged_total`); the solver's send never blocks.

mod metrics;
mod report_files;
mod routes;
mod server;
mod snapshot;
mod status;
mod tap;
mod test_api;
mod view;

use std::net::SocketAddr;

pub use server::{
    serve, wanted, AllowedHosts, HttpOptions, HttpServer, DEFAULT_ADDR, DEFAULT_PORT, HEADER_TIMEOUT, IDLE_TIMEOUT, MAX_CONNECTIONS,
};
pub use tap::SolverTap;
pub use test_api::{FAILURE_WINDOW, MAX_BODY, MAX_FAILURES};
pub use view::{observe, LiveView};

/// A problem of the HTTP sink.
#[derive(Debug, thiserror::Error)]
pub enum HttpError {
    /// The address cannot be listened on.
    #[error("cannot serve the live page on {addr}: {source}")]
    Bind {
        /// The address.
        addr: SocketAddr,
        /// The cause.
        source: std::io::Error,
    },
    /// The runtime or a thread could not be started.
    #[error("live page: {0}")]
    Io(#[from] std::io::Error),
}
