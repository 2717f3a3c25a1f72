//! `/api/status`: what the run is doing now, as JSON (field list in the README). The run's
//! identity and its newest line come from the status model the MQTT status reads too
//! ([`crate::status::RunStatus`]); the rest is the page's own view of the run.
//!
//! `problems` lists, in words, everything the page's banner shows: the UTM down, a camera
//! lost, stale (no frame for [`STALE_FRAME_INTERVALS`] frame intervals) or bumped in the
//! last [`BUMP_SHOWN_S`] s, not posed, the recording failing, no feed line for
//! [`STALE_FRAME_INTERVALS`] frame intervals.

use serde::Serialize;
use std::sync::atomic::Ordering;
use std::time::Instant;

use super::view::{CameraOnPage, FeedState, LiveView, RecordingState, UtmState};
use crate::status::{RunCamera, RunStatus};
use tagdeflect_core::camera_config::CameraConfig;
use tagdeflect_core::rig::TagRole;

/// A camera (or the feed) is stale after this many frame intervals without a frame (line).
pub const STALE_FRAME_INTERVALS: f64 = 5.0;
/// A bump is shown this long after it was detected, seconds.
pub const BUMP_SHOWN_S: f64 = 10.0;
/// Staleness is never claimed sooner than this, seconds (slow frame rates, start-up).
pub const MIN_STALE_S: f64 = 2.0;

/// The whole status.
#[derive(Debug, Serialize)]
pub struct Status {
    /// `tagdeflect` version.
    pub version: &'static str,
    /// `"live"` or `"replay"`.
    pub mode: &'static str,
    /// The run started, ns since the Unix epoch.
    pub started_ns: i64,
    /// Seconds since the start.
    pub uptime_s: f64,
    /// A replay whose recording is consumed (the page stays up).
    pub finished: bool,
    /// `world.up`: the page shows vertical displacement as `disp_mm · up`.
    pub world_up: [f64; 3],
    /// The expected frame interval, seconds (from the cameras' `fps`), when known.
    pub frame_interval_s: Option<f64>,
    /// The cameras.
    pub sources: Vec<SourceStatus>,
    /// The specimen tags and their roles.
    pub specimen_tags: Vec<TagStatus>,
    /// `[specimen.beam]` (the page's bending profile: the span), when configured.
    pub beam: Option<tagdeflect_core::beam::BeamConfig>,
    /// The CMOD gauge, when the rig has one.
    pub cmod_gauge: Option<String>,
    /// The standards' deflection-rate windows for this beam (see `RigInfo::rate_windows`).
    pub rate_windows: std::collections::BTreeMap<String, serde_json::Value>,
    /// The testing machine.
    pub utm: UtmStatus,
    /// The recording.
    pub recording: RecordingStatus,
    /// The feed's delivery to the archive over MQTT (`[output.mqtt]`), when published.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub archive: Option<ArchiveStatus>,
    /// The feed and the pipeline's counters.
    pub feed: FeedStatus,
    /// `/events` clients.
    pub http: HttpStatus,
    /// Everything wrong now, in words (empty when all is well).
    pub problems: Vec<String>,
}

/// One camera.
#[derive(Debug, Serialize)]
pub struct SourceStatus {
    /// Name from the config.
    pub name: String,
    /// `source` from the config.
    pub source: String,
    /// Image size, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// Configured frame rate, Hz.
    pub fps: Option<f64>,
    /// Frames delivered by the source.
    pub frames: u64,
    /// Frames the source lost before the pipeline.
    pub frames_dropped: u64,
    /// Measured frame rate over the last 16 frames, Hz.
    pub frame_rate_hz: Option<f64>,
    /// Seconds since the last frame.
    pub last_frame_age_s: Option<f64>,
    /// Why the camera is lost (being reopened), when it is.
    pub lost: Option<String>,
    /// No frame for several frame intervals.
    pub stale: bool,
    /// The camera has a pose.
    pub posed: bool,
    /// Bumps detected so far.
    pub bumps: u64,
    /// A bump was detected in the last [`BUMP_SHOWN_S`] seconds.
    pub bumped_recently: bool,
    /// RMS reprojection error of the background tags with the pose in use, px.
    pub pose_reproj_px: Option<f64>,
    /// How late the camera's frames steadily arrive, as the last feed line said
    /// (`cameras[].arrival_delay_ms`), ms.
    pub arrival_delay_ms: Option<f64>,
    /// Background tags seen in the last frame set.
    pub background_tags: Option<usize>,
    /// Specimen tags seen in the last frame set.
    pub specimen_tags: Option<usize>,
    /// The pose in use, world → camera (`x_cam = R(rvec) x_world + tvec_mm`).
    pub pose: Option<PoseStatus>,
    /// The newest annotated snapshot.
    pub snapshot: Option<SnapshotStatus>,
}

