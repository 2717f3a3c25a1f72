//! `check`: validates a config (opening its sources) or a recording, and prints each
//! camera's pose and reprojection error from the background tags and the tags it sees.
//!
//! A camera that sees too few background tags to be posed gets a clear warning; when no
//! camera at all can be posed, `check` fails (exit 2): such a rig cannot measure. A camera
//! whose background tags fit its pose worse than [`MAX_POSE_RMS_PX`] — or that sees several
//! background tags and still cannot be posed (they fit no one pose) — is warned of and `check`
//! exits 3 (not fit to measure).

use anyhow::{Context, Result};
use std::fmt::Write as _;
use std::path::Path;

use crate::config::Config;
use crate::config::Recording;
use tagdeflect_core::feed::FeedLine;
use tagdeflect_core::frame::FrameSet;
use tagdeflect_estimate::measure::Measurement;
use tagdeflect_io::sync::FrameSetAssembler;

/// Frame sets of a recording that `check` looks at (poses settle over a few sets).
const CHECK_SETS: usize = 3;

/// Times a recording's frames and UTM samples may carry: 2000-01-01 to 2200-01-01 UTC, in
/// nanoseconds since the Unix epoch.
const PLAUSIBLE_T_NS: std::ops::RangeInclusive<i64> = 946_684_800_000_000_000..=7_258_118_400_000_000_000;

