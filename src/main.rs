//! The `tagdeflect` command line (SPEC "Command line"). Only argument parsing, logging
//! set-up and the mapping of errors to exit codes live here.

use anyhow::{Context, Result};
use clap::{Parser, Subcommand};
use std::path::PathBuf;
use std::process::ExitCode;

use tagdeflect::config::Config;
use tagdeflect::pipeline::{self, bench::BenchOptions, live::LiveOptions};
use tagdeflect::recording::FrameFormat;
use tagdeflect::sim::SimParams;
use tagdeflect::sinks::http::HttpOptions;

/// Non-contact deflection measurement of beams in bending with AprilTags.
#[derive(Parser)]
#[command(name = "tagdeflect", version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

// Parsed once per process: the size of the largest variant does not matter.
#[allow(clippy::large_enum_variant)]
#[derive(Subcommand)]
enum Command {
    /// The live daemon: cameras + UTM, feed to the configured outputs, until SIGTERM/SIGINT.
    Run {
        /// The config file.
        #[arg(long)]
        config: PathBuf,
        /// Also save a recording into this new folder.
        #[arg(long)]
        record: Option<PathBuf>,
        /// Stop after this many seconds (default: run until SIGTERM/SIGINT).
        #[arg(long, value_parser = parse_duration_s)]
        duration_s: Option<f64>,
    },
    /// The same pipeline over a recording: feed to stdout, logs to stderr.
    Replay {
        /// The recording folder.
        dir: PathBuf,
        /// Use this config instead of the recording's own (camera sources are ignored).
        #[arg(long)]
        config: Option<PathBuf>,
        /// Feed frames at their recorded pace through the live pipeline (drops counted).
        #[arg(long)]
        realtime: bool,
        /// Force full-frame detection on every frame (no region-of-interest tracking).
        #[arg(long)]
        full_frame: bool,
        /// Serve the live page on ADDR (IP:PORT, port 0 = any free port) while replaying; it
        /// stays up after the recording is consumed until SIGINT/SIGTERM.
        #[arg(long, value_name = "ADDR", value_parser = parse_http_addr)]
        http: Option<std::net::SocketAddr>,
    },
    /// Save raw frames, UTM samples and the config in force as a recording.
    Record {
        /// The config file.
        #[arg(long)]
        config: PathBuf,
        /// The new recording folder.
        #[arg(long)]
        out: PathBuf,
        /// Stop after this many seconds (default: until SIGTERM/SIGINT).
        #[arg(long, value_parser = parse_duration_s)]
        duration_s: Option<f64>,
    },
    /// Write a synthetic recording with ground truth (`truth.jsonl`).
    Simulate {
        /// The new recording folder.
        #[arg(long)]
        out: PathBuf,
        /// How the frames are written (PGM: raw pixels, no decoding cost on replay).
        #[arg(long, value_enum, default_value_t = FrameFormat::Png)]
        frame_format: FrameFormat,
        #[command(flatten)]
        params: SimParams,
    },
    /// Validate a config (and open its sources) or a recording; print each camera's pose,
    /// reprojection error and the tags it sees.
    Check {
        /// A recording folder (or use --config).
        dir: Option<PathBuf>,
        /// A config file.
        #[arg(long)]
        config: Option<PathBuf>,
    },
    /// Replay a recording as fast as possible and print throughput, stage times, latency
    /// and peak memory.
    Bench(BenchOptions),
    /// The live pipeline on the built-in simulated rig (simulated cameras, simulated UTM
    /// over real Modbus TCP on loopback); the feed goes to stdout.
    Demo {
        /// Stop after this many seconds (default: until SIGTERM/SIGINT).
        #[arg(long, value_parser = parse_duration_s)]
        duration_s: Option<f64>,
        /// Use this config instead of the built-in demo rig.
        #[arg(long)]
        config: Option<PathBuf>,
        /// Serve the live page on ADDR (IP:PORT, port 0 = any free port) instead of
        /// 127.0.0.1:8080; the bound address is printed on stderr as http://ADDR/.
        #[arg(long, value_name = "ADDR", value_parser = parse_http_addr, conflicts_with = "no_http")]
        http: Option<std::net::SocketAddr>,
        /// Do not serve the live page.
        #[arg(long)]
        no_http: bool,
    },
    /// Subscribe to the feeds rigs publish over MQTT and keep them in PostgreSQL.
    Archive(tagdeflect::archive::ArchiveOptions),
    /// Measure how many feed lines per second one archive ingests (simulated rigs).
    ArchiveBench(tagdeflect::archive::bench::ArchiveBenchOptions),
    /// Camera intrinsics from views of a target (images or a live camera); writes an OpenCV
    /// FileStorage YAML and reports uncertainties, coverage and outliers.
    Calibrate(tagdeflect::calibrate::CalibrateOptions),
    /// The test report from a feed: report.html, report.json, curve.csv and plots.
    Report(tagdeflect::report::ReportArgs),
    /// The feed as CSV for spreadsheets (the columns of the report's curve.csv).
    Export(tagdeflect::report::ExportArgs),
}

fn parse_http_addr(s: &str) -> Result<std::net::SocketAddr, String> {
    tagdeflect::sinks::http::parse_addr(s)
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    init_logging();
    match run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("tagdeflect: error: {e:#}");
            ExitCode::from(exit_code(&e))
        }
    }
}