/// A camera pose.
#[derive(Debug, Serialize)]
pub struct PoseStatus {
    /// Rotation vector (OpenCV), rad.
    pub rvec: [f64; 3],
    /// Translation, mm.
    pub tvec_mm: [f64; 3],
    /// Camera centre in the world, mm.
    pub centre_mm: [f64; 3],
}

/// A camera snapshot.
#[derive(Debug, Serialize)]
pub struct SnapshotStatus {
    /// Where to get it.
    pub url: String,
    /// Frame set it shows.
    pub seq: u64,
    /// Frame time, ns since the Unix epoch.
    pub t_ns: i64,
    /// Seconds since it was made.
    pub age_s: f64,
}

/// A specimen tag.
#[derive(Debug, Serialize)]
pub struct TagStatus {
    /// Tag id.
    pub id: u32,
    /// `"support"`, `"midspan"` or none.
    pub role: Option<&'static str>,
}

/// The testing machine.
#[derive(Debug, Serialize)]
pub struct UtmStatus {
    /// A UTM is configured (or the recording has UTM samples).
    pub configured: bool,
    /// `"ok"`, `"down"`, `"waiting"` (configured, no answer yet) or `"none"`.
    pub state: &'static str,
    /// The configured address.
    pub address: Option<String>,
    /// Samples received.
    pub samples: u64,
    /// Times the link went down.
    pub outages: u64,
    /// The last fault reported.
    pub last_error: Option<String>,
    /// The newest sample's load, kN.
    #[serde(rename = "load_kN")]
    pub load_kn: Option<f64>,
    /// The newest sample's stroke, mm.
    pub stroke_mm: Option<f64>,
}

/// The recording.
#[derive(Debug, Serialize)]
pub struct RecordingStatus {
    /// A recording is being written.
    pub active: bool,
    /// Its folder.
    pub dir: Option<String>,
    /// Why it stopped, if it failed (the feed goes on).
    pub failed: Option<String>,
    /// Frames and samples it could not keep up with.
    pub dropped: u64,
}

/// The feed's delivery to the archive (the MQTT publisher's counters, see `sinks::mqtt`).
#[derive(Debug, Serialize)]
pub struct ArchiveStatus {
    /// Connected to the broker now.
    pub connected: bool,
    /// An archive has said what it holds of this run.
    pub heard: bool,
    /// Lines of this run the archive does not hold yet, as it last said (absent before it said).
    pub lag_lines: Option<u64>,
    /// Lines of this run the archive holds.
    pub confirmed_lines: u64,
    /// Lines not confirmed by the archive (in memory or only in the feed file).
    pub unconfirmed_lines: u64,
    /// Lines the archive will never get from this rig.
    pub dropped_lines: u64,
    /// Connections after the first.
    pub reconnects: u64,
}

/// The feed and the pipeline's counters.
#[derive(Debug, Serialize)]
pub struct FeedStatus {
    /// Feed lines so far.
    pub lines: u64,
    /// The newest line's frame set number.
    pub last_seq: Option<u64>,
    /// The newest line's time, ns since the Unix epoch.
    pub last_t_ns: Option<i64>,
    /// Seconds since the newest line was made.
    pub last_line_age_s: Option<f64>,
    /// No line for several frame intervals (live runs).
    pub stale: bool,
    /// Frame sets dropped in front of the solver so far.
    pub dropped_sets: u64,
    /// The newest line's latency, ms.
    pub latency_ms: Option<f64>,
    /// The newest line's net deflection, mm.
    pub net_deflection_mm: Option<f64>,
    /// The newest line's load, kN.
    #[serde(rename = "load_kN")]
    pub load_kn: Option<f64>,
    /// The newest line's RMS specimen reprojection error, px.
    pub reproj_px: Option<f64>,
    /// Specimen tags solved in the newest line.
    pub tags_solved: usize,
}

/// `/events` clients.
#[derive(Debug, Serialize)]
pub struct HttpStatus {
    /// Connected now.
    pub clients: u64,
    /// Events skipped by slow clients so far.
    pub lagged_events: u64,
}

fn age(t: Option<Instant>, now: Instant) -> Option<f64> {
    t.map(|t| (now.duration_since(t).as_secs_f64() * 1e3).round() / 1e3)
}

/// What the parts of the status share: the times, the run's model and the problems found.
struct Ctx<'a> {
    now: Instant,
    uptime_s: f64,
    stale_after: f64,
    live: bool,
    finished: bool,
    run: &'a RunStatus,
    problems: Vec<String>,
}

