//! The run's status, one model for the live page (`/api/status`, `http::status`) and the
//! rig's retained MQTT status (`<topic>/status`, `mqtt`): what runs (version, start, the
//! cameras and their sources, the testing machine's address, the recording) and what the
//! newest feed line said (its seq and time, which cameras gave a frame, the UTM's state).
//!
//! Both outputs read [`RunStatus`]: the MQTT message serialises it between its own fields
//! ([`RigStatus`]); the page takes its identity and its newest line from it and adds what only
//! the page knows (frame rates, poses, problems). The JSON of each is its own (SPEC
//! "Endpoints", "Configuration" `[output.mqtt]`).

use serde::Serialize;

use crate::RigInfo;
use tagdeflect_core::feed::FeedLine;

/// The run and its newest line.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RunStatus {
    /// `tagdeflect` version.
    pub version: &'static str,
    /// The run started, ns since the Unix epoch.
    pub started_ns: i64,
    /// The cameras, in config order.
    pub cameras: Vec<RunCamera>,
    /// The testing machine, when one is configured.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub utm: Option<RunUtm>,
    /// The recording's folder, when the run records.
    pub recording: Option<String>,
    /// The newest line's frame-set number.
    pub last_seq: Option<u64>,
    /// The newest line's time, ns since the Unix epoch.
    pub last_t_ns: Option<i64>,
}

/// A camera of the run.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RunCamera {
    /// Name from the config.
    pub name: String,
    /// `source` from the config.
    pub source: String,
    /// Contributed a frame to the last frame set.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub frame: Option<bool>,
}

/// The testing machine's link.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RunUtm {
    /// `utm.address` from the config.
    pub address: String,
    /// The newest line's `utm` (the link's state), when it said.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub state: Option<String>,
}

impl RunStatus {
    /// The status of a run of `rig` started at `started_ns`, recording into `recording`,
    /// before its first line.
    pub fn new(rig: &RigInfo, recording: Option<String>, started_ns: i64) -> RunStatus {
        RunStatus {
            version: env!("CARGO_PKG_VERSION"),
            started_ns,
            cameras: rig.cameras.iter().map(|c| RunCamera { name: c.name.clone(), source: c.source.to_string(), frame: None }).collect(),
            utm: rig.utm.as_ref().map(|a| RunUtm { address: a.to_string(), state: None }),
            recording,
            last_seq: None,
            last_t_ns: None,
        }
    }

    /// Takes in the newest line: its seq and time, the UTM's state, which cameras gave a frame.
    pub fn observe(&mut self, line: &FeedLine) {
        self.last_seq = Some(line.seq);
        self.last_t_ns = Some(line.t_ns);
        if let Some(u) = self.utm.as_mut() {
            u.state = line.utm.clone();
        }
        for c in &line.cameras {
            if let Some(cs) = self.cameras.iter_mut().find(|x| x.name == c.name) {
                cs.frame = Some(c.frame);
            }
        }
    }
}

/// The rig's retained MQTT status message: `online` while it runs, `offline` at the end and
/// as its last will.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RigStatus {
    /// `"online"` or `"offline"`.
    pub state: &'static str,
    /// The rig (`[output.mqtt] rig`).
    pub rig: String,
    /// The MQTT test id of the run.
    pub test: String,
    /// The run and its newest line.
    #[serde(flatten)]
    pub run: RunStatus,
    /// Lines the archive will never get from this rig, so far.
    pub mqtt_dropped: u64,
    /// Lines of this run the archive does not hold yet, as it last said.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub archive_lag: Option<u64>,
}
