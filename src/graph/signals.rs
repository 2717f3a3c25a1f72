//! The signals that stop a run: SIGINT, SIGTERM and SIGHUP (a closed terminal or a
//! `kill -HUP` ends the run as SIGTERM does), watched from the moment the run starts.

use anyhow::{Context, Result};

/// SIGINT, SIGTERM and SIGHUP, watched from the moment this is made (a signal that comes
/// before the first `recv` is kept for it).
pub(crate) struct StopSignals {
    int: tokio::signal::unix::Signal,
    term: tokio::signal::unix::Signal,
    hup: tokio::signal::unix::Signal,
}

impl StopSignals {
    /// Watches the three signals (inside a Tokio runtime).
    pub(crate) fn watch() -> Result<Self> {
        use tokio::signal::unix::{signal, SignalKind};
        Ok(Self {
            int: signal(SignalKind::interrupt()).context("cannot watch SIGINT")?,
            term: signal(SignalKind::terminate()).context("cannot watch SIGTERM")?,
            hup: signal(SignalKind::hangup()).context("cannot watch SIGHUP")?,
        })
    }

    /// Waits for the next stop signal; what to log ("SIGTERM: stopping", ...).
    pub(crate) async fn recv(&mut self) -> &'static str {
        tokio::select! {
            _ = self.int.recv() => "SIGINT: stopping",
            _ = self.term.recv() => "SIGTERM: stopping",
            _ = self.hup.recv() => "SIGHUP: stopping as on SIGTERM",
        }
    }

    /// Keeps the page up after a replay until SIGINT/SIGTERM/SIGHUP (watched since the run
    /// started: one that came during the replay ends this at once).
    pub(crate) async fn linger(&mut self) {
        tracing::info!("recording consumed; the live page stays up until Ctrl-C (SIGINT) or SIGTERM");
        self.recv().await;
    }
}