/// `check DIR`.
pub fn check_recording(dir: &Path) -> Result<()> {
    let rec = Recording::open(dir).with_context(|| format!("cannot check {}", dir.display()))?;
    let mut out = String::new();
    writeln!(out, "recording {}", dir.display())?;
    for (i, cam) in rec.config.cameras.iter().enumerate() {
        let n = rec.frames.iter().filter(|f| rec.config.camera_index(&f.camera) == Some(i)).count();
        writeln!(out, "  camera {:<10} {:>5} frames  {}x{}", cam.name, n, cam.width, cam.height)?;
    }
    // SPEC: times are nanoseconds since the Unix epoch; a time outside 2000–2200 is a
    // recording written by something else (a counter, a relative clock) and would give a
    // feed whose times mean nothing.
    if let Some(f) = rec.frames.iter().find(|f| !PLAUSIBLE_T_NS.contains(&f.t_ns)) {
        return Err(tagdeflect_core::BadInput::new(format!(
            "{}: frame {} of camera {} has t_ns {}: not a time between 2000 and 2200 in nanoseconds since the Unix epoch (SPEC)",
            dir.join("frames.jsonl").display(),
            f.seq,
            f.camera,
            f.t_ns
        ))
        .into());
    }
    if let Some(u) = rec.utm.iter().find(|u| !PLAUSIBLE_T_NS.contains(&u.t_ns)) {
        return Err(tagdeflect_core::BadInput::new(format!(
            "{}: a UTM sample has t_ns {}: not a time between 2000 and 2200 in nanoseconds since the Unix epoch (SPEC)",
            dir.join("utm.jsonl").display(),
            u.t_ns
        ))
        .into());
    }
    let (first, last) = (rec.frames.first().map(|f| f.t_ns).unwrap_or(0), rec.frames.last().map(|f| f.t_ns).unwrap_or(0));
    let span_s = (last as i128 - first as i128) as f64 * 1e-9;
    writeln!(out, "  span {span_s:.3} s, {} UTM samples, {} truth lines", rec.utm.len(), rec.truth.len())?;
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

/// `check --config FILE`: validates the config, reads the analog output's device (and with
/// `write_test` writes its safe state), opens every source, grabs one frame set.
pub fn check_config(path: &Path, write_test: bool) -> Result<()> {
    let config = Config::load(path)?;
    println!(
        "config {}: valid ({} cameras, {} background tags, {} specimen tags)",
        path.display(),
        config.cameras.len(),
        config.background.tags.len(),
        config.specimen.tags.len()
    );
    check_verification(&config)?;
    if let Some(w) = config.output.token_file_warning() {
        println!("  warning: {w}");
    }
    if let Some(a) = &config.output.analog {
        check_analog(a, write_test);
    } else if write_test {
        println!("  warning: --write-test: the config has no [output.analog]; nothing written");
    }
    let set = crate::graph::entry::grab_frame_set(&config, std::time::Duration::from_secs(10))?;
    for (i, cam) in config.cameras.iter().enumerate() {
        if !set.frames.iter().any(|f| f.camera == i) {
            println!("  warning: camera {} ({}) delivered no frame within 10 s", cam.name, cam.source);
        }
    }
    // The UTM is read once: a silent address is said here, not at the first test. The config
    // itself is fine, so this is a warning (exit 0), like a camera that sends no frame.
    if let Some(u) = &config.utm {
        check_utm(u);
    }
    report(&config, &[set])
}

/// Reads the analog output's device once (its identity) and, with `write_test`, writes its
/// safe state: the valid line low, then the safe voltage, read back. A device that does not
/// answer is a warning (exit 0), as a silent UTM is.
fn check_analog(a: &tagdeflect_sinks::analog_output::AnalogConfig, write_test: bool) {
    let rt = match tokio::runtime::Builder::new_current_thread().enable_all().build() {
        Ok(rt) => rt,
        Err(e) => return println!("  warning: analog output {}: cannot start the async runtime: {e}", a.address),
    };
    match rt.block_on(tagdeflect_sinks::analog_output::probe(a, write_test)) {
        Ok(p) => {
            println!("analog output {}: reachable; {}", a.address, p.identity);
            match p.write_test {
                Some(w) if w.matches => println!(
                    "  test write: valid line low, then the safe value {:.4} V written and read back ({:?})",
                    w.volts, w.read_back
                ),
                Some(w) => println!(
                    "  warning: test write: {:.4} V written but the register reads back {:?}: the map or word order does not match the device",
                    w.volts, w.read_back
                ),
                None => println!("  nothing written (`check --write-test` writes the valid line low and the safe value)"),
            }
        }
        Err(e) => println!("  warning: {e}"),
    }
}

/// How long `check --config` waits for the UTM's first reading.
const UTM_CHECK_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(5);

/// Reads the UTM once through the daemon's own poller; prints the value and the time to the
/// first reading, or what went wrong.
fn check_utm(u: &tagdeflect_io::utm::UtmConfig) {
    use tagdeflect_io::utm::modbus::{run_poller, UtmEvent};
    if u.address.is_sim() {
        println!("UTM: simulated (served by `run`/`demo` on loopback; nothing to contact)");
        return;
    }
    let rt = match tokio::runtime::Builder::new_current_thread().enable_all().build() {
        Ok(rt) => rt,
        Err(e) => {
            println!("  warning: UTM {}: cannot start the async runtime: {e}", u.address);
            return;
        }
    };
    let outcome = rt.block_on(async {
        let (tx, mut rx) = tokio::sync::mpsc::channel(16);
        let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
        let started = std::time::Instant::now();
        let poller = tokio::spawn(run_poller(u.clone(), tx, stop_rx));
        let mut problem = None;
        let deadline = tokio::time::Instant::now() + UTM_CHECK_TIMEOUT;
        let got = loop {
            match tokio::time::timeout_at(deadline, rx.recv()).await {
                Ok(Some(UtmEvent::Sample(s))) => break Some((s, started.elapsed())),
                Ok(Some(UtmEvent::Down { reason })) => problem = Some(reason),
                Ok(Some(UtmEvent::Up)) => {}
                Ok(None) | Err(_) => break None,
            }
        };
        let _ = stop_tx.send(true);
        poller.abort();
        (got, problem)
    });
    match outcome {
        (Some((s, rtt)), _) => println!(
            "UTM {}: load {:.4} kN{}; first reading after {:.0} ms",
            u.address,
            s.load_kn,
            s.stroke_mm.map(|v| format!(", stroke {v:.4} mm")).unwrap_or_default(),
            rtt.as_secs_f64() * 1e3
        ),
        (None, Some(reason)) => {
            println!("  warning: UTM {}: no reading within {} s: {reason}", u.address, UTM_CHECK_TIMEOUT.as_secs())
        }
        (None, None) => println!("  warning: UTM {}: no answer within {} s", u.address, UTM_CHECK_TIMEOUT.as_secs()),
    }
}

/// The background reprojection RMS a camera's pose may have in `check` (a good calibration
/// gives 0.1–0.5 px; a calibration of another image size gave 11.4 px): above it `check`
/// warns and exits 3.
pub const MAX_POSE_RMS_PX: f64 = 2.0;

/// The side a specimen tag should have in the image at least (docs/rig-setup.md).
const MIN_TAG_PX: f64 = 25.0;

/// Mean side length of a tag's quadrilateral, pixels.
fn side_px(c: &[nalgebra::Point2<f64>; 4]) -> f64 {
    (0..4).map(|k| (c[(k + 1) % 4] - c[k]).norm()).sum::<f64>() / 4.0
}

/// Runs the measurement over the sets and prints the per-camera summary of the last one.
fn report(config: &Config, sets: &[FrameSet]) -> Result<()> {
    if sets.is_empty() {
        return Err(tagdeflect_core::BadInput::new("no frame could be read: nothing to check").into());
    }
    let mut m = Measurement::new(&config.measurement(), false).context("cannot start the tag detector")?;
    let mut last: Option<FeedLine> = None;
    for s in sets {
        last = Some(m.process(s).0);
    }
    let line = last.expect("one set at least");
    let poses = m.camera_poses();
    let seen = m.observed().seen;
    let mut posed = 0;
    let mut poor: Vec<String> = Vec::new();
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
                    Some(e) if e > MAX_POSE_RMS_PX => {
                        println!("  background reprojection RMS: {e:.3} px");
                        println!("  warning: camera {}: the background tags fit its pose to {e:.2} px RMS, above {MAX_POSE_RMS_PX} px: its calibration or the background's world corners are wrong, and it measures wrongly", h.name);
                        poor.push(format!("{} {e:.2} px", h.name));
                    }
                    Some(e) => println!("  background reprojection RMS: {e:.3} px"),
                    None => println!("  background reprojection RMS: n/a (fixed pose from the config)"),
                }
            }
            // Several background tags seen and still no pose: they fit no one pose (a first
            // pose must fit each tag), so the calibration or the world corners are wrong.
            None if h.background_tags >= 2 => {
                println!(
                    "  warning: camera {}: its {} background tags fit no one pose (each must fit within 3 px; so above {MAX_POSE_RMS_PX} px RMS): its calibration or the background's world corners are wrong; it is not posed and measures nothing",
                    h.name, h.background_tags
                );
                poor.push(format!("{} fits no pose", h.name));
            }
            None => println!(
                "  warning: camera {} cannot be posed: it sees {} background tag(s); it needs at least one whole background tag (better several, on two planes) in view",
                h.name, h.background_tags
            ),
        }
        // How large each specimen tag appears: the sub-pixel corners need ~25 px a side.
        if let Some((_, tags)) = seen.iter().find(|(c, _)| *c == i) {
            let mut sizes: Vec<(u32, f64)> = tags.iter().filter(|t| t.specimen).map(|t| (t.id, side_px(&t.corners))).collect();
            sizes.sort_by_key(|s| s.0);
            if !sizes.is_empty() {
                let list: Vec<String> = sizes.iter().map(|(id, px)| format!("{id}: {px:.0}")).collect();
                println!("  specimen tag size (px, mean side): {}", list.join(", "));
                let small: Vec<String> = sizes.iter().filter(|s| s.1 < MIN_TAG_PX).map(|s| s.0.to_string()).collect();
                if !small.is_empty() {
                    println!(
                        "  warning: specimen tag(s) {} appear smaller than {MIN_TAG_PX:.0} px in camera {}: move the camera closer, use a longer lens or larger tags",
                        small.join(", "),
                        h.name
                    );
                }
            }
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
        return Err(tagdeflect_core::BadInput::new("no camera could be posed from the background tags: check the [background] tags' ids, family and world corners against what the cameras see").into());
    }
    if !poor.is_empty() {
        return Err(tagdeflect_core::NotFit::new(format!(
            "background reprojection RMS above {MAX_POSE_RMS_PX} px ({}): recalibrate at the camera's resolution, check the background's world corners",
            poor.join(", ")
        ))
        .into());
    }
    Ok(())
}

/// The verification in force (`[verification]`): its class, date and id, and why it is stale
/// if it is (a warning: the rig still measures; exit 0). A certificate that cannot be read is
/// bad input (exit 2), named.
fn check_verification(config: &Config) -> Result<()> {
    match config.verification_in_force() {
        Ok(None) => println!("verification: none configured ([verification] certificate)"),
        Ok(Some(v)) if v.stale.is_empty() => println!("{}", v.describe()),
        Ok(Some(v)) => println!("  warning: {}", v.describe()),
        Err(e) => return Err(tagdeflect_core::BadInput::new(format!("[verification] {e}")).into()),
    }
    Ok(())
}
