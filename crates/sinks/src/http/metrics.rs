//! `/metrics`: the Prometheus (OpenMetrics text) exposition, with the `prometheus-client`
//! crate. Every metric is an atomic updated where the event happens (solver, assembler,
//! UTM forwarder, recorder); a scrape only reads them.

use prometheus_client::encoding::EncodeLabelSet;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::{exponential_buckets, Histogram};
use prometheus_client::registry::Registry;
use std::sync::atomic::AtomicU64;

/// The label of per-camera metrics.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct CameraLabel {
    /// The camera's name from the config.
    pub camera: String,
}

/// Every metric of the daemon (names under the `tagdeflect_` prefix; see the README).
pub struct Metrics {
    registry: Registry,
    /// Frames delivered by each camera's source (live and `replay --realtime`).
    pub frames: Family<CameraLabel, Counter>,
    /// Frames a source reported lost before they reached the pipeline (driver drops,
    /// incomplete buffers, a full channel).
    pub frames_dropped: Family<CameraLabel, Counter>,
    /// Frames of each camera in solved frame sets.
    pub frames_solved: Family<CameraLabel, Counter>,
    /// Camera lost events (a source stopped and is being reopened).
    pub camera_lost: Family<CameraLabel, Counter>,
    /// Bumps detected per camera (camera found moved and re-posed).
    pub bumps: Family<CameraLabel, Counter>,
    /// RMS reprojection error of the background corners with the pose in use, px.
    pub pose_reproj_px: Family<CameraLabel, Gauge<f64, AtomicU64>>,
    /// 1 when the camera has a pose.
    pub posed: Family<CameraLabel, Gauge>,
    /// How late the camera's frames steadily arrive, as the frame sets learned it (the feed's
    /// `cameras[].arrival_delay_ms`), seconds; no series while it is learned or the camera is
    /// silent.
    pub arrival_delay_s: Family<CameraLabel, Gauge<f64, AtomicU64>>,
    /// Frame sets solved (feed lines made).
    pub sets_solved: Counter,
    /// Frame sets dropped by the drop-oldest queue in front of the solver.
    pub sets_dropped: Counter,
    /// Frame set complete → feed line, seconds.
    pub latency: Histogram,
    /// Net deflection of the last feed line, mm.
    pub net_deflection_mm: Gauge<f64, AtomicU64>,
    /// Load of the last feed line, kN.
    pub load_kn: Gauge<f64, AtomicU64>,
    /// 1 while the UTM answers (0 when down or not configured).
    pub utm_up: Gauge,
    /// UTM outages (the link went down).
    pub utm_outages: Counter,
    /// UTM poll errors seen by the daemon (one per outage today: the poller reports a fault
    /// once per outage; a poller that reports each failed retry feeds the same counter).
    pub utm_poll_errors: Counter,
    /// UTM samples received.
    pub utm_samples: Counter,
    /// 1 while a recording is being written.
    pub recorder_active: Gauge,
    /// 1 once the recording failed (the feed goes on).
    pub recorder_failed: Gauge,
    /// Frames and UTM samples the recorder could not keep up with.
    pub recorder_dropped: Gauge,
    /// Clients connected to `/events`.
    pub http_clients: Gauge,
    /// Events lost by slow `/events` clients (they skip ahead; the solver never waits).
    pub http_events_lagged: Counter,
    /// Connections and requests the server refused (connection cap, `Host` check).
    pub http_refused: Counter,
    /// 1 while connected to the MQTT broker (`[output.mqtt]`).
    pub mqtt_connected: Gauge,
    /// Lines of this run the archive does not hold yet, as it last said.
    pub archive_lag: Gauge,
    /// Lines of this run the archive holds, as it last said.
    pub archive_confirmed: Gauge,
    /// Lines not confirmed by the archive (in memory or only in the feed file).
    pub mqtt_unconfirmed: Gauge,
    /// Lines the archive will never get from this rig.
    pub mqtt_dropped: Gauge,
}

impl Default for Metrics {
    fn default() -> Self {
        Self::new()
    }
}

