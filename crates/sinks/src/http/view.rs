//! The live view: what the endpoints serve (the cameras, the UTM, the recording and the
//! feed as the page shows them, the metrics, the `/events` backlog and broadcast), and the
//! hooks the pipeline calls to keep it current.

use std::collections::VecDeque;
use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;
use tokio::sync::broadcast;

use super::metrics::{cam, Metrics};
use super::snapshot::Snapshot;
use super::tap::SolverTap;
use super::HttpError;
use crate::RigInfo;
use tagdeflect_core::feed::FeedLine;
use tagdeflect_io::sources::SourceEvent;
use tagdeflect_io::utm::modbus::UtmEvent;

/// Events (feed lines, snapshot notices) kept for `/events` clients that fall behind.
pub(crate) const EVENT_BUFFER: usize = 256;
/// Feed lines kept for clients that connect later (sent first on `/events`); when full,
/// every second line is dropped, so the backlog spans the whole run (older parts at a
/// coarser step, the newest at full rate).
pub(crate) const BACKLOG_LINES: usize = 2000;

/// What `/events` carries.
#[derive(Clone, Debug)]
pub(crate) enum Event {
    /// A feed line (JSON).
    Line(Arc<str>),
    /// A new snapshot of a camera (JSON notice).
    Snapshot(Arc<str>),
}

/// Per camera, as the page shows it.
#[derive(Debug, Default)]
pub(crate) struct CameraOnPage {
    pub frames: u64,
    pub frames_dropped: u64,
    pub lost: Option<String>,
    pub recent: VecDeque<Instant>,
    pub last_frame: Option<Instant>,
    pub health: Option<tagdeflect_core::feed::CameraHealth>,
    pub bumps: u64,
    pub last_bump: Option<Instant>,
    pub pose: Option<tagdeflect_core::camera::Pose>,
    pub snapshot: Option<Snapshot>,
}

/// The UTM as the page shows it.
#[derive(Debug, Default)]
pub(crate) struct UtmState {
    pub up: Option<bool>,
    pub last_error: Option<String>,
    pub samples: u64,
    pub outages: u64,
    pub last_sample: Option<tagdeflect_io::utm::UtmSample>,
}

/// The recording as the page shows it.
#[derive(Debug, Default)]
pub(crate) struct RecordingState {
    pub dir: Option<String>,
    pub failed: Option<String>,
    pub drops: Option<Arc<crate::recorder::RecorderStatus>>,
}

/// The feed as the page shows it.
#[derive(Debug, Default)]
pub(crate) struct FeedState {
    pub lines: u64,
    pub last: Option<FeedLine>,
    pub last_at: Option<Instant>,
}

#[derive(Debug, Default)]
pub(crate) struct State {
    pub cameras: Vec<CameraOnPage>,
    pub utm: UtmState,
    pub recording: RecordingState,
    pub feed: FeedState,
    pub finished: bool,
}

/// The backlog of feed lines and the broadcast, changed together so that a client that
/// subscribes sees every line exactly once (backlog first, then live).
struct Events {
    backlog: VecDeque<Arc<str>>,
}

/// Everything the endpoints serve: shared by the server, the solver's tap and the hooks.
pub struct LiveView {
    pub(crate) config: RigInfo,
    pub(crate) mode: &'static str,
    pub(crate) metrics: Metrics,
    pub(crate) state: Mutex<State>,
    events: Mutex<Events>,
    tx: broadcast::Sender<Event>,
    pub(crate) started: Instant,
    pub(crate) started_ns: i64,
    pub(crate) clients: AtomicU64,
    /// The tests and their control API (`[output] tests`), once set.
    pub(crate) test_api: std::sync::OnceLock<super::test_api::TestApi>,
    /// The MQTT publisher's counters (`[output.mqtt]`), once set: the archive's lag.
    #[cfg(feature = "mqtt")]
    pub(crate) mqtt: std::sync::OnceLock<Arc<crate::mqtt::MqttStats>>,
}

impl LiveView {
    /// A view of a run of `config`; `mode` is `"live"` or `"replay"` (shown in the status).
    pub fn new(config: &RigInfo, mode: &'static str) -> Arc<LiveView> {
        let (tx, _) = broadcast::channel(EVENT_BUFFER);
        let metrics = Metrics::new();
        let view = LiveView {
            config: config.clone(),
            mode,
            metrics,
            state: Mutex::new(State { cameras: config.cameras.iter().map(|_| CameraOnPage::default()).collect(), ..State::default() }),
            events: Mutex::new(Events { backlog: VecDeque::new() }),
            tx,
            started: Instant::now(),
            started_ns: tagdeflect_core::clock::now_epoch_ns(),
            clients: AtomicU64::new(0),
            test_api: std::sync::OnceLock::new(),
            #[cfg(feature = "mqtt")]
            mqtt: std::sync::OnceLock::new(),
        };
        for c in &config.cameras {
            // Every camera's series exist from the start (a dashboard sees zeros, not gaps).
            let l = cam(&c.name);
            let _ = view.metrics.frames.get_or_create(&l);
            let _ = view.metrics.frames_dropped.get_or_create(&l);
            let _ = view.metrics.bumps.get_or_create(&l);
            let _ = view.metrics.posed.get_or_create(&l);
        }
        Arc::new(view)
    }