/// The status now.
pub fn status(view: &LiveView) -> Status {
    let now = Instant::now();
    let cfg = &view.config;
    let max_fps = cfg.cameras.iter().filter_map(|c| c.fps).fold(0.0f64, f64::max);
    let frame_interval_s = (max_fps > 0.0).then(|| 1.0 / max_fps);
    let st = view.lock();
    let mut run = RunStatus::new(cfg, st.recording.dir.clone(), view.started_ns);
    if let Some(l) = &st.feed.last {
        run.observe(l);
    }
    let mut cx = Ctx {
        now,
        uptime_s: now.duration_since(view.started).as_secs_f64(),
        stale_after: (STALE_FRAME_INTERVALS * frame_interval_s.unwrap_or(0.2)).max(MIN_STALE_S),
        live: view.mode == "live" || view.mode == "realtime",
        finished: st.finished,
        run: &run,
        problems: Vec::new(),
    };
    let sources = cfg.cameras.iter().zip(&st.cameras).zip(&run.cameras).map(|((c, s), r)| cx.source(c, s, r)).collect();
    let utm = cx.utm(cfg.utm.is_some() || st.utm.samples > 0, &st.utm);
    let (recording, archive) = (cx.recording(&st.recording), cx.archive(view));
    let feed = cx.feed(&st.feed);
    Status {
        version: run.version,
        mode: view.mode,
        started_ns: run.started_ns,
        uptime_s: (cx.uptime_s * 1e3).round() / 1e3,
        finished: st.finished,
        world_up: cfg.world.up,
        frame_interval_s,
        sources,
        specimen_tags: specimen_tags(&cfg.specimen),
        beam: cfg.specimen.beam.clone(),
        cmod_gauge: cfg.cmod_gauge.clone(),
        rate_windows: cfg.rate_windows.clone(),
        utm,
        recording,
        archive,
        feed,
        http: HttpStatus { clients: view.clients.load(Ordering::Relaxed), lagged_events: view.metrics.http_events_lagged.get() },
        problems: cx.problems,
    }
}

fn specimen_tags(specimen: &tagdeflect_core::rig::SpecimenConfig) -> Vec<TagStatus> {
    specimen
        .tags
        .iter()
        .map(|t| TagStatus {
            id: t.id,
            role: t.role.map(|r| match r {
                TagRole::Support => "support",
                TagRole::Midspan => "midspan",
            }),
        })
        .collect()
}

