//! `bench`: replays a recording as fast as it can and prints throughput, per-stage times,
//! latency and peak memory — as a table, or as JSON with `--json`. With `--full-frame`
//! the same recording is replayed a second time with full-frame detection on every
//! frame, and both runs are printed side by side with the speed-up. `--realtime` plays the
//! recording at its pace through the live graph instead (`realtime.rs`); figures against a
//! synthetic recording's truth (output noise, step response) are `truth.rs`'s; the control
//! signal's dynamics (`--dynamics`, with `--analog ADDR` the DAQ's) are `dynamics.rs`'s.

use anyhow::Result;
use serde::Serialize;
use std::path::PathBuf;

use crate::graph::in_process::{self as replay, ReplayOptions};

mod dynamics;
mod dynamics_valid;
mod memory;
mod realtime;
mod truth;

pub use dynamics::ControlDynamics;
pub use memory::{peak_rss_mb, rss_mb};
pub use realtime::RealtimeFigures;
use realtime::{print_realtime, run_realtime};
pub use truth::StepResponse;
use truth::{net_errors, net_noise, settled, step_response, SETTLE_NS};

/// Options of `tagdeflect bench`.
#[derive(Debug, Clone, clap::Args)]
pub struct BenchOptions {
    /// The recording folder.
    pub dir: PathBuf,
    /// Print JSON instead of a table.
    #[arg(long)]
    pub json: bool,
    /// Also run with full-frame detection on every frame, for comparison (with
    /// `--realtime`: run full-frame instead).
    #[arg(long)]
    pub full_frame: bool,
    /// Replay the recording this many times in a row (a longer steady state).
    #[arg(long, default_value_t = 1)]
    pub repeat: u32,
    /// Instead, play the frames at their recorded pace through the live pipeline (as from
    /// cameras: drop-oldest queue, assembler, solver thread) and report frame sets solved
    /// per second, dropped, and latency frame set complete → feed line.
    #[arg(long)]
    pub realtime: bool,
    /// Run once with each estimator (`[measure] estimator`: temporal, then per set, then the
    /// temporal estimate smoothed as `replay --smooth` does) and print them side by side
    /// (accuracy and net-deflection noise against truth).
    #[arg(long)]
    pub estimators: bool,
    /// The control signal's dynamics (docs/control.md "Dynamics"): DIR played at its pace
    /// as `--realtime` (exposure → register, and with `--analog` exposure → DAC write
    /// acknowledged), the temporal estimate's gain and phase lag at 0.1, 0.5 and 2 Hz and
    /// its step response, and with `--analog` the valid line's timings on a lost camera, a
    /// stalled pipeline and a device fault.
    #[arg(long)]
    pub dynamics: bool,
    /// With `--dynamics`: the analog output's device, IP:PORT (a LabJack T-series map: a
    /// real DAQ, or `tests/fixtures/analog_device.py labjack PORT`); DAC0 and FIO0 are
    /// written.
    #[arg(long, value_name = "ADDR", requires = "dynamics")]
    pub analog: Option<String>,
}

