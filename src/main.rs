//! The `tagdeflect` command line (SPEC "Command line"). Only argument parsing, logging
//! set-up and the mapping of errors to exit codes live here.

use anyhow::Result;
use clap::{Parser, Subcommand};
use std::path::PathBuf;
use std::process::ExitCode;

use tagdeflect::commands::{self, bench::BenchOptions, optional, parse_duration_s};
use tagdeflect::config::Config;
use tagdeflect::graph::entry::{self as live, LiveOptions};
use tagdeflect::graph::page::{self, http_options, parse_http_addr};

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
    /// `simulate`, `demo` (the `sim` feature).
    #[command(flatten)]
    Sim(optional::sim::SimCommand),
    /// Validate a config (and open its sources) or a recording; print each camera's pose,
    /// reprojection error and the tags it sees.
    Check {
        /// A recording folder (or use --config).
        dir: Option<PathBuf>,
        /// A config file.
        #[arg(long)]
        config: Option<PathBuf>,
        /// With --config: also write the analog output's safe state to its device (the valid
        /// line low, then the safe voltage) and read it back. Never written otherwise.
        #[arg(long, requires = "config")]
        write_test: bool,
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
    /// Drive the test of a running daemon through its control API (start, stop, mark, zero).
    Test(commands::lab_test::TestArgs),
    /// The control API's users and roles (`[output] users_file`): add, list, remove.
    User(commands::user::UserArgs),
    /// The test methods: list them, show one, record the lab's review of one.
    Method(commands::method::MethodArgs),
    /// `archive`, `archive-bench` (the `archive` feature).
    #[command(flatten)]
    Archive(optional::archive::ArchiveCommand),
    /// `calibrate` (the `calibrate` feature).
    #[command(flatten)]
    Calibrate(optional::calibrate::CalibrateCommand),
    /// The test report from a feed: report.html, report.json, curve.csv and plots.
    Report(commands::report::ReportArgs),
    /// Verify the rig from a recording of a rigid target at rest and at known positions: the
    /// ISO 9513 class, VDI/VDE 2626 figures, the expanded uncertainty, a certificate.
    Verify(commands::verify::VerifyArgs),
    /// The feed as CSV for spreadsheets (the columns of the report's curve.csv).
    Export(commands::report::ExportArgs),
    /// Write the man pages and shell completions into OUT (for packaging).
    #[command(hide = true)]
    Assets {
        /// The folder for man/ and completions/.
        #[arg(long)]
        out: PathBuf,
    },
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    init_logging();
    // A panic anywhere (a library's, caught or not) is one ERROR log line with its place,
    // with the journal's priority, rather than the default hook's raw text on stderr; the
    // same place again within 10 s is counted, not logged (a client sending a frame that
    // panics a library's decoder 1 000 times gets a line per 10 s).
    std::panic::set_hook(Box::new(|info| {
        let thread = std::thread::current().name().unwrap_or("unnamed").to_string();
        let place = info.location().map(|l| format!("{}:{}", l.file(), l.line())).unwrap_or_default();
        let Some(repeats) = panic_throttle(&place) else { return };
        let what = info
            .payload()
            .downcast_ref::<&str>()
            .map(|s| s.to_string())
            .or_else(|| info.payload().downcast_ref::<String>().cloned())
            .unwrap_or_else(|| "(no message)".into());
        tracing::error!(thread = %thread, at = %place, repeats, "panic: {what}");
    }));
    match run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("tagdeflect: error: {}", error_text(&e));
            ExitCode::from(exit_code(&e))
        }
    }
}

/// Whether a panic at `place` is logged now: the first, then once per 10 s per place, with
/// the count of the panics there since the last line (`Some(count)`).
fn panic_throttle(place: &str) -> Option<u64> {
    use std::collections::HashMap;
    use std::sync::Mutex;
    use std::time::{Duration, Instant};
    static SEEN: Mutex<Option<HashMap<String, (Option<Instant>, u64)>>> = Mutex::new(None);
    let mut g = SEEN.lock().unwrap_or_else(|p| p.into_inner());
    let seen = g.get_or_insert_with(HashMap::new);
    let now = Instant::now();
    let entry = seen.entry(place.to_string()).or_insert((None, 0));
    entry.1 += 1;
    if entry.0.is_some_and(|t| now.duration_since(t) < Duration::from_secs(10)) {
        return None;
    }
    entry.0 = Some(now);
    Some(std::mem::take(&mut entry.1))
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

/// Exit codes, chosen from the error's type: 0 done; 3 done, but the result is not fit to
/// measure with ([`tagdeflect_core::NotFit`]: a POOR calibration, a `check` over its pose
/// limit); 2 bad input — a config, a recording, a
/// feed, an option, an output path that cannot be used: a restart cannot help, so the unit
/// says `RestartPreventExitStatus=2`; 1 a failure of the running program that a restart may
/// cure ([`tagdeflect_core::RuntimeFailure`], and any error not known as bad input: a thread or
/// runtime that cannot start, an I/O failure on the way).
fn exit_code(e: &anyhow::Error) -> u8 {
    if e.chain().any(|c| c.is::<tagdeflect_core::NotFit>()) {
        return 3;
    }
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
    if optional::sim::is_bad_input(c) {
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
        Command::Check { dir, config, write_test } => match (dir, config) {
            (Some(dir), None) => commands::check::check_recording(&dir),
            (None, Some(cfg)) => commands::check::check_config(&cfg, write_test),
            _ => Err(tagdeflect_core::BadInput::new("check takes either a recording folder or --config FILE").into()),
        },
        Command::Cameras { with_fake } => commands::cameras::list(with_fake),
        Command::Test(args) => commands::lab_test::run(&args),
        Command::User(args) => commands::user::run(&args),
        Command::Method(args) => commands::method::run(&args),
        Command::Bench(opts) => commands::bench::bench(&opts),
        Command::Sim(command) => command.run(),
        Command::Archive(command) => command.run(),
        Command::Calibrate(command) => command.run(),
        Command::Report(args) => commands::report::run_cli(&args).map(|_| ()),
        Command::Verify(args) => commands::verify::run(&args).map(|_| ()),
        Command::Export(args) => commands::report::export_cli(&args),
        Command::Assets { out } => commands::assets::write(<Cli as clap::CommandFactory>::command(), &out),
    }
}
