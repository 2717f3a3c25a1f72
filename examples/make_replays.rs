//! Writes the small simulated recordings committed under `replay/`, and with `--bench`
//! times the renderer instead (one 3 × 1280x960 frame set, and the per-frame cost once the
//! fixed scene is cached, as a live simulated camera pays it).
//!
//! `cargo run --release --example make_replays -- [--bench] [OUT_DIR]` (default `replay/`).
#![allow(unsafe_code)] // getrusage for the peak-memory figure

use std::path::PathBuf;
use std::time::Instant;

use tagdeflect::commands::simulate::simulate;
use tagdeflect_sim::{render_frame_set, SimParams, SimRig};

/// CPU time of this process so far (all threads), seconds.
fn cpu_s() -> f64 {
    // SAFETY: getrusage only writes into the struct we pass.
    // SAFETY: rusage is plain data (all-zero is valid); getrusage writes into it.
    let mut u: libc::rusage = unsafe { std::mem::zeroed() };
    // SAFETY: getrusage writes the struct it is given by valid mutable reference.
    unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut u) };
    let tv = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 * 1e-6;
    tv(u.ru_utime) + tv(u.ru_stime)
}

fn bench(only: Option<(u32, u32, u32)>) {
    let cases = match only {
        Some(c) => vec![c],
        None => vec![(1280u32, 960u32, 8u32), (640, 480, 8), (640, 480, 4)],
    };
    for (w, h, n) in cases {
        let p = SimParams { width: w, height: h, frame_sets: 40, subsamples: n, ..SimParams::default() };
        let rig = SimRig::new(&p).expect("valid parameters");
        let (t, c) = (Instant::now(), cpu_s());
        let first = render_frame_set(&rig, 0);
        let (cold, cold_cpu) = (t.elapsed(), cpu_s() - c);
        assert_eq!(first.len(), 3);
        let n = 10;
        let (t, c) = (Instant::now(), cpu_s());
        for k in 1..=n {
            render_frame_set(&rig, k);
        }
        let warm = t.elapsed() / n as u32;
        let warm_cpu = (cpu_s() - c) / n as f64;
        println!(
            "3 x {w}x{h} (subsamples {}): first frame set {:.0} ms wall / {:.0} ms CPU (rays + fixed scene + beam); then per frame set {:.0} ms wall / {:.0} ms CPU ({:.0} ms CPU per camera frame); {} threads",
            p.subsamples,
            cold.as_secs_f64() * 1e3,
            cold_cpu * 1e3,
            warm.as_secs_f64() * 1e3,
            warm_cpu * 1e3,
            warm_cpu * 1e3 / 3.0,
            rayon::current_num_threads()
        );
    }
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.iter().any(|a| a == "--bench") {
        // Optional: `--bench W H SUBSAMPLES` for one case.
        let nums: Vec<u32> = args.iter().filter_map(|a| a.parse().ok()).collect();
        bench((nums.len() == 3).then(|| (nums[0], nums[1], nums[2])));
        return;
    }
    let root = args
        .iter()
        .find(|a| !a.starts_with("--") && a.parse::<u32>().is_err())
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from("replay"));
    let sets = [
        ("three-cam", SimParams { cameras: 3, width: 640, height: 480, frame_sets: 8, rest_frames: 2, ..SimParams::default() }),
        ("one-cam", SimParams { cameras: 1, width: 800, height: 600, frame_sets: 8, rest_frames: 2, ..SimParams::default() }),
    ];
    for (name, params) in sets {
        let out = root.join(name);
        let t = Instant::now();
        match simulate(&params, &out) {
            Ok(s) => println!(
                "{}: {} frames, {} UTM samples, final deflection {:.3} mm ({:.1} s)",
                out.display(),
                s.frames,
                s.utm_samples,
                s.final_deflection_mm,
                t.elapsed().as_secs_f64()
            ),
            Err(e) => {
                eprintln!("{}: {e}", out.display());
                std::process::exit(2);
            }
        }
    }
}
