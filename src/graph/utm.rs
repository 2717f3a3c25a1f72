//! The UTM in a run: where its events come from (the poller of `[utm]`, the simulated UTM, a
//! recording played at its pace, or none), and the forwarder that shows each event to the page,
//! the tests, the UTM files and the recorder before relaying it to the solver.

use std::sync::atomic::AtomicI64;
use std::sync::Arc;
use std::time::Duration;

use anyhow::Result;
use tokio::sync::{mpsc, watch};

use tagdeflect_io::utm::modbus::{run_poller, UtmEvent};
use tagdeflect_io::utm::relay::RelaySender;
use tagdeflect_sinks::lab_test::LabTests;
use tagdeflect_sinks::recorder::RecorderTx;

use crate::config::Config;
use crate::graph::page::PageHandle;
use crate::graph::playback::{recorded_utm_wait, PacedUtm, Pacing, Playback};
use crate::graph::sim::{self, SimUtmServer};
use crate::graph::solver::UtmFeed;
use crate::graph::sources::Sources;
use crate::graph::utm_file::UtmFiles;

/// UTM events a run's tasks send to the forwarder.
const UTM_EVENTS: usize = 256;

/// The run's UTM: its events' receiver, how the solver waits for it, and what keeps it up.
pub(crate) struct Utm {
    pub(crate) events: mpsc::Receiver<UtmEvent>,
    /// How each set waits for the sample after it (none: no UTM feeds the run).
    pub(crate) feed: Option<UtmFeed>,
    /// Keeps the simulated UTM's server up while held.
    pub(crate) guard: UtmGuard,
}

/// What keeps the run's UTM up (the simulated UTM's server), held for the run.
pub(crate) struct UtmGuard(#[allow(dead_code)] Option<SimUtmServer>);

/// Starts the run's UTM (see the module doc). An as-fast replay has its UTM samples already
/// (given to the measurement before the first set) and marks no UTM state; a replay at the
/// recorded pace, paced without dropping or not, has its recording's samples handed over by
/// its player(s) in step with the frames ([`in_step_link`]) whether or not its config has a
/// `[utm]` (a folder may carry `utm.jsonl` from a UTM configured elsewhere): each set then
/// waits, by the recording's clock, for the samples around its time.
pub(crate) async fn start(
    config: &Config,
    playback: Option<&Playback>,
    sources: Option<&Sources>,
    in_step: Option<InStepLink>,
    shutdown: watch::Receiver<bool>,
) -> Result<Utm> {
    if let Some(InStepLink { events, sent, wait }) = in_step {
        let feed = UtmFeed { wait, up_at_start: true, in_step: Some(sent) };
        return Ok(Utm { events, feed: Some(feed), guard: UtmGuard(None) });
    }
    let (tx, events) = mpsc::channel::<UtmEvent>(UTM_EVENTS);
    if playback.is_some() {
        return Ok(Utm { events, feed: None, guard: UtmGuard(None) });
    }
    let Some(ucfg) = &config.utm else { return Ok(Utm { events, feed: None, guard: UtmGuard(None) }) };
    let (ucfg, sim) = sim::polled_utm(ucfg, sources.map(|s| &s.rig)).await?;
    let feed = UtmFeed { wait: Duration::from_secs_f64(2.5 / ucfg.poll_hz), up_at_start: false, in_step: None };
    tokio::spawn(async move {
        if let Err(e) = run_poller(ucfg, tx, shutdown).await {
            tracing::error!("UTM: {e}");
        }
    });
    Ok(Utm { events, feed: Some(feed), guard: UtmGuard(Some(sim)) })
}

/// The solver's side of a replay's UTM stream handed over with its frames (see [`in_step_link`]).
pub(crate) struct InStepLink {
    events: mpsc::Receiver<UtmEvent>,
    sent: Arc<AtomicI64>,
    wait: Duration,
}

/// The UTM stream of a replay at its recorded pace ([`Pacing::Paced`] or [`Pacing::Recorded`])
/// of `pb`, handed over with its frames: the players' side (the channel and the recorded time
/// of the newest sample handed over) and the run's. None as fast as it goes, or when the
/// recording has no UTM sample.
pub(crate) fn in_step_link(pb: &Playback) -> Option<(PacedUtm, InStepLink)> {
    if pb.pacing == Pacing::AsFast || pb.rec.utm.is_empty() {
        return None;
    }
    let (tx, events) = mpsc::channel::<UtmEvent>(UTM_EVENTS);
    let sent = Arc::new(AtomicI64::new(i64::MIN));
    Some((PacedUtm { tx, sent: sent.clone() }, InStepLink { events, sent, wait: recorded_utm_wait(&pb.rec) }))
}

/// Who sees each UTM event before the solver.
pub(crate) struct UtmWatchers {
    pub(crate) page: PageHandle,
    pub(crate) tests: Option<Arc<LabTests>>,
    pub(crate) files: UtmFiles,
    pub(crate) recorder: Option<RecorderTx>,
}

/// Forwards every UTM event to its watchers, then to the solver's relay.
pub(crate) fn forward(mut events: mpsc::Receiver<UtmEvent>, w: UtmWatchers, solver: RelaySender) -> tokio::task::JoinHandle<()> {
    let throttle = crate::graph::solver::throttle();
    tokio::spawn(async move {
        while let Some(ev) = events.recv().await {
            if let Some(t) = throttle {
                tokio::time::sleep(t).await;
            }
            w.page.on_utm(&ev);
            if let UtmEvent::Sample(s) = &ev {
                if let Some(t) = &w.tests {
                    t.on_utm(s);
                }
                w.files.push(s);
                if let Some(tx) = &w.recorder {
                    tx.utm(*s);
                }
            }
            solver.send(ev);
        }
    })
}
