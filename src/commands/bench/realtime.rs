//! `bench --realtime`: a recording played at its recorded pace through the live graph, its
//! lines timed as they reach an in-memory feed.

use anyhow::Result;
use serde::Serialize;

use tagdeflect_sinks::analog_output::{AnalogConfig, AnalogOutput};

use super::{peak_rss_mb, percentile};

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
    /// Exposure → the analog output's DAC write acknowledged by the device, steady state,
    /// median, ms (`bench --dynamics --analog`; counted as the register's).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub exposure_to_dac_p50_ms: Option<f64>,
    /// The same, 99th percentile, ms.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub exposure_to_dac_p99_ms: Option<f64>,
    /// The same, worst, ms.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub exposure_to_dac_max_ms: Option<f64>,
    /// Values timed from exposure to the DAC write acknowledged (steady state).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub exposure_to_dac_values: Option<usize>,
    /// Values written to the DAC / superseded by a newer one before their write.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub dac_written_superseded: Option<(u64, u64)>,
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

/// An in-memory feed sink shared with the bench; it notes when each line was written and
/// gives each line to the analog output when there is one.
#[derive(Clone, Default)]
struct SharedBuf(
    std::sync::Arc<std::sync::Mutex<Vec<u8>>>,
    std::sync::Arc<std::sync::Mutex<Vec<std::time::Instant>>>,
    Option<std::sync::Arc<AnalogOutput>>,
);

impl std::io::Write for SharedBuf {
    fn write(&mut self, b: &[u8]) -> std::io::Result<usize> {
        let mut text = self.0.lock().expect("feed buffer");
        let start = text.len();
        text.extend_from_slice(b);
        if let Some(analog) = &self.2 {
            // The lines completed by this write (a line's start is after the last newline before it).
            let from = text[..start].iter().rposition(|&c| c == b'\n').map_or(0, |i| i + 1);
            let end = text.iter().rposition(|&c| c == b'\n').map_or(0, |i| i + 1);
            if end > from {
                for l in text[from..end].split(|&c| c == b'\n').filter(|l| !l.is_empty()) {
                    if let Ok(line) = serde_json::from_slice::<tagdeflect_core::feed::FeedLine>(l) {
                        analog.take_line(&line);
                    }
                }
            }
        }
        drop(text);
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

/// Plays `rec` at its pace through the live graph; with `analog`, the lines also go to that
/// analog output (its DAC writes are timed from exposure as the register is).
pub(super) fn run_realtime(rec: &crate::config::Recording, full_frame: bool, analog: Option<AnalogConfig>) -> Result<RealtimeFigures> {
    let analog = analog.map(|c| AnalogOutput::start(&c).map(std::sync::Arc::new)).transpose()?;
    let buf = SharedBuf(Default::default(), Default::default(), analog.clone());
    let sink = tagdeflect_core::feed_file::FeedWriter::from_writer("bench", Box::new(buf.clone()));
    // The control output serves the run too (its register is updated on the sinks' thread
    // right after the feed line is written).
    let mut paced = rec.clone();
    paced.config.output.control = Some(tagdeflect_sinks::control_output::ControlConfig::on("127.0.0.1:0"));
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
    let playhead = tagdeflect_io::sources::playback::last_playhead_start().filter(|p| *p >= started).unwrap_or(started);
    let mut exposure: Vec<f64> = lines
        .iter()
        .zip(&stamps)
        .skip(warm)
        .map(|(l, at)| (at.saturating_duration_since(playhead).as_secs_f64() - (l.t_ns - t0) as f64 * 1e-9) * 1e3)
        .collect();
    exposure.sort_by(f64::total_cmp);
    let dac = analog.map(|a| {
        let status = a.status();
        let t_of: std::collections::HashMap<u64, i64> = lines.iter().skip(warm).map(|l| (l.seq, l.t_ns)).collect();
        let mut ms: Vec<f64> = status
            .acknowledged()
            .iter()
            .filter_map(|(seq, at)| {
                t_of.get(seq).map(|t| (at.saturating_duration_since(playhead).as_secs_f64() - (t - t0) as f64 * 1e-9) * 1e3)
            })
            .collect();
        ms.sort_by(f64::total_cmp);
        let max = ms.last().copied().unwrap_or(f64::NAN);
        (percentile(&ms, 0.5), percentile(&ms, 0.99), (status.values_written, status.superseded), max, ms.len())
    });
    Ok(RealtimeFigures {
        exposure_to_dac_p50_ms: dac.map(|d| d.0),
        exposure_to_dac_p99_ms: dac.map(|d| d.1),
        dac_written_superseded: dac.map(|d| d.2),
        exposure_to_dac_max_ms: dac.map(|d| d.3),
        exposure_to_dac_values: dac.map(|d| d.4),
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

pub(super) fn print_realtime(dir: &std::path::Path, r: &RealtimeFigures) {
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
    if let (Some(p50), Some(p99)) = (r.exposure_to_dac_p50_ms, r.exposure_to_dac_p99_ms) {
        println!("{:<36}{:>12.1}", "exposure → DAC acknowledged p50 ms", p50);
        println!("{:<36}{:>12.1}", "exposure → DAC acknowledged p99 ms", p99);
    }
    if let (Some(max), Some(n)) = (r.exposure_to_dac_max_ms, r.exposure_to_dac_values) {
        println!("{:<36}{:>12.1}", "exposure → DAC acknowledged max ms", max);
        println!("{:<36}{:>12}", "  values timed (steady state)", n);
    }
    if let Some((w, s)) = r.dac_written_superseded {
        println!("{:<36}{:>12}", "DAC values written / superseded", format!("{w} / {s}"));
    }
    println!("{:<36}{:>12.1}", "peak RSS MB", r.peak_rss_mb);
    println!("{:<36}{:>12.3}", "first solved set after s", r.first_solved_s);
    println!("{:<36}{:>12}", "dropped after the first solved set", r.dropped_after_first_solved);
    println!("{:<36}{:>12}", "dropped after the first second", r.dropped_after_1s);
}