/// Exit codes: 0 done; 2 bad input (config, recording, command line — a restart cannot help,
/// so the unit says `RestartPreventExitStatus=2`); 1 a failure of the running daemon that a
/// restart may cure ([`tagdeflect::RuntimeFailure`]).
fn exit_code(e: &anyhow::Error) -> u8 {
    if e.chain().any(|c| c.is::<tagdeflect::RuntimeFailure>()) {
        1
    } else {
        2
    }
}

fn init_logging() {
    use tracing_subscriber::{fmt, EnvFilter};
    // TAGDEFLECT_LOG, else RUST_LOG, else "info" (e.g. TAGDEFLECT_LOG=debug).
    let filter =
        EnvFilter::try_from_env("TAGDEFLECT_LOG").or_else(|_| EnvFilter::try_from_default_env()).unwrap_or_else(|_| EnvFilter::new("info"));
    // Under systemd the journal adds its own timestamps.
    let under_systemd = std::env::var_os("JOURNAL_STREAM").is_some();
    // Colour only on a terminal: files and the journal get plain text.
    let ansi = std::io::IsTerminal::is_terminal(&std::io::stderr()) && std::env::var_os("NO_COLOR").is_none();
    let builder = fmt().with_env_filter(filter).with_writer(std::io::stderr).with_target(false).with_ansi(ansi);
    if under_systemd {
        builder.without_time().init();
    } else {
        builder.init();
    }
}

/// Longest `--duration-s` accepted (about 115 days).
const MAX_DURATION_S: f64 = 1e7;

/// `--duration-s`: a finite number of seconds in (0, 1e7].
fn parse_duration_s(s: &str) -> Result<f64, String> {
    let v: f64 = s.trim().parse().map_err(|_| format!("\"{s}\" is not a number of seconds"))?;
    if v.is_finite() && v > 0.0 && v <= MAX_DURATION_S {
        Ok(v)
    } else {
        Err(format!("{s}: expected more than 0 and at most {MAX_DURATION_S} seconds (about 115 days)"))
    }
}

fn load_config(path: &std::path::Path) -> Result<Config> {
    Ok(Config::load(path)?)
}

fn run(cli: Cli) -> Result<()> {
    match cli.command {
        Command::Run { config, record, duration_s } => {
            let cfg = load_config(&config)?;
            // Without `[output] feed` the feed goes to stdout (SPEC leaves it open; a feed
            // nobody sees helps no one).
            let feed_to_stdout = cfg.output.feed.is_none();
            pipeline::live::run(cfg, LiveOptions { record, duration_s, feed_to_stdout, ..LiveOptions::default() })
        }
        Command::Replay { dir, config, realtime, full_frame, http } => {
            let cfg = config.as_deref().map(load_config).transpose()?;
            let http = http.map(|addr| HttpOptions { addr, required: true });
            if realtime {
                pipeline::live::replay_realtime_http(&dir, cfg, full_frame, http)
            } else if let Some(h) = http {
                tagdeflect::sinks::http::replay_with_page(&dir, cfg, full_frame, h)
            } else {
                pipeline::replay::replay_to_stdout(&dir, cfg, full_frame).map(|_| ())
            }
        }
        Command::Record { config, out, duration_s } => {
            let cfg = load_config(&config)?;
            pipeline::live::run(cfg, LiveOptions { record: Some(out), duration_s, record_only: true, ..LiveOptions::default() })
        }
        Command::Simulate { out, frame_format, params } => {
            let summary =
                tagdeflect::sim::simulate_as(&params, &out, frame_format).with_context(|| format!("simulating into {}", out.display()))?;
            eprintln!(
                "simulated {} frame sets ({} frames, {} dropped, {} UTM samples) into {}; final midspan deflection {:.3} mm",
                summary.frame_sets,
                summary.frames,
                summary.dropped,
                summary.utm_samples,
                summary.dir.display(),
                summary.final_deflection_mm
            );
            Ok(())
        }
        Command::Check { dir, config } => match (dir, config) {
            (Some(dir), None) => pipeline::check::check_recording(&dir),
            (None, Some(cfg)) => pipeline::check::check_config(&cfg),
            _ => anyhow::bail!("check takes either a recording folder or --config FILE"),
        },
        Command::Bench(opts) => pipeline::bench::bench(&opts),
        Command::Demo { duration_s, config, http, no_http } => {
            let cfg = match config {
                Some(p) => load_config(&p)?,
                None => tagdeflect::sources::sim::demo_config(),
            };
            // The page by default on loopback; a taken default port only costs the page.
            let mut cfg = cfg;
            if no_http {
                cfg.output.http = None;
            }
            let http = match (http, no_http) {
                (_, true) => None,
                (Some(addr), false) => Some(HttpOptions { addr, required: true }),
                (None, false) if cfg.output.http.is_some() => None,
                (None, false) => Some(HttpOptions { addr: tagdeflect::sinks::http::DEFAULT_ADDR.parse()?, required: false }),
            };
            pipeline::live::run(cfg, LiveOptions { duration_s, feed_to_stdout: true, http, ..LiveOptions::default() })
        }
        Command::Archive(opts) => tagdeflect::archive::run(opts),
        Command::ArchiveBench(opts) => tagdeflect::archive::bench::run(&opts),
        Command::Calibrate(opts) => tagdeflect::calibrate::run(&opts),
        Command::Report(args) => tagdeflect::report::run_cli(&args).map(|_| ()),
        Command::Export(args) => tagdeflect::report::export_cli(&args),
    }
}