/// Figures of one bench run.
#[derive(Debug, Clone, Serialize)]
pub struct BenchFigures {
    /// "roi-tracking" or "full-frame".
    pub mode: String,
    /// Frame sets processed.
    pub sets: u64,
    /// Frame sets per second of wall time (decode runs in parallel with the rest).
    pub sets_per_s: f64,
    /// Frame sets per second in steady state: wall time from the end of the warm-up (the
    /// first 10 % of each pass, at least one set: the first full-frame searches) to the last
    /// feed line.
    pub steady_sets_per_s: f64,
    /// Frame sets per second the measurement alone sustains (1 / mean of detect + pose +
    /// solve + output time): the rate if decoding cost nothing (it shares the cores).
    pub measure_sets_per_s: f64,
    /// Mean decode time per frame set, ms (reader thread, overlapped).
    pub decode_ms: f64,
    /// Mean detection time per frame set, ms.
    pub detect_ms: f64,
    /// CPU per frame set (all cameras) confirming tracked tags at their predicted place, ms.
    pub tracking_cpu_ms: f64,
    /// Wall time per frame set of window searches and sweep tiles (on the library's
    /// worker threads), ms.
    pub search_ms: f64,
    /// Of that, the retries at the configured resolution of windows whose expected tag the
    /// decimated search missed, ms.
    pub retry_ms: f64,
    /// Wall time per frame set of full-frame searches (likewise), ms.
    pub full_frame_ms: f64,
    /// Mean camera-pose time per frame set, ms.
    pub pose_ms: f64,
    /// Mean solve time per frame set, ms.
    pub solve_ms: f64,
    /// Mean feed-line output time per frame set, ms.
    pub output_ms: f64,
    /// Processing latency (frame set taken by the solver → feed line made) in steady state
    /// (after the first tenth of the sets), median, ms.
    pub latency_p50_ms: f64,
    /// The same, 99th percentile, ms.
    pub latency_p99_ms: f64,
    /// Processing time of the first frame set (full-frame searches of every camera), ms.
    pub first_set_ms: f64,
    /// Peak resident memory of the process so far, MB.
    pub peak_rss_mb: f64,
    /// Resident memory after the first frame set, MB.
    pub rss_first_set_mb: f64,
    /// Resident memory at the end, MB (equal to the above when memory stays flat).
    pub rss_end_mb: f64,
    /// Frame sets dropped (always 0 here: bench never drops; see `--realtime`).
    pub dropped_sets: u64,
    /// Full-frame searches run.
    pub full_frame_searches: u64,
    /// Window searches run.
    pub window_searches: u64,
    /// Of those, windows searched again at the configured resolution (a tag expected there
    /// missed by the decimated search).
    pub window_retries: u64,
    /// Whole-frame searches run in the background.
    pub background_searches: u64,
    /// Time the solver waited for background searches, ms per frame set.
    pub background_wait_ms: f64,
    /// Tag views confirmed at their predicted place without a search.
    pub tracked_tags: u64,
    /// Of those, fitted on the pixels selected in an earlier frame (the tag had barely moved).
    pub reused_band_tags: u64,
    /// Standard deviation of the net deflection's error against truth, mm (synthetic
    /// recordings with support and midspan tags): the output noise (at rest: the noise).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub net_noise_mm: Option<f64>,
    /// The same over the lines from [`SETTLE_NS`] after the first line with a net deflection
    /// on: the estimator's steady state, without its start (a filter started on its first set
    /// knows no rate yet and averages over the sets it has seen).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub net_noise_settled_mm: Option<f64>,
    /// The response to a step of the net deflection (recordings whose truth holds still, steps
    /// once and holds again: `simulate --rest-frames R --hold-frames H` with no set left for a
    /// ramp).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub step: Option<StepResponse>,
    /// Mean of `net_deflection_sigma_mm` over the lines, mm.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub net_sigma_mm: Option<f64>,
    /// Accuracy against the recording's ground truth (synthetic recordings only).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub accuracy: Option<crate::accuracy::Accuracy>,
}

