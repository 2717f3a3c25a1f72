//! The `tagdeflect` command line (SPEC "Command line"). Only argument parsing, logging
//! set-up and the mapping of errors to exit codes live here.

use anyhow::Result;
use clap::{Parser, Subcommand};
use std::path::PathBuf;
use std::process::ExitCode;

use tagdeflect::commands::{self, bench::BenchOptions};
use tagdeflect::config::Config;
use tagdeflect::graph::entry::{self as live, LiveOptions};
use tagdeflect::graph::page::{self, http_options, parse_http_addr};
#[cfg(feature = "sim")]
use tagdeflect_io::recording::FrameFormat;
#[cfg(feature = "sim")]
use tagdeflect_sim::SimParams;

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
        /// Keep each test in its own folder here (as `[output] tests`; enables the control API).
        #[arg(long, value_name = "DIR")]
        tests: Option<PathBuf>,
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
        /// Smooth every line with the frame sets after it (a fixed-lag Rauch–Tung–Striebel
        /// smoother over the temporal estimate; lines say `"smoothed": true`). Not with
        /// --realtime, which is causal like a live run.
        #[arg(long, conflicts_with = "realtime")]
        smooth: bool,
        /// Frame sets the smoother looks ahead (with --smooth).
        #[arg(long, value_name = "SETS", default_value_t = tagdeflect_estimate::smooth::DEFAULT_LAG_SETS as u64, value_parser = clap::value_parser!(u64).range(1..=10_000))]
        smooth_lag_sets: u64,
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
    #[cfg(feature = "sim")]
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
    /// List the cameras this machine sees: V4L2 devices by their stable /dev/v4l/by-id paths
    /// with formats, sizes and frame rates, and GigE/USB3 Vision devices (Aravis) by id.
    Cameras {
        /// Also list Aravis's in-process fake camera (a demonstration; `aravis:Fake_1`).
        #[arg(long)]
        with_fake: bool,
    },
    /// Replay a recording as fast as possible and print throughput, stage times, latency
    /// and peak memory.
    Bench(BenchOptions),
    /// The live pipeline on the built-in simulated rig (simulated cameras, simulated UTM
    /// over real Modbus TCP on loopback); the feed goes to stdout.
    #[cfg(feature = "sim")]
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
        /// Keep each test in its own folder here (as `[output] tests`; enables the control API).
        #[arg(long, value_name = "DIR")]
        tests: Option<PathBuf>,
        /// Serve the net deflection (or `[output.control] gauge`) as a control signal on a
        /// read-only Modbus TCP server at ADDR (IP:PORT; see docs/control.md).
        #[arg(long, value_name = "ADDR", value_parser = parse_control_addr)]
        control: Option<std::net::SocketAddr>,
    },
    /// Drive the test of a running daemon through its control API (start, stop, mark, zero).
    Test(commands::lab_test::TestArgs),
    /// Subscribe to the feeds rigs publish over MQTT and keep them in PostgreSQL.
    #[cfg(feature = "archive")]
    Archive(tagdeflect_archive::ArchiveOptions),
    /// Measure how many feed lines per second one archive ingests (simulated rigs).
    #[cfg(feature = "archive")]
    ArchiveBench(tagdeflect_archive::bench::ArchiveBenchOptions),
    /// Camera intrinsics from views of a target (images or a live camera); writes an OpenCV
    /// FileStorage YAML and reports uncertainties, coverage and outliers.
    #[cfg(feature = "calibrate")]
    Calibrate(tagdeflect_calibrate::CalibrateOptions),
    /// The test report from a feed: report.html, report.json, curve.csv and plots.
    Report(commands::report::ReportArgs),
    /// The feed as CSV for spreadsheets (the columns of the report's curve.csv).
    Export(commands::report::ExportArgs),
    /// Write the man pages and shell completions into OUT (for packaging).
    #[command(hide = true)]
    Assets {
        /// The folder for man/ and completions/.
        #[arg(long)]
        out: PathBuf,
    },
    /// A command this build was made without (its feature is named in the error); only in a
    /// build without some feature, so a full build keeps clap's own error for a typo.
    #[cfg(not(all(feature = "sim", feature = "archive", feature = "calibrate")))]
    #[command(external_subcommand)]
    Missing(Vec<String>),
}

