//! Simulated live cameras (`source = "sim"`) and the built-in demo rig.
//!
//! The scene is the one `simulate` renders ([`crate::SimRig`]), run live: the rig's
//! clock starts at the moment the pipeline starts and the load cycles (up, down, up …) so a
//! demo can run for hours. Each simulated camera is a thread that renders its frame of
//! frame set `k` at the nominal time `start + k / fps` (with the rig's jitter and simulated
//! dropped frames) through the capture loop every camera uses ([`SimSession`]): `try_send`
//! only, a full channel drops the frame. If rendering falls behind the frame clock, frames
//! are skipped (counted), never queued up, so the demo reflects a real camera's behaviour.

use std::sync::Arc;
use std::time::Duration;

use crate::{SimError, SimParams, SimRig};
use tagdeflect_core::clock;
use tagdeflect_core::frame::GrayImage;
use tagdeflect_io::sources::capture::{CaptureSession, Captured};
use tagdeflect_io::utm::config::{RegisterConfig, RegisterKind, UtmAddress, UtmConfig, ValueType, WordOrder};
use tagdeflect_io::utm::sim_server::UtmModel;

/// The simulated rig of a live run.
#[derive(Debug)]
pub struct LiveRig {
    rig: SimRig,
}

impl LiveRig {
    /// Builds the rig from the config's `[sim]` section (defaults when absent), with its
    /// clock starting at `start_ns` and a cyclic load history (a verification run holds its last
    /// step instead). The config's `sim` cameras are
    /// the rig's cameras (same names, in order): checked when the config is read.
    pub fn new(sim: Option<&SimParams>, start_ns: i64) -> Result<LiveRig, SimError> {
        let mut params = sim.cloned().unwrap_or_default();
        params.start_ns = start_ns;
        // A verification run holds its last position; a test cycles so a demo can run for hours.
        params.cyclic = params.verify_steps.trim().is_empty();
        let rig = SimRig::new(&params)?;
        Ok(LiveRig { rig })
    }

    /// The underlying rig (truth, rendering).
    pub fn rig(&self) -> &SimRig {
        &self.rig
    }

    /// The simulated UTM's outage window (ns since the Unix epoch), if `[sim]` sets one.
    pub fn utm_outage(&self) -> Option<(i64, i64)> {
        self.rig.utm_outage()
    }

    /// The UTM's load and stroke as functions of time, for the simulated Modbus server.
    pub fn utm_model(self: &Arc<Self>) -> UtmModel {
        let me = self.clone();
        Arc::new(move |t_ns| {
            let s = me.rig.utm_sample(t_ns);
            (s.load_kn, s.stroke_mm.unwrap_or(0.0))
        })
    }
}

/// Simulated camera `camera` of the rig as a capture session: each frame of set `k` is
/// rendered at its nominal time `start + k / fps` (with the rig's jitter and dropped frames)
/// and handed to the same capture loop as a real camera's buffers ([`tagdeflect_io::sources::capture`]:
/// same emitter, frame pool and drop counting). If rendering falls behind the frame clock,
/// frames are skipped and counted as missed, never queued up, as a real camera's would be.
#[derive(Debug)]
pub struct SimSession {
    rig: Arc<LiveRig>,
    camera: usize,
    k: u64,
    missed: u64,
}

impl SimSession {
    /// Camera `camera` of `rig`, from its first frame set.
    pub fn new(rig: Arc<LiveRig>, camera: usize) -> Self {
        Self { rig, camera, k: 0, missed: 0 }
    }
}

impl CaptureSession for SimSession {
    fn next(&mut self, into: &mut GrayImage) -> Captured {
        let r = &self.rig.rig;
        let due = r.set_time_ns(self.k);
        let now = clock::now_epoch_ns();
        if due > now {
            // Bounded wait, so the capture loop sees its stop flag.
            std::thread::sleep(Duration::from_nanos(due.saturating_sub(now).unsigned_abs()).min(Duration::from_millis(100)));
            return Captured::Timeout;
        }
        // Behind the frame clock by more than a frame: skip to the current frame.
        let current = u64::try_from(r.set_index_at(now)).unwrap_or(0).max(self.k);
        if current > self.k + 1 {
            self.missed += current - self.k - 1;
            self.k = current;
            return Captured::Timeout;
        }
        let k = self.k;
        self.k += 1;
        match r.frame_time_ns(self.camera, k) {
            Some(t_ns) => {
                *into = r.render(self.camera, t_ns);
                Captured::Image(t_ns)
            }
            // The rig drops this frame (`drop_prob`): as a camera losing a frame.
            None => {
                self.missed += 1;
                Captured::Timeout
            }
        }
    }

    fn take_missed(&mut self) -> u64 {
        std::mem::take(&mut self.missed)
    }
}

/// The built-in demo rig's parameters: three simulated 640x480 cameras at 5 fps. Sized to
/// keep up on a 2-core machine (rendering and measuring share the cores).
pub fn demo_params() -> SimParams {
    SimParams { cameras: 3, width: 640, height: 480, fps: 5.0, frame_sets: 60, rest_frames: 5, subsamples: 4, ..SimParams::default() }
}

/// The demo's UTM: the simulated UTM served over Modbus TCP on loopback (f32 load at input
/// register 0, f32 stroke at 2), polled at 50 Hz.
pub fn demo_utm() -> UtmConfig {
    let f32_at = |register| RegisterConfig {
        register,
        kind: RegisterKind::Input,
        value_type: ValueType::F32,
        word_order: WordOrder::Abcd,
        scale: 1.0,
        offset: 0.0,
    };
    UtmConfig { address: UtmAddress::Sim, unit: 1, poll_hz: 50.0, timeout_ms: 200.0, load: f32_at(0), stroke: Some(f32_at(2)) }
}
