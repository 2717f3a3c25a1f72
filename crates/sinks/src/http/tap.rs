//! The solver's side of the live view: each finished line published, camera frames
//! offered to the snapshot thread, the tap as a sink of finished lines.

use std::sync::{mpsc as std_mpsc, Arc};
use std::time::Instant;

use super::snapshot::{self, SnapshotJob, SNAPSHOT_INTERVAL};
use super::{HttpError, LiveView};
use tagdeflect_core::feed::FeedLine;
use tagdeflect_core::frame::FrameSet;
use tagdeflect_core::observed::Observed;

/// The sinks' side of the live view, a [`LineSink`](crate::LineSink) whose `accept` never waits.
pub struct SolverTap {
    view: Arc<LiveView>,
    snapshots: std_mpsc::SyncSender<SnapshotJob>,
    last_offer: Vec<Option<Instant>>,
}

impl SolverTap {
    /// Starts the snapshot thread of `view` and the tap that feeds it.
    pub(super) fn start(view: &Arc<LiveView>) -> Result<SolverTap, HttpError> {
        let n = view.config.cameras.len();
        let (tx, rx) = std_mpsc::sync_channel::<SnapshotJob>(n.max(1));
        let v = view.clone();
        snapshot::spawn_encoder(rx, move |camera, snap| v.store_snapshot(camera, snap))?;
        Ok(SolverTap { view: view.clone(), snapshots: tx, last_offer: vec![None; n] })
    }

    /// Publishes a finished feed line; offers each camera's frame of `set` with the tags
    /// the measurement detected in it to the snapshot thread, at most once per camera per
    /// second.
    pub(crate) fn publish(&mut self, line: &FeedLine, set: Option<&FrameSet>, observed: &Observed) {
        self.view.publish_line(line);
        self.view.set_poses(observed.camera_poses.clone());
        let Some(set) = set else { return };
        let now = Instant::now();
        for (ci, tags) in &observed.seen {
            let Some(last) = self.last_offer.get_mut(*ci) else { continue };
            if last.is_some_and(|t| now.duration_since(t) < SNAPSHOT_INTERVAL) {
                continue;
            }
            let Some(frame) = set.frames.iter().find(|f| f.camera == *ci) else { continue };
            let job = SnapshotJob { camera: *ci, seq: set.seq, t_ns: frame.t_ns, image: frame.image.clone(), tags: tags.clone() };
            // A busy encoder: this frame is skipped, the next set is offered again.
            if self.snapshots.try_send(job).is_ok() {
                *last = Some(now);
            }
        }
    }
}

impl crate::LineSink for SolverTap {
    fn name(&self) -> String {
        "live page".into()
    }
    fn accept(&mut self, f: &crate::Finished) {
        self.publish(&f.line, f.set.as_ref(), &f.observed);
    }
}