/// Runs the bench and prints the figures.
pub fn bench(opts: &BenchOptions) -> Result<()> {
    let rec = replay::open(&opts.dir, None)?;
    if opts.dynamics {
        return dynamics::bench_dynamics(&rec, opts);
    }
    if opts.realtime {
        let r = run_realtime(&rec, opts.full_frame, None)?;
        if opts.json {
            println!("{}", serde_json::to_string(&r)?);
        } else {
            print_realtime(&opts.dir, &r);
        }
        return Ok(());
    }
    preload(&rec);
    let mut runs = Vec::new();
    if opts.estimators {
        use tagdeflect_estimate::temporal::Estimator;
        for (e, label) in [(Estimator::Temporal, "temporal"), (Estimator::PerSet, "per-set")] {
            let mut r = rec.clone();
            r.config.measure.estimator = e;
            let mut f = run_once(&r, false, opts.repeat, None)?;
            f.mode = label.into();
            runs.push(f);
        }
        // The temporal estimate smoothed as `replay --smooth` does.
        let mut r = rec.clone();
        r.config.measure.estimator = Estimator::Temporal;
        let mut f = run_once(&r, false, opts.repeat, Some(tagdeflect_estimate::smooth::DEFAULT_LAG_SETS))?;
        f.mode = "temporal+smoothed".into();
        runs.push(f);
    } else {
        runs.push(run_once(&rec, false, opts.repeat, None)?);
    }
    if opts.full_frame {
        runs.push(run_once(&rec, true, opts.repeat, None)?);
    }
    if opts.json {
        let ratio = |f: fn(&BenchFigures) -> f64| (runs.len() == 2 && runs[1].mode == "full-frame").then(|| f(&runs[0]) / f(&runs[1]));
        println!(
            "{}",
            serde_json::json!({
                "recording": opts.dir,
                "runs": runs,
                "speedup_vs_full_frame": ratio(|f| f.sets_per_s),
                "steady_speedup_vs_full_frame": ratio(|f| f.steady_sets_per_s),
                "measure_speedup_vs_full_frame": ratio(|f| f.measure_sets_per_s),
            })
        );
    } else {
        print_table(&opts.dir, &runs);
    }
    Ok(())
}

fn run_once(rec: &crate::config::Recording, full_frame: bool, repeat: u32, smooth_lag_sets: Option<usize>) -> Result<BenchFigures> {
    let mut detect = 0.0;
    let mut parts = tagdeflect_estimate::measure::DetectParts::default();
    let mut pose = 0.0;
    let mut solve = 0.0;
    let mut output = 0.0;
    let mut latencies = Vec::new();
    let mut first_set_s = 0.0;
    let mut rss_first_mb = 0.0;
    let mut sets = 0;
    let mut wall = 0.0;
    let mut decode = 0.0;
    let mut stats = Default::default();
    let mut sink = Vec::with_capacity(4096);
    let mut lines = Vec::new();
    let (mut steady_sets, mut steady_s) = (0u64, 0.0);
    for pass in 0..repeat.max(1) {
        let mut stamps = Vec::new();
        let mut k = 0usize;
        let warm_sets = (rec.frames.len() / rec.config.cameras.len().max(1) / 10).max(1);
        let summary = replay::replay(rec, ReplayOptions { full_frame, progress: false, smooth_lag_sets }, |line, t, _queued| {
            let t0 = std::time::Instant::now();
            stamps.push(t0);
            sink.clear();
            serde_json::to_writer(&mut sink, line).expect("serialise");
            std::hint::black_box(&sink);
            let out_s = t0.elapsed().as_secs_f64();
            output += out_s;
            detect += t.detect;
            parts.add(&t.detect_parts);
            pose += t.pose;
            solve += t.solve;
            // Processing latency (set taken by the solver → line made) in steady state; in
            // an as-fast-as-possible replay the time a set waits behind the reader says
            // nothing about a live run (see `--realtime` for that).
            let processing = t.detect + t.pose + t.solve + out_s;
            if k == 0 && pass == 0 {
                first_set_s = processing;
                rss_first_mb = rss_mb();
            }
            if k >= warm_sets {
                latencies.push(processing);
            }
            k += 1;
            if pass == 0 && !rec.truth.is_empty() {
                lines.push(line.clone());
            }
        })?;
        let warm = (stamps.len() / 10).max(1);
        if stamps.len() > warm + 1 {
            steady_sets += (stamps.len() - 1 - warm) as u64;
            steady_s += stamps[stamps.len() - 1].duration_since(stamps[warm]).as_secs_f64();
        }
        sets += summary.sets;
        wall += summary.wall_s;
        decode += summary.decode_s;
        stats = summary.stats;
    }
    latencies.sort_by(f64::total_cmp);
    let n = sets.max(1) as f64;
    let stats: tagdeflect_estimate::measure::MeasureStats = stats;
    let errors = net_errors(rec, &lines);
    Ok(BenchFigures {
        mode: if full_frame { "full-frame" } else { "roi-tracking" }.into(),
        sets,
        sets_per_s: sets as f64 / wall.max(1e-9),
        steady_sets_per_s: if steady_s > 0.0 { steady_sets as f64 / steady_s } else { 0.0 },
        measure_sets_per_s: n / (detect + pose + solve + output).max(1e-9),
        decode_ms: decode / n * 1e3,
        detect_ms: detect / n * 1e3,
        tracking_cpu_ms: parts.tracking / n * 1e3,
        search_ms: parts.search / n * 1e3,
        retry_ms: parts.retry / n * 1e3,
        full_frame_ms: parts.full_frame / n * 1e3,
        pose_ms: pose / n * 1e3,
        solve_ms: solve / n * 1e3,
        output_ms: output / n * 1e3,
        latency_p50_ms: percentile(&latencies, 0.5) * 1e3,
        latency_p99_ms: percentile(&latencies, 0.99) * 1e3,
        first_set_ms: first_set_s * 1e3,
        peak_rss_mb: peak_rss_mb(),
        rss_first_set_mb: rss_first_mb,
        rss_end_mb: rss_mb(),
        dropped_sets: 0,
        full_frame_searches: stats.full_frame_searches,
        window_searches: stats.window_searches,
        window_retries: stats.window_retries,
        background_searches: stats.background_searches,
        background_wait_ms: parts.background_wait / n * 1e3,
        tracked_tags: stats.tracked_tags,
        reused_band_tags: stats.reused_band_tags,
        net_noise_mm: net_noise(&errors),
        net_noise_settled_mm: net_noise(&net_errors(rec, settled(&lines, SETTLE_NS))),
        step: step_response(&errors),
        net_sigma_mm: {
            let s: Vec<f64> = lines.iter().filter_map(|l| l.net_deflection_sigma_mm).collect();
            (!s.is_empty()).then(|| s.iter().sum::<f64>() / s.len() as f64)
        },
        accuracy: (!rec.truth.is_empty()).then(|| crate::accuracy::evaluate(&rec.config, &rec.truth, &lines)),
    })
}

