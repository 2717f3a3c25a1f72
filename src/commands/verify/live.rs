//! `verify --config FILE --live --duration-s S`: the verification recorded on the rig itself,
//! then computed as on a recording. The rig is recorded (`record`'s graph: frames and UTM
//! samples, no measuring while recording) into the certificate's own `recording/` folder for
//! the stated time; the known displacements come from `--reference FILE`, the UTM's stroke
//! (`--reference-from-stroke`), or positions typed in while it records (`--type-positions`).
//!
//! **Typed positions.** Each line typed on standard input is the position (mm, downward) the
//! target was set to and has settled at; it is held from the moment Enter is pressed for
//! `--hold-s` seconds, or until the next line if that comes sooner. The lines become the
//! recording's `reference.jsonl` (two lines per hold: its start and its end), used as any
//! reference file. A line that is not a number is said on stderr and ignored; the end of the
//! input ends the typing (the recording still lasts its stated time).

use std::io::BufRead;
use std::path::{Path, PathBuf};
use std::sync::mpsc;

use anyhow::{Context, Result};
use tagdeflect_core::BadInput;
use tagdeflect_verify::{ReferencePoint, REFERENCE_FILE};

use crate::config::Config;
use crate::graph::entry::{self, LiveOptions};

use super::VerifyArgs;

/// A position typed in, stamped when Enter was pressed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Typed {
    /// When Enter was pressed, ns since the Unix epoch (the feed's clock).
    pub t_ns: i64,
    /// The position typed, mm downward.
    pub position_mm: f64,
}

/// Records the rig of `args.config` for `args.duration_s` into `out/recording` (typing
/// positions meanwhile with `--type-positions`); returns the recording's folder.
pub fn record(args: &VerifyArgs, out: &Path) -> Result<PathBuf> {
    let (path, duration_s) = match (&args.config, args.duration_s) {
        (Some(p), Some(d)) if d.is_finite() && d > 0.0 => (p, d),
        _ => return Err(BadInput::new("verify --live needs --config FILE and --duration-s S (a positive number of seconds)").into()),
    };
    let config = Config::load(path)?;
    let dir = out.join("recording");
    let typed = args.type_positions.then(start_typing);
    let opts = LiveOptions { record: Some(dir.clone()), duration_s: Some(duration_s), record_only: true, ..LiveOptions::default() };
    eprintln!("recording the rig for {duration_s} s into {}", dir.display());
    entry::run(config, opts)?;
    if let Some(rx) = typed {
        let entries: Vec<Typed> = rx.try_iter().collect();
        let points = reference_points(&entries, (args.hold_s * 1e9).round() as i64);
        let text: String =
            points.iter().map(|p| format!("{{\"t_ns\": {}, \"displacement_mm\": {}}}\n", p.t_ns, p.displacement_mm)).collect();
        std::fs::write(dir.join(REFERENCE_FILE), text).with_context(|| format!("writing {}", dir.join(REFERENCE_FILE).display()))?;
    }
    Ok(dir)
}

/// Reads typed positions from standard input on a thread of its own (it ends with the input).
fn start_typing() -> mpsc::Receiver<Typed> {
    let (tx, rx) = mpsc::channel();
    eprintln!("type each position (mm, downward) once the target has settled there, then Enter");
    std::thread::spawn(move || {
        for line in std::io::stdin().lock().lines() {
            let Ok(line) = line else { break };
            let t_ns = tagdeflect_core::clock::now_epoch_ns();
            match line.trim().parse::<f64>() {
                Ok(v) if v.is_finite() => {
                    eprintln!("position {v} mm from now");
                    if tx.send(Typed { t_ns, position_mm: v }).is_err() {
                        break;
                    }
                }
                _ if line.trim().is_empty() => {}
                _ => eprintln!("{:?} is not a position in mm: ignored", line.trim()),
            }
        }
    });
    rx
}

/// The reference's lines of typed positions: each held from its time for `hold_ns`, or to
/// 1 ns before the next position's time if that is sooner.
pub fn reference_points(typed: &[Typed], hold_ns: i64) -> Vec<ReferencePoint> {
    let mut out = Vec::with_capacity(2 * typed.len());
    for (i, t) in typed.iter().enumerate() {
        let end = typed.get(i + 1).map_or(t.t_ns + hold_ns, |next| (t.t_ns + hold_ns).min(next.t_ns - 1)).max(t.t_ns);
        out.push(ReferencePoint { t_ns: t.t_ns, displacement_mm: t.position_mm });
        out.push(ReferencePoint { t_ns: end, displacement_mm: t.position_mm });
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_typed_position_is_held_for_the_hold_or_until_the_next() {
        let s = 1_000_000_000;
        let typed =
            [Typed { t_ns: 0, position_mm: 0.0 }, Typed { t_ns: 4 * s, position_mm: 0.5 }, Typed { t_ns: 20 * s, position_mm: 0.0 }];
        let p = reference_points(&typed, 10 * s);
        let got: Vec<(i64, f64)> = p.iter().map(|p| (p.t_ns, p.displacement_mm)).collect();
        assert_eq!(got, vec![(0, 0.0), (4 * s - 1, 0.0), (4 * s, 0.5), (14 * s, 0.5), (20 * s, 0.0), (30 * s, 0.0)]);
        let holds = tagdeflect_verify::reference::holds(&p);
        assert_eq!(holds.len(), 3);
    }
}