impl Metrics {
    /// All metrics registered, at zero.
    pub fn new() -> Self {
        let mut registry = Registry::with_prefix("tagdeflect");
        let m = Metrics {
            frames: Family::default(),
            frames_dropped: Family::default(),
            frames_solved: Family::default(),
            camera_lost: Family::default(),
            bumps: Family::default(),
            pose_reproj_px: Family::default(),
            posed: Family::default(),
            arrival_delay_s: Family::default(),
            sets_solved: Counter::default(),
            sets_dropped: Counter::default(),
            // 1 ms … ~16 s.
            latency: Histogram::new(exponential_buckets(0.001, 2.0, 15)),
            net_deflection_mm: Gauge::default(),
            load_kn: Gauge::default(),
            utm_up: Gauge::default(),
            utm_outages: Counter::default(),
            utm_poll_errors: Counter::default(),
            utm_samples: Counter::default(),
            recorder_active: Gauge::default(),
            recorder_failed: Gauge::default(),
            recorder_dropped: Gauge::default(),
            http_clients: Gauge::default(),
            http_events_lagged: Counter::default(),
            http_refused: Counter::default(),
            mqtt_connected: Gauge::default(),
            archive_lag: Gauge::default(),
            archive_confirmed: Gauge::default(),
            mqtt_unconfirmed: Gauge::default(),
            mqtt_dropped: Gauge::default(),
            registry: Registry::default(),
        };
        registry.register("camera_frames", "Frames delivered by the camera's source", m.frames.clone());
        registry.register("camera_frames_dropped", "Frames the camera's source lost before the pipeline", m.frames_dropped.clone());
        registry.register("camera_frames_solved", "Frames of the camera in solved frame sets", m.frames_solved.clone());
        registry.register("camera_lost", "Times the camera was lost (and reopened)", m.camera_lost.clone());
        registry.register("camera_bumps", "Times the camera was found moved and re-posed", m.bumps.clone());
        registry.register(
            "camera_pose_reprojection_px",
            "RMS reprojection error of the background tags with the pose in use, pixels",
            m.pose_reproj_px.clone(),
        );
        registry.register("camera_posed", "1 when the camera has a pose", m.posed.clone());
        registry.register(
            "camera_arrival_delay_seconds",
            "How late the camera's frames steadily arrive (learned by the frame sets' wait), seconds",
            m.arrival_delay_s.clone(),
        );
        registry.register("frame_sets_solved", "Frame sets solved (feed lines)", m.sets_solved.clone());
        registry.register("frame_sets_dropped", "Frame sets dropped in front of the solver (it fell behind)", m.sets_dropped.clone());
        registry.register("feed_latency_seconds", "Frame set complete to feed line, seconds", m.latency.clone());
        registry.register("net_deflection_mm", "Net deflection of the last feed line, mm", m.net_deflection_mm.clone());
        registry.register("load_kn", "Load of the last feed line, kN", m.load_kn.clone());
        registry.register("utm_up", "1 while the testing machine answers", m.utm_up.clone());
        registry.register("utm_outages", "Times the testing machine's link went down", m.utm_outages.clone());
        registry.register("utm_poll_errors", "Failed polls of the testing machine reported to the pipeline", m.utm_poll_errors.clone());
        registry.register("utm_samples", "Samples read from the testing machine", m.utm_samples.clone());
        registry.register("recorder_active", "1 while a recording is written", m.recorder_active.clone());
        registry.register("recorder_failed", "1 once the recording failed (the feed goes on)", m.recorder_failed.clone());
        registry.register("recorder_dropped", "Frames and UTM samples the recorder could not keep up with", m.recorder_dropped.clone());
        registry.register("http_event_clients", "Clients connected to /events", m.http_clients.clone());
        registry.register("http_events_lagged", "Events skipped by slow /events clients", m.http_events_lagged.clone());
        registry.register("http_refused", "Connections and requests refused (connection cap, Host check)", m.http_refused.clone());
        registry.register("mqtt_connected", "1 while connected to the MQTT broker", m.mqtt_connected.clone());
        registry.register("archive_lag_lines", "Lines of this run the archive does not hold yet, as it last said", m.archive_lag.clone());
        registry.register("archive_confirmed_lines", "Lines of this run the archive holds, as it last said", m.archive_confirmed.clone());
        registry.register(
            "mqtt_unconfirmed_lines",
            "Feed lines the archive has not confirmed (in memory or in the feed file)",
            m.mqtt_unconfirmed.clone(),
        );
        registry.register("mqtt_dropped_lines", "Feed lines the archive will never get from this rig", m.mqtt_dropped.clone());
        Metrics { registry, ..m }
    }

    /// The OpenMetrics text exposition of every metric.
    pub fn encode(&self) -> String {
        let mut out = String::new();
        prometheus_client::encoding::text::encode(&mut out, &self.registry).expect("writing to a String cannot fail");
        out
    }
}

/// The label of camera `name`.
pub fn cam(name: &str) -> CameraLabel {
    CameraLabel { camera: name.to_string() }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exposition_names_the_metrics() {
        let m = Metrics::new();
        m.frames.get_or_create(&cam("left")).inc();
        m.latency.observe(0.012);
        m.pose_reproj_px.get_or_create(&cam("left")).set(0.25);
        m.arrival_delay_s.get_or_create(&cam("left")).set(0.125);
        let text = m.encode();
        assert!(text.contains("tagdeflect_camera_frames_total{camera=\"left\"} 1"), "{text}");
        assert!(text.contains("tagdeflect_feed_latency_seconds_bucket"), "{text}");
        assert!(text.contains("tagdeflect_camera_pose_reprojection_px{camera=\"left\"} 0.25"), "{text}");
        assert!(text.contains("tagdeflect_camera_arrival_delay_seconds{camera=\"left\"} 0.125"), "{text}");
        assert!(text.trim_end().ends_with("# EOF"), "{text}");
    }
}
