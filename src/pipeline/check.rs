//! `check`: validates a config (opening its sources) or a recording, and prints each
//! camera's pose and reprojection error from the background tags and the tags it sees.
//!
//! A camera that sees too few background tags to be posed gets a clear warning; when no
//! camera at all can be posed, `check` fails (exit 2): such a rig cannot measure.

use anyhow::{Context, Result};
use std::fmt::Write as _;
use std::path::Path;

use crate::config::Config;
use crate::feed::FeedLine;
use crate::frame::FrameSet;
use crate::pipeline::measure::Measurement;
use crate::recording::Recording;
use crate::sync::FrameSetAssembler;

/// Frame sets of a recording that `check` looks at (poses settle over a few sets).
const CHECK_SETS: usize = 3;

/// `check DIR`.
pub fn check_recording(dir: &Path) -> Result<()> {
    let rec = Recording::open(dir).with_context(|| format!("cannot check {}", dir.display()))?;
    let mut out = String::new();
    writeln!(out, "recording {}", dir.display())?;
    for (i, cam) in rec.config.cameras.iter().enumerate() {
        let n = rec.frames.iter().filter(|f| rec.config.camera_index(&f.camera) == Some(i)).count();
        writeln!(out, "  camera {:<10} {:>5} frames  {}x{}", cam.name, n, cam.width, cam.height)?;
    }
    let (first, last) = (rec.frames.first().map(|f| f.t_ns).unwrap_or(0), rec.frames.last().map(|f| f.t_ns).unwrap_or(0));
    writeln!(out, "  span {:.3} s, {} UTM samples, {} truth lines", (last - first) as f64 * 1e-9, rec.utm.len(), rec.truth.len())?;
    for s in &rec.skipped_lines {
        writeln!(out, "  warning: {s}")?;
    }
    let mut assembler = FrameSetAssembler::new(rec.config.cameras.len(), rec.config.sync.tolerance_ms);
    let mut sets = Vec::new();
    for read in rec.frames() {
        if sets.len() >= CHECK_SETS {
            break;
        }
        match read.frame {
            Ok(frame) => sets.extend(assembler.push(frame)),
            Err(e) => writeln!(out, "  warning: {e}")?,
        }
    }
    if sets.len() < CHECK_SETS {
        sets.extend(assembler.flush());
    }
    print!("{out}");
    report(&rec.config, &sets)
}

/// `check --config FILE`: validates the config, opens every source, grabs one frame set.
pub fn check_config(path: &Path) -> Result<()> {
    let config = Config::load(path)?;
    println!(
        "config {}: valid ({} cameras, {} background tags, {} specimen tags)",
        path.display(),
        config.cameras.len(),
        config.background.tags.len(),
        config.specimen.tags.len()
    );
    let set = crate::graph::run::grab_frame_set(&config, std::time::Duration::from_secs(10))?;
    for (i, cam) in config.cameras.iter().enumerate() {
        if !set.frames.iter().any(|f| f.camera == i) {
            println!("  warning: camera {} ({}) delivered no frame within 10 s", cam.name, cam.source);
        }
    }
    report(&config, &[set])
}

/// Runs the measurement over the sets and prints the per-camera summary of the last one.
fn report(config: &Config, sets: &[FrameSet]) -> Result<()> {
    if sets.is_empty() {
        return Err(crate::BadInput::new("no frame could be read: nothing to check").into());
    }
    let mut m = Measurement::new(&config.measurement(), false).context("cannot start the tag detector")?;
    let mut last: Option<FeedLine> = None;
    for s in sets {
        last = Some(m.process(s).0);
    }
    let line = last.expect("one set at least");
    let poses = m.camera_poses();
    let mut posed = 0;
    for (i, h) in line.cameras.iter().enumerate() {
        println!("camera {}:", h.name);
        println!(
            "  background tags seen: {} of {}; specimen tags seen: {} of {}",
            h.background_tags,
            config.background.tags.len(),
            h.specimen_tags,
            config.specimen.tags.len()
        );
        match poses[i] {
            Some(p) => {
                posed += 1;
                let r = p.rvec();
                let c = p.centre();
                println!("  pose: rvec [{:.5}, {:.5}, {:.5}]  tvec_mm [{:.2}, {:.2}, {:.2}]", r[0], r[1], r[2], p.translation.x, p.translation.y, p.translation.z);
                println!("  camera centre (world, mm): [{:.1}, {:.1}, {:.1}]", c.x, c.y, c.z);
                match h.pose_reproj_px {
                    Some(e) => println!("  background reprojection RMS: {e:.3} px"),
                    None => println!("  background reprojection RMS: n/a (fixed pose from the config)"),
                }
            }
            None => println!(
                "  warning: camera {} cannot be posed: it sees {} background tag(s); it needs at least one whole background tag (better several, on two planes) in view",
                h.name, h.background_tags
            ),
        }
    }
    println!("specimen tags solved: {} of {}", line.tags.len(), config.specimen.tags.len());
    for t in &line.tags {
        println!(
            "  tag {:>3}: pos_mm [{:.3}, {:.3}, {:.3}]  views {}  reproj {:.3} px",
            t.id,
            t.pos_mm[0],
            t.pos_mm[1],
            t.pos_mm[2],
            t.views,
            t.reproj_px.unwrap_or(f64::NAN)
        );
    }
    if posed == 0 {
        return Err(crate::BadInput::new("no camera could be posed from the background tags: check the [background] tags' ids, family and world corners against what the cameras see").into());
    }
    Ok(())
}