/// The commands that need a cargo feature, and the feature.
#[cfg(not(all(feature = "sim", feature = "archive", feature = "calibrate")))]
const FEATURE_COMMANDS: &[(&str, &str)] =
    &[("simulate", "sim"), ("demo", "sim"), ("archive", "archive"), ("archive-bench", "archive"), ("calibrate", "calibrate")];

/// The error for a command this build does not have.
#[cfg(not(all(feature = "sim", feature = "archive", feature = "calibrate")))]
fn missing_command(args: &[String]) -> anyhow::Error {
    let name = args.first().map(String::as_str).unwrap_or("");
    match FEATURE_COMMANDS.iter().find(|(c, _)| *c == name) {
        Some((c, f)) => anyhow::Error::new(tagdeflect_core::BadInput::new(format!(
            "`tagdeflect {c}` is not in this build: it needs the `{f}` feature (cargo build --release --features {f})"
        ))),
        None => anyhow::Error::new(tagdeflect_core::BadInput::new(format!("unknown command \"{name}\" (see `tagdeflect --help`)"))),
    }
}

#[cfg(feature = "sim")] // only `demo --control` takes it
fn parse_control_addr(s: &str) -> Result<std::net::SocketAddr, String> {
    tagdeflect_core::listen::parse_listen_addr(s, tagdeflect_sinks::control_output::EXAMPLE_PORT).map_err(|e| e.to_string())
}

/// The live page of `demo`: `--http ADDR` must be served (an error if it cannot be);
/// without it the config's `[output] http` is used, else [`DEFAULT_ADDR`] on loopback, where
/// a port another program holds only costs the page (a warning); `--no-http`: none.
///
/// [`DEFAULT_ADDR`]: tagdeflect_sinks::http::DEFAULT_ADDR
#[cfg(feature = "sim")]
fn demo_http(http: Option<std::net::SocketAddr>, no_http: bool, configured: bool) -> anyhow::Result<Option<page::HttpOptions>> {
    Ok(match (http, no_http) {
        (_, true) => None,
        (Some(addr), false) => http_options(Some(addr), true),
        (None, false) if configured => None,
        (None, false) => http_options(page::default_addr(), false),
    })
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    init_logging();
    // A panic anywhere (a library's, caught or not) is one ERROR log line with its place,
    // with the journal's priority, rather than the default hook's raw text on stderr.
    std::panic::set_hook(Box::new(|info| {
        let thread = std::thread::current().name().unwrap_or("unnamed").to_string();
        let place = info.location().map(|l| format!("{}:{}", l.file(), l.line())).unwrap_or_default();
        let what = info
            .payload()
            .downcast_ref::<&str>()
            .map(|s| s.to_string())
            .or_else(|| info.payload().downcast_ref::<String>().cloned())
            .unwrap_or_else(|| "(no message)".into());
        tracing::error!(thread = %thread, at = %place, "panic: {what}");
    }));
    match run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("tagdeflect: error: {}", error_text(&e));
            ExitCode::from(exit_code(&e))
        }
    }
}

/// The error and its causes in one line, each said once: a cause whose text its error
/// already quotes (`cannot serve the live page on ADDR: Address already in use`) is not
/// repeated after it.
fn error_text(e: &anyhow::Error) -> String {
    let mut text = String::new();
    for cause in e.chain() {
        let c = cause.to_string();
        if text.is_empty() {
            text = c;
        } else if !c.is_empty() && !text.contains(&c) {
            text.push_str(": ");
            text.push_str(&c);
        }
    }
    if text.trim().is_empty() {
        text = format!("{e:?}");
    }
    text
}

/// Exit codes, chosen from the error's type: 0 done; 2 bad input — a config, a recording, a
/// feed, an option, an output path that cannot be used: a restart cannot help, so the unit
/// says `RestartPreventExitStatus=2`; 1 a failure of the running program that a restart may
/// cure ([`tagdeflect_core::RuntimeFailure`], and any error not known as bad input: a thread or
/// runtime that cannot start, an I/O failure on the way).
fn exit_code(e: &anyhow::Error) -> u8 {
    if e.chain().any(|c| c.is::<tagdeflect_core::RuntimeFailure>()) {
        return 1;
    }
    if e.chain().any(is_bad_input) {
        2
    } else {
        1
    }
}