    /// Shows the MQTT publisher's delivery (the archive's lag) on the status and `/metrics`.
    #[cfg(feature = "mqtt")]
    pub fn set_mqtt(&self, stats: Arc<crate::mqtt::MqttStats>) {
        let _ = self.mqtt.set(stats);
    }

    /// Serves the control API of `tests` (SPEC "Tests"): every POST needs a token `auth` knows.
    pub fn set_test_api(&self, tests: Arc<crate::lab_test::LabTests>, auth: tagdeflect_core::users::Credentials) {
        let _ = self.test_api.set(super::test_api::TestApi::new(tests, auth));
    }

    pub(super) fn lock(&self) -> std::sync::MutexGuard<'_, State> {
        // A panicking holder leaves plain data behind: keep serving it.
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// The backlog so far and a receiver of what follows.
    pub(crate) fn subscribe(&self) -> (Vec<Arc<str>>, broadcast::Receiver<Event>) {
        let ev = self.events.lock().unwrap_or_else(|e| e.into_inner());
        (ev.backlog.iter().cloned().collect(), self.tx.subscribe())
    }

    /// Publishes a feed line to `/events`, the status and the metrics (never waits on a
    /// client). `latency_ms` and `dropped_sets` are read from the line.
    pub fn publish_line(&self, line: &FeedLine) {
        let json: Arc<str> = Arc::from(line.to_json());
        let m = &self.metrics;
        m.sets_solved.inc();
        if let Some(d) = line.dropped_sets {
            let seen = m.sets_dropped.get();
            if d > seen {
                m.sets_dropped.inc_by(d - seen);
            }
        }
        if let Some(l) = line.latency_ms {
            m.latency.observe(l / 1e3);
        }
        if let Some(n) = line.net_deflection_mm {
            m.net_deflection_mm.set(n);
        }
        if let Some(l) = line.load_kn {
            m.load_kn.set(l);
        }
        for h in &line.cameras {
            let l = cam(&h.name);
            if h.frame {
                m.frames_solved.get_or_create(&l).inc();
            }
            if let Some(r) = h.pose_reproj_px {
                m.pose_reproj_px.get_or_create(&l).set(r);
            }
            m.posed.get_or_create(&l).set(h.posed as i64);
            if let Some(d) = h.arrival_delay_ms {
                m.arrival_delay_s.get_or_create(&l).set(d / 1e3);
            } else {
                m.arrival_delay_s.remove(&l);
            }
            if h.bumped {
                m.bumps.get_or_create(&l).inc();
            }
        }
        {
            let now = Instant::now();
            let mut st = self.lock();
            for h in &line.cameras {
                if let Some(i) = self.config.camera_index(&h.name) {
                    let c = &mut st.cameras[i];
                    if h.bumped {
                        c.bumps += 1;
                        c.last_bump = Some(now);
                    }
                    c.health = Some(h.clone());
                }
            }
            st.feed.lines += 1;
            st.feed.last = Some(line.clone());
            st.feed.last_at = Some(now);
        }
        let mut ev = self.events.lock().unwrap_or_else(|e| e.into_inner());
        if ev.backlog.len() >= BACKLOG_LINES {
            // Keep every second line: the backlog covers the whole run at half the step.
            let mut keep = false;
            ev.backlog.retain(|_| {
                keep = !keep;
                keep
            });
        }
        ev.backlog.push_back(json.clone());
        // No receivers is not an error; a full buffer overwrites the oldest event.
        let _ = self.tx.send(Event::Line(json));
    }

    /// Camera poses after a frame set (world → camera).
    pub(crate) fn set_poses(&self, poses: Vec<Option<tagdeflect_core::camera::Pose>>) {
        let mut st = self.lock();
        for (c, p) in st.cameras.iter_mut().zip(poses) {
            c.pose = p;
        }
    }

    /// Hook: camera `camera` delivered a frame.
    pub(crate) fn on_frame(&self, camera: usize) {
        if let Some(c) = self.config.cameras.get(camera) {
            self.metrics.frames.get_or_create(&cam(&c.name)).inc();
        }
        let now = Instant::now();
        let mut st = self.lock();
        if let Some(c) = st.cameras.get_mut(camera) {
            c.frames += 1;
            c.last_frame = Some(now);
            c.lost = None;
            c.recent.push_back(now);
            while c.recent.len() > 16 {
                c.recent.pop_front();
            }
        }
    }

