//! `simulate`: renders the rig's frame sets and writes a SPEC recording with ground truth.
//!
//! Besides the SPEC files (`tagdeflect.toml`, `frames.jsonl`, the PNG frames, `utm.jsonl`,
//! `truth.jsonl`), a simulated recording holds [`SIM_TRUTH_FILE`] (`sim_truth.jsonl`): one
//! [`SimTruthLine`](super::SimTruthLine) per frame set with the set number and nominal
//! time, the midspan deflection of the neutral axis, the true net deflection (feed sense),
//! load and stroke, every camera's true pose (`rvec`, `tvec_mm`, `x_cam = R x_world + t`),
//! whether it has been bumped, its frame's capture time (absent when dropped), motion blur
//! and hidden tag, and every specimen tag's pose (centre, rotation vector tag → world,
//! the four world corners in SPEC order, role).

use std::io::Write;
use std::path::{Path, PathBuf};

use rand::seq::SliceRandom;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

use tagdeflect_io::recording::{FrameEntry, FrameFormat, RecordedConfig, RecordingError, RecordingWriter, TruthLine, TruthTag};

use super::{SimError, SimParams, SimRig};

/// Name of the extra truth file of a simulated recording.
pub const SIM_TRUTH_FILE: &str = "sim_truth.jsonl";

/// What [`simulate`] wrote.
#[derive(Debug, Clone, PartialEq)]
pub struct SimSummary {
    /// The recording folder.
    pub dir: PathBuf,
    /// Frame sets simulated.
    pub frame_sets: u64,
    /// Frames written (all cameras).
    pub frames: u64,
    /// Frames dropped (absent from the recording).
    pub dropped: u64,
    /// UTM samples written.
    pub utm_samples: u64,
    /// Midspan deflection of the last frame set, mm.
    pub final_deflection_mm: f64,
}

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> SimError + '_ {
    move |source| SimError::Io { path: path.to_path_buf(), source }
}

/// Writes a simulated recording of `params` into `out` (which must not hold a recording),
/// frames as PNG; `config` is the rig's config as the binary builds it (written as the
/// recording's `tagdeflect.toml`).
///
/// Frames are rendered at their own (jittered) capture times; `truth.jsonl` holds one
/// line per frame set at the set's nominal time; dropped frames are simply absent.
pub fn simulate(params: &SimParams, out: &Path, config: &impl RecordedConfig) -> Result<SimSummary, SimError> {
    simulate_as(params, out, FrameFormat::Png, config)
}

/// [`simulate`] with the frames written in `format`.
pub fn simulate_as(params: &SimParams, out: &Path, format: FrameFormat, config: &impl RecordedConfig) -> Result<SimSummary, SimError> {
    let rig = SimRig::new(params)?;
    let mut writer = RecordingWriter::create(out, config)?;
    let names: Vec<String> = config.cameras().iter().map(|c| c.name.clone()).collect();
    let truth_path = out.join(SIM_TRUTH_FILE);
    let mut sim_truth = std::io::BufWriter::new(std::fs::File::create(&truth_path).map_err(io_err(&truth_path))?);
    let mut entries = Vec::new();
    let mut seqs = vec![0u64; names.len()];
    let mut dropped = 0;
    for k in 0..params.frame_sets as u64 {
        // The cameras of one set render one after another (each on both cores); their
        // frames are then encoded in parallel.
        let mut images = Vec::new();
        for (c, name) in names.iter().enumerate() {
            match rig.frame_time_ns(c, k) {
                None => dropped += 1,
                Some(t) => images.push((c, name, t, rig.render(c, t))),
            }
        }
        let encoded: Vec<_> = images.par_iter().map(|(c, name, t, img)| (*c, *name, *t, format.encode(img))).collect();
        for (c, name, t, bytes) in encoded {
            let file = format!("{name}/{:06}.{}", seqs[c], format.extension());
            let path = out.join(&file);
            let bytes = bytes.map_err(|m| RecordingError::BadImage { path: path.clone(), message: m.to_string() })?;
            std::fs::write(&path, bytes).map_err(io_err(&path))?;
            entries.push(FrameEntry { camera: name.clone(), seq: seqs[c], t_ns: t, file });
            seqs[c] += 1;
        }
        let line = rig.truth_line(k);
        writer.write_truth(&TruthLine {
            t_ns: line.t_ns,
            tags: line.tags.iter().map(|t| TruthTag { id: t.id, center_mm: t.center_mm }).collect(),
        })?;
        serde_json::to_writer(&mut sim_truth, &line).map_err(|e| SimError::Io { path: truth_path.clone(), source: e.into() })?;
        sim_truth.write_all(b"\n").map_err(io_err(&truth_path))?;
    }
    if params.shuffle {
        let mut rng = ChaCha8Rng::seed_from_u64(params.seed ^ 0x5u64);
        entries.shuffle(&mut rng);
    }
    for e in &entries {
        writer.write_frame_entry(e)?;
    }
    let utm = rig.utm_samples();
    for s in &utm {
        writer.write_utm(s)?;
    }
    sim_truth.flush().map_err(io_err(&truth_path))?;
    write_verify_steps(&rig, out)?;
    writer.finish()?;
    let last = rig.set_time_ns(params.frame_sets as u64 - 1);
    Ok(SimSummary {
        dir: out.to_path_buf(),
        frame_sets: params.frame_sets as u64,
        frames: entries.len() as u64,
        dropped,
        utm_samples: utm.len() as u64,
        final_deflection_mm: rig.midspan_deflection(last),
    })
}

/// A verification run's steps: SPEC's reference file ([`tagdeflect_verify::REFERENCE_FILE`],
/// one `{"t_ns", "displacement_mm"}` line per frame set, the position the stage held at that
/// set's time) and the step plan with its windows ([`tagdeflect_verify::VERIFY_STEPS_FILE`]);
/// nothing for a test.
fn write_verify_steps(rig: &SimRig, out: &Path) -> Result<(), SimError> {
    let windows = rig.verify_windows();
    if windows.is_empty() {
        return Ok(());
    }
    let mut plan = tagdeflect_verify::StepPlan::from_positions(&windows.iter().map(|w| w.0).collect::<Vec<_>>());
    for (s, &(_, a, b)) in plan.steps.iter_mut().zip(&windows) {
        (s.start_ns, s.end_ns) = (Some(a), Some(b));
    }
    let path = out.join(tagdeflect_verify::VERIFY_STEPS_FILE);
    let text = serde_json::to_string_pretty(&plan).map_err(|e| SimError::Io { path: path.clone(), source: e.into() })?;
    std::fs::write(&path, text + "\n").map_err(io_err(&path))?;
    let mut reference = String::new();
    for k in 0..rig.params.frame_sets as u64 {
        let t_ns = rig.set_time_ns(k);
        if let Some(&(p, _, _)) = windows.iter().find(|&&(_, a, b)| t_ns >= a && t_ns < b) {
            reference += &format!("{{\"t_ns\":{t_ns},\"displacement_mm\":{p}}}\n");
        }
    }
    let path = out.join(tagdeflect_verify::REFERENCE_FILE);
    std::fs::write(&path, reference).map_err(io_err(&path))
}

/// Renders frame set `k` of every camera in parallel threads (used by benchmarks): returns
/// each camera's `(t_ns, image)` or `None` for a dropped frame.
pub fn render_frame_set(rig: &SimRig, k: u64) -> Vec<Option<(i64, tagdeflect_core::frame::GrayImage)>> {
    (0..rig.camera_count()).into_par_iter().map(|c| rig.frame_time_ns(c, k).map(|t| (t, rig.render(c, t)))).collect()
}