/// The error types that say the input is at fault.
fn is_bad_input(c: &(dyn std::error::Error + 'static)) -> bool {
    #[cfg(feature = "sim")]
    if c.is::<tagdeflect_sim::SimError>() {
        return true;
    }
    if page::is_bad_input(c) {
        return true;
    }
    c.is::<tagdeflect_core::BadInput>()
        || c.is::<tagdeflect::config::ConfigError>()
        || c.is::<tagdeflect::config::CalibrationError>()
        || c.is::<tagdeflect_io::recording::RecordingError>()
        || c.is::<tagdeflect_report::ReportError>()
        || c.is::<tagdeflect_io::sources::SourceError>()
        || c.is::<clap::Error>()
}

/// An archive error with its exit code (bad options exit 2, a failure of the machine 1).
#[cfg(feature = "archive")]
fn archive_error(e: tagdeflect_archive::ArchiveError) -> anyhow::Error {
    if e.is_bad_input() {
        anyhow::Error::new(tagdeflect_core::BadInput::new(e.to_string()))
    } else {
        anyhow::Error::new(tagdeflect_core::RuntimeFailure::new(e.to_string()))
    }
}

fn init_logging() {
    use tracing_subscriber::{fmt, EnvFilter};
    // TAGDEFLECT_LOG, else RUST_LOG, else "info" (e.g. TAGDEFLECT_LOG=debug).
    let wanted = std::env::var("TAGDEFLECT_LOG").or_else(|_| std::env::var("RUST_LOG")).unwrap_or_else(|_| "info".into());
    // The Modbus library logs every poll at DEBUG: that is TRACE for a lab; it speaks at
    // DEBUG only when the filter names it (`TAGDEFLECT_LOG=debug,tokio_modbus=debug`).
    let directives = if wanted.contains("tokio_modbus") { wanted.clone() } else { format!("{wanted},tokio_modbus=info") };
    let filter = EnvFilter::try_new(&directives).unwrap_or_else(|e| {
        eprintln!("TAGDEFLECT_LOG=\"{wanted}\" is not a log filter ({e}); logging at info");
        EnvFilter::new("info,tokio_modbus=info")
    });
    // Under systemd the journal adds its own timestamps, and takes each line's priority from
    // a `<N>` prefix (sd-daemon(3)), so `journalctl -p warning` shows warnings and errors.
    let under_systemd = std::env::var_os("JOURNAL_STREAM").is_some();
    // Colour only on a terminal: files and the journal get plain text.
    let ansi = std::io::IsTerminal::is_terminal(&std::io::stderr()) && std::env::var_os("NO_COLOR").is_none();
    let builder = fmt().with_env_filter(filter).with_writer(std::io::stderr).with_target(false).with_ansi(ansi);
    if under_systemd {
        builder.event_format(JournalPrefix(fmt::format().without_time().with_target(false).with_ansi(false))).init();
    } else {
        builder.init();
    }
}

/// Writes each event with the journal's priority prefix (`<3>` error … `<7>` debug), then
/// as `inner` formats it.
struct JournalPrefix<F>(F);

impl<S, N, F> tracing_subscriber::fmt::FormatEvent<S, N> for JournalPrefix<F>
where
    S: tracing::Subscriber + for<'a> tracing_subscriber::registry::LookupSpan<'a>,
    N: for<'a> tracing_subscriber::fmt::FormatFields<'a> + 'static,
    F: tracing_subscriber::fmt::FormatEvent<S, N>,
{
    fn format_event(
        &self,
        ctx: &tracing_subscriber::fmt::FmtContext<'_, S, N>,
        mut writer: tracing_subscriber::fmt::format::Writer<'_>,
        event: &tracing::Event<'_>,
    ) -> std::fmt::Result {
        let priority = match *event.metadata().level() {
            tracing::Level::ERROR => 3,
            tracing::Level::WARN => 4,
            tracing::Level::INFO => 6,
            _ => 7,
        };
        write!(writer, "<{priority}>")?;
        self.0.format_event(ctx, writer, event)
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
        Command::Run { config, record, duration_s, tests } => {
            let mut cfg = load_config(&config)?;
            if tests.is_some() {
                cfg.output.tests = tests;
            }
            // Without `[output] feed` the feed goes to stdout (SPEC leaves it open; a feed
            // nobody sees helps no one).
            let feed_to_stdout = cfg.output.feed.is_none();
            live::run(cfg, LiveOptions { record, duration_s, feed_to_stdout, ..LiveOptions::default() })
        }
        Command::Replay { dir, config, realtime, full_frame, http, smooth, smooth_lag_sets } => {
            let cfg = config.as_deref().map(load_config).transpose()?;
            let http = http_options(http, true);
            // One graph; `--realtime` is only the recording's pacing.
            if realtime {
                live::replay_realtime_http(&dir, cfg, full_frame, http)
            } else {
                live::replay_smoothed(&dir, cfg, full_frame, http, smooth.then_some(smooth_lag_sets as usize))
            }
        }
        Command::Record { config, out, duration_s } => {
            let cfg = load_config(&config)?;
            live::run(cfg, LiveOptions { record: Some(out), duration_s, record_only: true, ..LiveOptions::default() })
        }
        #[cfg(feature = "sim")]
        Command::Simulate { out, frame_format, params } => {
            let summary = anyhow::Context::with_context(tagdeflect::commands::simulate::simulate_as(&params, &out, frame_format), || {
                format!("simulating into {}", out.display())
            })?;
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
            (Some(dir), None) => commands::check::check_recording(&dir),
            (None, Some(cfg)) => commands::check::check_config(&cfg),
            _ => Err(tagdeflect_core::BadInput::new("check takes either a recording folder or --config FILE").into()),
        },
        Command::Cameras { with_fake } => commands::cameras::list(with_fake),
        Command::Test(args) => commands::lab_test::run(&args),
        Command::Bench(opts) => commands::bench::bench(&opts),
        #[cfg(feature = "sim")]
        Command::Demo { duration_s, config, http, no_http, tests, control } => {
            let cfg = match config {
                Some(p) => load_config(&p)?,
                None => Config::demo(),
            };
            // The page by default on loopback; a taken default port only costs the page.
            let mut cfg = cfg;
            if let Some(addr) = control {
                let c = cfg.output.control.get_or_insert_with(|| tagdeflect_sinks::control_output::ControlConfig::on(&addr.to_string()));
                c.modbus = addr.to_string();
            }
            if no_http {
                cfg.output.http = None;
            }
            if tests.is_some() {
                cfg.output.tests = tests;
            }
            let http = demo_http(http, no_http, cfg.output.http.is_some())?;
            live::run(cfg, LiveOptions { duration_s, feed_to_stdout: true, http, ..LiveOptions::default() })
        }
        #[cfg(feature = "archive")]
        Command::Archive(opts) => tagdeflect_archive::run(opts).map_err(archive_error),
        #[cfg(feature = "archive")]
        Command::ArchiveBench(opts) => tagdeflect_archive::bench::run(&opts).map_err(archive_error),
        #[cfg(feature = "calibrate")]
        Command::Calibrate(opts) => commands::calibrate::run(&opts),
        Command::Report(args) => commands::report::run_cli(&args).map(|_| ()),
        Command::Export(args) => commands::report::export_cli(&args),
        Command::Assets { out } => commands::assets::write(<Cli as clap::CommandFactory>::command(), &out),
        #[cfg(not(all(feature = "sim", feature = "archive", feature = "calibrate")))]
        Command::Missing(args) => Err(missing_command(&args)),
    }
}

#[cfg(all(test, feature = "sim", feature = "http"))]
mod tests {
    use super::*;

    #[test]
    fn demo_serves_the_default_page_on_loopback_and_only_warns_when_its_port_is_taken() {
        let default = demo_http(None, false, false).unwrap().unwrap();
        assert_eq!(default.addr, std::net::SocketAddr::from(([127, 0, 0, 1], 8080)));
        assert!(default.addr.ip().is_loopback());
        assert!(!default.required, "a taken default port costs only the page");
        let given: std::net::SocketAddr = "127.0.0.1:0".parse().unwrap();
        let asked = demo_http(Some(given), false, false).unwrap().unwrap();
        assert_eq!((asked.addr, asked.required), (given, true), "--http ADDR must be served");
        assert!(demo_http(None, true, false).unwrap().is_none());
        assert!(demo_http(Some(given), true, false).unwrap().is_none());
        assert!(demo_http(None, false, true).unwrap().is_none(), "the config's [output] http is served by the graph");
    }
}
