//! `bench`: replays a recording as fast as it can and prints throughput, per-stage times,
//! latency and peak memory — as a table, or as JSON with `--json`. With `--full-frame`
//! the same recording is replayed a second time with full-frame detection on every
//! frame, and both runs are printed side by side with the speed-up.

use anyhow::Result;
use serde::Serialize;
use std::path::PathBuf;

use crate::graph::in_process::{self as replay, ReplayOptions};

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
}

/// Figures of a paced run of a recording through the live pipeline (`bench --realtime`).
#[derive(Debug, Clone, Serialize)]
pub struct RealtimeFigures {
    /// "roi-tracking" or "full-frame".
    pub mode: String,
    /// Frame sets in the recording (frames of its busiest camera).
    pub recorded_sets: u64,
    /// Length of the recording, s.
    pub recorded_s: f64,
    /// Feed lines made (frame sets solved).
    pub solved_sets: u64,
    /// Frame sets solved per second of recording in steady state (after the first tenth).
    pub steady_solved_per_s: f64,
    /// Frame sets the drop-oldest queue in front of the solver dropped.
    pub dropped_sets: u64,
    /// Of those, dropped in steady state (after the first tenth of the lines; the first
    /// frame set's full-frame searches take most of a second).
    pub steady_dropped_sets: u64,
    /// Latency frame set complete → feed line in steady state, median, ms.
    pub latency_p50_ms: f64,
    /// The same, 99th percentile, ms.
    pub latency_p99_ms: f64,
    /// The same, worst, ms.
    pub latency_max_ms: f64,
    /// Exposure (the frame set's time) → feed line written and control register updated,
    /// steady state, median, ms (an upper bound: counted from before the sources open).
    pub exposure_to_register_p50_ms: f64,
    /// The same, 99th percentile, ms.
    pub exposure_to_register_p99_ms: f64,
    /// Peak resident memory, MB.
    pub peak_rss_mb: f64,
    /// From the first frame played (sources open) to the first feed line with a solved
    /// tag, s (that set's time in the recording plus its latency).
    pub first_solved_s: f64,
    /// Frame sets dropped after the first solved one.
    pub dropped_after_first_solved: u64,
    /// Frame sets dropped after the first second of the recording.
    pub dropped_after_1s: u64,
}

/// An in-memory feed sink shared with the bench; it notes when each line was written.
#[derive(Clone, Default)]
struct SharedBuf(std::sync::Arc<std::sync::Mutex<Vec<u8>>>, std::sync::Arc<std::sync::Mutex<Vec<std::time::Instant>>>);