    /// Hook: camera `camera`'s source lost `count` frames.
    pub(crate) fn on_frames_dropped(&self, camera: usize, count: u64) {
        if let Some(c) = self.config.cameras.get(camera) {
            self.metrics.frames_dropped.get_or_create(&cam(&c.name)).inc_by(count);
        }
        if let Some(c) = self.lock().cameras.get_mut(camera) {
            c.frames_dropped += count;
        }
    }

    /// Hook: camera `camera` was lost (`Some(reason)`) or is back (`None`).
    pub(crate) fn on_camera_lost(&self, camera: usize, reason: Option<&str>) {
        if let (Some(c), Some(_)) = (self.config.cameras.get(camera), reason) {
            self.metrics.camera_lost.get_or_create(&cam(&c.name)).inc();
        }
        if let Some(c) = self.lock().cameras.get_mut(camera) {
            c.lost = reason.map(str::to_string);
        }
    }

    /// Hook: an event of the UTM poller (or a sample of a replayed recording).
    pub fn on_utm(&self, ev: &UtmEvent) {
        let m = &self.metrics;
        let mut st = self.lock();
        match ev {
            UtmEvent::Sample(s) => {
                m.utm_samples.inc();
                st.utm.samples += 1;
                st.utm.last_sample = Some(*s);
                if st.utm.up != Some(true) {
                    st.utm.up = Some(true);
                    m.utm_up.set(1);
                }
            }
            UtmEvent::Up => {
                st.utm.up = Some(true);
                m.utm_up.set(1);
            }
            UtmEvent::Down { reason } => {
                m.utm_up.set(0);
                m.utm_outages.inc();
                m.utm_poll_errors.inc();
                st.utm.outages += 1;
                st.utm.up = Some(false);
                st.utm.last_error = Some(reason.clone());
            }
        }
    }

    /// Hook: a recording is written into `dir`; `drops` is the recorder's state and what it
    /// could not keep up with (`sinks::recorder`).
    pub fn on_recording(&self, dir: &Path, drops: Arc<crate::recorder::RecorderStatus>) {
        self.metrics.recorder_active.set(1);
        let mut st = self.lock();
        st.recording.dir = Some(dir.display().to_string());
        st.recording.drops = Some(drops);
    }

    /// Hook: the recording failed (the feed goes on).
    pub fn on_recording_failed(&self, error: &str) {
        self.metrics.recorder_active.set(0);
        self.metrics.recorder_failed.set(1);
        self.lock().recording.failed = Some(error.to_string());
    }

    /// Hook: the run's sources are consumed (a replay ended); the page stays up.
    pub fn on_finished(&self) {
        self.lock().finished = true;
    }

    /// A camera's newest snapshot.
    pub(crate) fn snapshot(&self, camera: usize) -> Option<Snapshot> {
        self.lock().cameras.get(camera).and_then(|c| c.snapshot.clone())
    }

    pub(super) fn store_snapshot(&self, camera: usize, snap: Snapshot) {
        let Some(name) = self.config.cameras.get(camera).map(|c| c.name.clone()) else { return };
        let notice = serde_json::json!({
            "camera": name, "seq": snap.seq, "t_ns": snap.t_ns, "width": snap.width, "height": snap.height,
            "url": format!("/camera/{name}.jpg?seq={}", snap.seq),
        });
        if let Some(c) = self.lock().cameras.get_mut(camera) {
            c.snapshot = Some(snap);
        }
        let _ = self.tx.send(Event::Snapshot(Arc::from(notice.to_string())));
    }

    /// The solver's handle: publishes each frame set's line and offers snapshots.
    pub fn tap(self: &Arc<Self>) -> Result<SolverTap, HttpError> {
        SolverTap::start(self)
    }
}

/// Hook of the live pipeline's assembler: shows `ev` to the view (frames, drops, lost
/// cameras) and hands it back.
pub fn observe(view: Option<&LiveView>, ev: Option<SourceEvent>) -> Option<SourceEvent> {
    if let (Some(v), Some(e)) = (view, &ev) {
        match e {
            SourceEvent::Frame(f) => v.on_frame(f.camera),
            SourceEvent::Dropped { camera, count, .. } => v.on_frames_dropped(*camera, *count),
            SourceEvent::Lost { camera, reason } => v.on_camera_lost(*camera, Some(reason)),
            SourceEvent::Reopened { camera } => v.on_camera_lost(*camera, None),
        }
    }
    ev
}

/// Counts an `/events` client while it is connected.
pub(crate) struct ClientGuard(pub Arc<LiveView>);

impl ClientGuard {
    pub fn new(view: Arc<LiveView>) -> Self {
        let n = view.clients.fetch_add(1, Ordering::Relaxed) + 1;
        view.metrics.http_clients.set(n as i64);
        ClientGuard(view)
    }
}

impl Drop for ClientGuard {
    fn drop(&mut self) {
        let n = self.0.clients.fetch_sub(1, Ordering::Relaxed).saturating_sub(1);
        self.0.metrics.http_clients.set(n as i64);
    }
}