/// Reads every frame file once before the timed runs, so they measure the pipeline and
/// not the disk (a 3 × 1080p PGM stream is ~190 MB/s; a recording larger than the free
/// memory is read from disk during the run anyway — keep bench recordings small, or on a
/// RAM disk).
fn preload(rec: &crate::config::Recording) {
    let t = std::time::Instant::now();
    let mut bytes = 0u64;
    let mut buf = Vec::new();
    for f in &rec.frames {
        use std::io::Read;
        buf.clear();
        if let Ok(mut file) = std::fs::File::open(rec.dir.join(&f.file)) {
            bytes += file.read_to_end(&mut buf).unwrap_or(0) as u64;
        }
    }
    tracing::info!(
        "{} frames ({:.0} MB) read into the page cache in {:.1} s before timing",
        rec.frames.len(),
        bytes as f64 / 1e6,
        t.elapsed().as_secs_f64()
    );
}

/// The `p` quantile (0..1, nearest rank) of sorted values; 0 for none.
pub(super) fn percentile(sorted: &[f64], p: f64) -> f64 {
    sorted.get(((sorted.len() as f64 - 1.0) * p).round() as usize).copied().unwrap_or(0.0)
}

/// One row of the bench table: its label and how to format a run's value.
type Row = (&'static str, fn(&BenchFigures) -> String);

fn print_table(dir: &std::path::Path, runs: &[BenchFigures]) {
    println!("bench {} ({} cores)", dir.display(), std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1));
    let rows: [Row; 32] = [
        ("frame sets", |f| f.sets.to_string()),
        ("frame sets/s", |f| format!("{:.1}", f.sets_per_s)),
        ("steady frame sets/s", |f| format!("{:.1}", f.steady_sets_per_s)),
        ("measure-only frame sets/s", |f| format!("{:.1}", f.measure_sets_per_s)),
        ("decode ms/set (overlapped)", |f| format!("{:.2}", f.decode_ms)),
        ("detect ms/set", |f| format!("{:.2}", f.detect_ms)),
        ("  tracked tags CPU ms/set", |f| format!("{:.2}", f.tracking_cpu_ms)),
        ("  windows+sweep ms/set", |f| format!("{:.2}", f.search_ms)),
        ("    of which retries ms/set", |f| format!("{:.2}", f.retry_ms)),
        ("  full-frame ms/set", |f| format!("{:.2}", f.full_frame_ms)),
        ("pose ms/set", |f| format!("{:.3}", f.pose_ms)),
        ("solve ms/set", |f| format!("{:.3}", f.solve_ms)),
        ("output ms/set", |f| format!("{:.3}", f.output_ms)),
        ("latency p50 ms (steady)", |f| format!("{:.1}", f.latency_p50_ms)),
        ("latency p99 ms (steady)", |f| format!("{:.1}", f.latency_p99_ms)),
        ("first frame set ms", |f| format!("{:.1}", f.first_set_ms)),
        ("peak RSS MB", |f| format!("{:.1}", f.peak_rss_mb)),
        ("RSS MB after first set", |f| format!("{:.1}", f.rss_first_set_mb)),
        ("RSS MB at the end", |f| format!("{:.1}", f.rss_end_mb)),
        ("dropped sets", |f| f.dropped_sets.to_string()),
        ("full-frame searches", |f| f.full_frame_searches.to_string()),
        ("window searches", |f| f.window_searches.to_string()),
        ("  of which retries", |f| f.window_retries.to_string()),
        ("background searches", |f| f.background_searches.to_string()),
        ("  waited for, ms/set", |f| format!("{:.2}", f.background_wait_ms)),
        ("tags tracked without search", |f| f.tracked_tags.to_string()),
        ("  on reused pixels", |f| f.reused_band_tags.to_string()),
        ("net deflection noise µm", |f| f.net_noise_mm.map_or("-".into(), |v| format!("{:.2}", v * 1e3))),
        ("  after the first second µm", |f| f.net_noise_settled_mm.map_or("-".into(), |v| format!("{:.2}", v * 1e3))),
        ("net deflection mean σ µm", |f| f.net_sigma_mm.map_or("-".into(), |v| format!("{:.2}", v * 1e3))),
        ("step: errors after, µm", |f| {
            f.step.as_ref().map_or("-".into(), |s| s.errors_after_um.iter().map(|e| format!("{e:.0}")).collect::<Vec<_>>().join(" "))
        }),
        ("step: sets to within 10 %", |f| {
            f.step.as_ref().map_or("-".into(), |s| s.sets_to_10_percent.map_or("never".into(), |k| k.to_string()))
        }),
    ];
    print!("{:<28}", "");
    for r in runs {
        print!("{:>16}", r.mode);
    }
    println!();
    for (name, f) in rows {
        print!("{name:<28}");
        for r in runs {
            print!("{:>16}", f(r));
        }
        println!();
    }
    if runs.len() == 2 && runs[1].mode == "full-frame" {
        println!("{:<28}{:>16.1}x", "speed-up vs full-frame", runs[0].sets_per_s / runs[1].sets_per_s);
        println!("{:<28}{:>16.1}x", "speed-up, steady state", runs[0].steady_sets_per_s / runs[1].steady_sets_per_s);
        println!("{:<28}{:>16.1}x", "speed-up, measure only", runs[0].measure_sets_per_s / runs[1].measure_sets_per_s);
    }
    for r in runs {
        if let Some(a) = &r.accuracy {
            println!("accuracy ({}): {a}", r.mode);
        }
    }
}