impl std::io::Write for SharedBuf {
    fn write(&mut self, b: &[u8]) -> std::io::Result<usize> {
        self.0.lock().expect("feed buffer").extend_from_slice(b);
        let lines = b.iter().filter(|&&c| c == b'\n').count();
        if lines > 0 {
            let now = std::time::Instant::now();
            self.1.lock().expect("feed stamps").extend(std::iter::repeat_n(now, lines));
        }
        Ok(b.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

fn run_realtime(rec: &crate::config::Recording, full_frame: bool) -> Result<RealtimeFigures> {
    let buf = SharedBuf::default();
    let sink = tagdeflect_core::feed_file::FeedWriter::from_writer("bench", Box::new(buf.clone()));
    // The control output serves the run too (its register is updated on the sinks' thread
    // right after the feed line is written).
    let mut paced = rec.clone();
    paced.config.output.control = Some(tagdeflect_sinks::control::ControlConfig::on("127.0.0.1:0"));
    let started = std::time::Instant::now();
    crate::graph::entry::replay_paced(paced, full_frame, vec![sink])?;
    let stamps = std::mem::take(&mut *buf.1.lock().expect("feed stamps"));
    let text = String::from_utf8(std::mem::take(&mut *buf.0.lock().expect("feed buffer")))?;
    let lines: Vec<tagdeflect_core::feed::FeedLine> = text.lines().map(serde_json::from_str).collect::<Result<_, _>>()?;
    let mut per_camera = std::collections::HashMap::new();
    for f in &rec.frames {
        *per_camera.entry(&f.camera).or_insert(0u64) += 1;
    }
    let (t0, t1) = (rec.frames.iter().map(|f| f.t_ns).min().unwrap_or(0), rec.frames.iter().map(|f| f.t_ns).max().unwrap_or(0));
    let warm = lines.len() / 10;
    let steady = &lines[warm.min(lines.len())..];
    let steady_solved_per_s = match (steady.first(), steady.last()) {
        (Some(a), Some(b)) if b.t_ns > a.t_ns => (steady.len() - 1) as f64 / ((b.t_ns - a.t_ns) as f64 * 1e-9),
        _ => 0.0,
    };
    let first_solved = lines.iter().find(|l| !l.tags.is_empty());
    let total_dropped = lines.last().and_then(|l| l.dropped_sets).unwrap_or(0);
    let dropped_since = |l: Option<&tagdeflect_core::feed::FeedLine>| l.map_or(0, |l| total_dropped - l.dropped_sets.unwrap_or(0));
    let mut lat: Vec<f64> = steady.iter().filter_map(|l| l.latency_ms).collect();
    lat.sort_by(f64::total_cmp);
    // Exposure → line written (and register updated): when the line was written after the
    // playhead's start, less when its frames were due (their recorded time since the first
    // frame: a recording's pauses are short, none capped here).
    let playhead = tagdeflect_io::sources::recording::last_playhead_start().filter(|p| *p >= started).unwrap_or(started);
    let mut exposure: Vec<f64> = lines
        .iter()
        .zip(&stamps)
        .skip(warm)
        .map(|(l, at)| (at.saturating_duration_since(playhead).as_secs_f64() - (l.t_ns - t0) as f64 * 1e-9) * 1e3)
        .collect();
    exposure.sort_by(f64::total_cmp);
    Ok(RealtimeFigures {
        mode: if full_frame { "full-frame" } else { "roi-tracking" }.into(),
        recorded_sets: per_camera.values().copied().max().unwrap_or(0),
        recorded_s: (t1 - t0) as f64 * 1e-9,
        solved_sets: lines.len() as u64,
        steady_solved_per_s,
        dropped_sets: lines.last().and_then(|l| l.dropped_sets).unwrap_or(0),
        steady_dropped_sets: match (steady.first(), steady.last()) {
            (Some(a), Some(b)) => b.dropped_sets.unwrap_or(0) - a.dropped_sets.unwrap_or(0),
            _ => 0,
        },
        latency_p50_ms: percentile(&lat, 0.5),
        latency_p99_ms: percentile(&lat, 0.99),
        latency_max_ms: lat.last().copied().unwrap_or(0.0),
        exposure_to_register_p50_ms: percentile(&exposure, 0.5),
        exposure_to_register_p99_ms: percentile(&exposure, 0.99),
        peak_rss_mb: peak_rss_mb(),
        first_solved_s: first_solved.map_or(f64::NAN, |l| (l.t_ns - t0) as f64 * 1e-9 + l.latency_ms.unwrap_or(0.0) * 1e-3),
        dropped_after_first_solved: dropped_since(first_solved),
        dropped_after_1s: dropped_since(lines.iter().find(|l| l.t_ns >= t0 + 1_000_000_000)),
    })
}

fn print_realtime(dir: &std::path::Path, r: &RealtimeFigures) {
    println!(
        "bench --realtime {} ({} cores, {})",
        dir.display(),
        std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1),
        r.mode
    );
    println!("{:<36}{:>12}", "frame sets recorded", r.recorded_sets);
    println!("{:<36}{:>12.1}", "recording length s", r.recorded_s);
    println!("{:<36}{:>12.1}", "recorded frame sets/s", r.recorded_sets as f64 / r.recorded_s.max(1e-9));
    println!("{:<36}{:>12}", "frame sets solved", r.solved_sets);
    println!("{:<36}{:>12.1}", "solved frame sets/s (steady)", r.steady_solved_per_s);
    println!("{:<36}{:>12}", "dropped sets (solver queue)", r.dropped_sets);
    println!("{:<36}{:>12}", "  of which in steady state", r.steady_dropped_sets);
    println!("{:<36}{:>12.1}", "latency p50 ms (steady)", r.latency_p50_ms);
    println!("{:<36}{:>12.1}", "latency p99 ms (steady)", r.latency_p99_ms);
    println!("{:<36}{:>12.1}", "latency max ms (steady)", r.latency_max_ms);
    println!("{:<36}{:>12.1}", "exposure → register p50 ms", r.exposure_to_register_p50_ms);
    println!("{:<36}{:>12.1}", "exposure → register p99 ms", r.exposure_to_register_p99_ms);
    println!("{:<36}{:>12.1}", "peak RSS MB", r.peak_rss_mb);
    println!("{:<36}{:>12.3}", "first solved set after s", r.first_solved_s);
    println!("{:<36}{:>12}", "dropped after the first solved set", r.dropped_after_first_solved);
    println!("{:<36}{:>12}", "dropped after the first second", r.dropped_after_1s);
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

/// How the net deflection followed a step of its truth (`BenchFigures::step`).
#[derive(Debug, Clone, Serialize)]
pub struct StepResponse {
    /// The step of the true net deflection, mm.
    pub step_mm: f64,
    /// Errors of the first four lines after the step, µm, less the mean error of the lines
    /// before it (the zero's own offset): `[0]` is the first set after the step, half a frame
    /// period after it.
    pub errors_after_um: Vec<f64>,
    /// Lines after the step before the error stays within 10 % of the step for five lines in
    /// a row (0: from the first set after it on, i.e. within half a frame period of the step);
    /// `None` if it never does.
    pub sets_to_10_percent: Option<usize>,
}

/// Runs the bench and prints the figures.
pub fn bench(opts: &BenchOptions) -> Result<()> {
    let rec = replay::open(&opts.dir, None)?;
    if opts.realtime {
        let r = run_realtime(&rec, opts.full_frame)?;
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

/// The true net deflection and the feed's error against it, line by line (the first line
/// with a net deflection is the reference, as the feed's displacements), mm.
fn net_errors(rec: &crate::config::Recording, lines: &[tagdeflect_core::feed::FeedLine]) -> Vec<(f64, f64)> {
    use crate::config::TagRole;
    let up = nalgebra::Vector3::from(rec.config.world.up).normalize();
    let mut first = std::collections::HashMap::new();
    let mut out = Vec::new();
    for l in lines {
        let tr = crate::accuracy::truth_at(&rec.truth, l.t_ns);
        let mut down = std::collections::HashMap::new();
        for t in &l.tags {
            if let Some(p) = tr.get(&t.id) {
                let p0 = *first.entry(t.id).or_insert(*p);
                down.insert(t.id, -(p - p0).dot(&up));
            }
        }
        let Some(net) = l.net_deflection_mm else { continue };
        let mean = |role: TagRole| {
            let v: Vec<f64> =
                l.tags.iter().filter(|t| rec.config.role_of(t.id) == Some(role)).filter_map(|t| down.get(&t.id)).copied().collect();
            (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
        };
        if let (Some(m), Some(s)) = (mean(TagRole::Midspan), mean(TagRole::Support)) {
            out.push((m - s, net - (m - s)));
        }
    }
    out
}

/// Time after the first line with a net deflection from which the output noise counts as
/// settled (`net_noise_settled_mm`), ns.
const SETTLE_NS: i64 = 1_000_000_000;

/// The lines from `after_ns` past the first line with a net deflection on (none when there
/// is no such line).
fn settled(lines: &[tagdeflect_core::feed::FeedLine], after_ns: i64) -> &[tagdeflect_core::feed::FeedLine] {
    let Some(t0) = lines.iter().find(|l| l.net_deflection_mm.is_some()).map(|l| l.t_ns) else { return &[] };
    let from = lines.iter().position(|l| l.t_ns >= t0 + after_ns).unwrap_or(lines.len());
    &lines[from..]
}

/// Standard deviation of the net deflection's error against truth (`net_errors`), mm.
fn net_noise(errors: &[(f64, f64)]) -> Option<f64> {
    if errors.len() < 2 {
        return None;
    }
    let n = errors.len() as f64;
    let mean = errors.iter().map(|e| e.1).sum::<f64>() / n;
    Some((errors.iter().map(|e| (e.1 - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt())
}

/// The response to a step of the true net deflection (`net_errors`): one change between
/// consecutive lines at least 20× every other, with at least three lines before it and five
/// after; `None` for any other course (a ramp, a recording at rest).
fn step_response(errors: &[(f64, f64)]) -> Option<StepResponse> {
    let changes: Vec<f64> = errors.windows(2).map(|w| w[1].0 - w[0].0).collect();
    let (k, step) = changes.iter().copied().enumerate().max_by(|a, b| a.1.abs().total_cmp(&b.1.abs()))?;
    let at = k + 1;
    let alone = changes.iter().enumerate().all(|(j, c)| j == k || c.abs() * 20.0 <= step.abs());
    if step == 0.0 || !alone || at < 3 || errors.len() < at + 5 {
        return None;
    }
    let offset = errors[..at].iter().map(|e| e.1).sum::<f64>() / at as f64;
    let after: Vec<f64> = errors[at..].iter().map(|e| e.1 - offset).collect();
    let within = |e: &f64| e.abs() <= 0.1 * step.abs();
    Some(StepResponse {
        step_mm: step,
        errors_after_um: after.iter().take(4).map(|e| e * 1e3).collect(),
        sets_to_10_percent: (0..=after.len() - 5).find(|&j| after[j..j + 5].iter().all(within)),
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
fn percentile(sorted: &[f64], p: f64) -> f64 {
    sorted.get(((sorted.len() as f64 - 1.0) * p).round() as usize).copied().unwrap_or(0.0)
}

/// One row of the bench table: its label and how to format a run's value.
type Row = (&'static str, fn(&BenchFigures) -> String);

fn print_table(dir: &std::path::Path, runs: &[BenchFigures]) {
    println!("bench {} ({} cores)", dir.display(), std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1));
    let rows: [Row; 30] = [
        ("frame sets", |f| f.sets.to_string()),
        ("frame sets/s", |f| format!("{:.1}", f.sets_per_s)),
        ("steady frame sets/s", |f| format!("{:.1}", f.steady_sets_per_s)),
        ("measure-only frame sets/s", |f| format!("{:.1}", f.measure_sets_per_s)),
        ("decode ms/set (overlapped)", |f| format!("{:.2}", f.decode_ms)),
        ("detect ms/set", |f| format!("{:.2}", f.detect_ms)),
        ("  tracked tags CPU ms/set", |f| format!("{:.2}", f.tracking_cpu_ms)),
        ("  windows+sweep ms/set", |f| format!("{:.2}", f.search_ms)),
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

/// Peak resident set size of this process (VmHWM), MB; 0 where /proc is unavailable.
pub fn peak_rss_mb() -> f64 {
    proc_status_kb("VmHWM:") / 1024.0
}

/// Current resident set size (VmRSS), MB.
pub fn rss_mb() -> f64 {
    proc_status_kb("VmRSS:") / 1024.0
}

fn proc_status_kb(key: &str) -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| s.lines().find(|l| l.starts_with(key)).and_then(|l| l.split_whitespace().nth(1)).and_then(|v| v.parse::<f64>().ok()))
        .unwrap_or(0.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_step_is_found_and_its_settling_counted() {
        // Truth 0 for 6 lines, then 0.05 mm; the error has an offset of 2 µm, the estimate
        // lags by 30 % and 12 % of the step in the first two lines after it.
        let truth = |k: usize| if k < 6 { 0.0 } else { 0.05 };
        let err = |k: usize| 0.002 + [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -0.015, -0.006, 0.001, -0.001, 0.0, 0.0, 0.0][k];
        let errors: Vec<(f64, f64)> = (0..13).map(|k| (truth(k), err(k))).collect();
        let s = step_response(&errors).unwrap();
        assert!((s.step_mm - 0.05).abs() < 1e-12);
        assert_eq!(s.errors_after_um.iter().map(|e| e.round() as i64).collect::<Vec<_>>(), [-15, -6, 1, -1]);
        assert_eq!(s.sets_to_10_percent, Some(2));
        // A ramp is no step; nor is a recording at rest.
        let ramp: Vec<(f64, f64)> = (0..13).map(|k| (k as f64 * 0.01, 0.0)).collect();
        assert!(step_response(&ramp).is_none());
        let rest: Vec<(f64, f64)> = (0..13).map(|k| (0.0, k as f64 * 1e-4)).collect();
        assert!(step_response(&rest).is_none());
        assert!(net_noise(&rest).unwrap() > 0.0);
        // Never within 10 %: said.
        let slow: Vec<(f64, f64)> = (0..13).map(|k| (truth(k), if k < 6 { 0.0 } else { -0.01 })).collect();
        assert_eq!(step_response(&slow).unwrap().sets_to_10_percent, None);
    }

    #[test]
    fn the_settled_noise_counts_from_a_second_after_the_first_net_deflection() {
        let line = |t_ns: i64, net: Option<f64>| tagdeflect_core::feed::FeedLine { t_ns, net_deflection_mm: net, ..Default::default() };
        // No net deflection on the first two lines; the first one at 0.5 s.
        let lines: Vec<_> = (0..10).map(|k| line(k * 250_000_000, (k >= 2).then_some(0.0))).collect();
        let s = settled(&lines, SETTLE_NS);
        assert_eq!(s.first().map(|l| l.t_ns), Some(1_500_000_000));
        assert_eq!(s.len(), 4);
        assert!(settled(&lines, 10 * SETTLE_NS).is_empty());
        assert!(settled(&lines[..2], 0).is_empty());
    }
}