impl Ctx<'_> {
    /// One camera: its counters, rate, staleness, pose and snapshot; its problems.
    fn source(&mut self, c: &CameraConfig, s: &CameraOnPage, r: &RunCamera) -> SourceStatus {
        let now = self.now;
        let rate = (s.recent.len() >= 2)
            .then(|| {
                let span = s.recent.back()?.duration_since(*s.recent.front()?).as_secs_f64();
                (span > 0.0).then(|| ((s.recent.len() - 1) as f64 / span * 100.0).round() / 100.0)
            })
            .flatten();
        let last_age = age(s.last_frame, now);
        let stale = self.live && !self.finished && last_age.map_or(self.uptime_s > self.stale_after, |a| a > self.stale_after);
        let bumped_recently = s.last_bump.is_some_and(|t| now.duration_since(t).as_secs_f64() < BUMP_SHOWN_S);
        let h = s.health.as_ref();
        let posed = h.is_some_and(|h| h.posed);
        if let Some(why) = &s.lost {
            self.problems.push(format!("camera {} lost: {why}", r.name));
        } else if stale {
            self.problems.push(format!("camera {}: no frame for {:.1} s", r.name, last_age.unwrap_or(self.uptime_s)));
        }
        if bumped_recently {
            self.problems.push(format!("camera {} was bumped and re-posed", r.name));
        }
        if h.is_some() && !posed {
            self.problems.push(format!("camera {} has no pose (too few background tags seen)", r.name));
        }
        SourceStatus {
            name: r.name.clone(),
            source: r.source.clone(),
            width: c.width,
            height: c.height,
            fps: c.fps,
            frames: s.frames,
            frames_dropped: s.frames_dropped,
            frame_rate_hz: rate,
            last_frame_age_s: last_age,
            lost: s.lost.clone(),
            stale,
            posed,
            bumps: s.bumps,
            bumped_recently,
            pose_reproj_px: h.and_then(|h| h.pose_reproj_px),
            arrival_delay_ms: h.and_then(|h| h.arrival_delay_ms),
            background_tags: h.map(|h| h.background_tags),
            specimen_tags: h.map(|h| h.specimen_tags),
            pose: s.pose.map(|p| {
                let c = p.centre();
                PoseStatus { rvec: p.rvec(), tvec_mm: p.translation.into(), centre_mm: c.into() }
            }),
            snapshot: s.snapshot.as_ref().map(|sn| SnapshotStatus {
                url: format!("/camera/{}.jpg?seq={}", r.name, sn.seq),
                seq: sn.seq,
                t_ns: sn.t_ns,
                age_s: age(Some(sn.made), now).unwrap_or(0.0),
            }),
        }
    }

    /// The testing machine's link; its problem.
    fn utm(&mut self, configured: bool, u: &UtmState) -> UtmStatus {
        let state = match (configured, u.up) {
            (false, _) => "none",
            (true, None) => "waiting",
            (true, Some(true)) => "ok",
            (true, Some(false)) => "down",
        };
        if state == "down" {
            self.problems.push(format!("UTM down: {}", u.last_error.as_deref().unwrap_or("no answer")));
        } else if state == "waiting" && self.live && self.uptime_s > self.stale_after {
            self.problems.push("UTM: no answer yet".to_string());
        }
        UtmStatus {
            configured,
            state,
            address: self.run.utm.as_ref().map(|u| u.address.clone()),
            samples: u.samples,
            outages: u.outages,
            last_error: u.last_error.clone(),
            load_kn: u.last_sample.map(|s| s.load_kn),
            stroke_mm: u.last_sample.and_then(|s| s.stroke_mm),
        }
    }

    /// The recording; its problem.
    fn recording(&mut self, r: &RecordingState) -> RecordingStatus {
        let dropped = r.drops.as_ref().map_or(0, |d| d.dropped_frames());
        let failing = r.drops.as_ref().is_some_and(|d| d.state() != tagdeflect_core::feed_file::SinkState::Ok);
        if let Some(e) = &r.failed {
            self.problems.push(format!("recording failed: {e}"));
        } else if failing && !self.finished {
            self.problems.push("recording failing: writes fail, retrying (frames dropped meanwhile are counted)".to_string());
        }
        RecordingStatus {
            active: self.run.recording.is_some() && r.failed.is_none() && !failing && !self.finished,
            dir: self.run.recording.clone(),
            failed: r.failed.clone(),
            dropped,
        }
    }

    /// The feed's delivery to the archive, when published over MQTT; its problem.
    fn archive(&mut self, view: &LiveView) -> Option<ArchiveStatus> {
        #[cfg(feature = "mqtt")]
        let archive = view.mqtt.get().map(|m| {
            use std::sync::atomic::Ordering::Relaxed;
            let heard = m.archive_high.load(Relaxed) > 0 || m.archive_confirmed.load(Relaxed) > 0;
            ArchiveStatus {
                connected: m.connected.load(Relaxed) == 1,
                heard,
                lag_lines: heard.then(|| m.archive_lag.load(Relaxed)),
                confirmed_lines: m.archive_confirmed.load(Relaxed),
                unconfirmed_lines: m.unconfirmed.load(Relaxed),
                dropped_lines: m.dropped.load(Relaxed),
                reconnects: m.reconnects.load(Relaxed),
            }
        });
        #[cfg(not(feature = "mqtt"))]
        let archive: Option<ArchiveStatus> = {
            let _ = view;
            None
        };
        if let Some(a) = &archive {
            if !a.connected && self.uptime_s > 5.0 {
                self.problems.push(format!(
                    "MQTT broker unreachable: {} feed lines wait for the archive (kept, sent on reconnecting)",
                    a.unconfirmed_lines
                ));
            }
        }
        archive
    }

    /// The feed and the newest line; its problem.
    fn feed(&mut self, f: &FeedState) -> FeedStatus {
        let last = f.last.as_ref();
        let line_age = age(f.last_at, self.now);
        let stale = self.live && !self.finished && line_age.map_or(self.uptime_s > 2.0 * self.stale_after, |a| a > self.stale_after);
        if stale {
            self.problems.push(match line_age {
                Some(a) => format!("no feed line for {a:.1} s"),
                None => "no feed line yet".to_string(),
            });
        }
        FeedStatus {
            lines: f.lines,
            last_seq: self.run.last_seq,
            last_t_ns: self.run.last_t_ns,
            last_line_age_s: line_age,
            stale,
            dropped_sets: last.and_then(|l| l.dropped_sets).unwrap_or(0),
            latency_ms: last.and_then(|l| l.latency_ms),
            net_deflection_mm: last.and_then(|l| l.net_deflection_mm),
            load_kn: last.and_then(|l| l.load_kn),
            reproj_px: last.and_then(|l| l.reproj_px),
            tags_solved: last.map_or(0, |l| l.tags.len()),
        }
    }
}
