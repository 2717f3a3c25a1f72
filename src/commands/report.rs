//! `tagdeflect report`, `tagdeflect report verify` and `tagdeflect export`: the command line
//! of the report (`tagdeflect_report` computes and writes it).

use std::path::{Path, PathBuf};

use tagdeflect_report::{build, csv_out, write, write_atomic, Feed, ReadOptions, Report, ReportConfig, Standard, UtmStream};

use crate::config::Config;

/// `tagdeflect report` options.
#[derive(Debug, Clone, clap::Args)]
#[command(args_conflicts_with_subcommands = true, subcommand_negates_reqs = true)]
pub struct ReportArgs {
    /// `verify DIR`: the inputs of a report hashed again.
    #[command(subcommand)]
    pub action: Option<ReportAction>,
    /// The feed (JSON Lines) of the test.
    #[arg(required_unless_present = "series")]
    pub feed: Option<PathBuf>,
    /// A series of specimens: each feed reported in its own folder under --out, with the
    /// mean, standard deviation and coefficient of variation of every quantity (a test
    /// folder may be given instead of its feed.jsonl).
    #[arg(long, num_args = 1.., conflicts_with = "feed")]
    pub series: Vec<PathBuf>,
    /// The config of the test (its `[specimen.beam]` gives the geometry; its `[report]`, when
    /// present, the report's options).
    #[arg(long, required = true)]
    pub config: Option<PathBuf>,
    /// The standard.
    #[arg(long, value_enum, required = true)]
    pub standard: Option<Standard>,
    /// Output folder (created; existing report files in it are replaced).
    #[arg(long, required = true)]
    pub out: Option<PathBuf>,
    /// The UTM's own samples (SPEC `utm.jsonl`); default: `utm.jsonl` beside the feed when
    /// there is one.
    #[arg(long)]
    pub utm: Option<PathBuf>,
    /// A feed whose seq goes back or repeats holds several runs: report each on its own
    /// (default: an error naming the line).
    #[arg(long)]
    pub allow_restarts: bool,
    /// Use this gauge as the net deflection (default: the feed's `net_deflection_mm`).
    #[arg(long)]
    pub deflection_gauge: Option<String>,
    /// Use this gauge as the CMOD (EN 14651; default: the gauge named `cmod`).
    #[arg(long)]
    pub cmod_gauge: Option<String>,
    /// Points of the local-linear smoothing of deflection/CMOD over time (odd; 1 = none;
    /// default 5 or `[report] smooth_points`).
    #[arg(long)]
    pub smooth_points: Option<usize>,
    /// The specimen's response as the lab states it (ASTM C1609/C1856; default softening or
    /// `[report] response`): hardening accepts a first peak beyond L/150.
    #[arg(long, value_enum)]
    pub response: Option<tagdeflect_report::Response>,
    /// Resolution of the load reading, kN (adds resolution/√12 to each load's σ).
    #[arg(long)]
    pub load_resolution_kn: Option<f64>,
    /// Largest |load| a line may carry, kN (default 10000).
    #[arg(long)]
    pub max_load_kn: Option<f64>,
    /// Largest |length| a line may carry, mm (default 10000).
    #[arg(long)]
    pub max_length_mm: Option<f64>,
    /// Longest time without a feed line or UTM sample in a valid test, s (default 2).
    #[arg(long)]
    pub max_gap_s: Option<f64>,
    /// Do not print `report.pdf` (printed with headless Chromium when it is installed).
    #[arg(long)]
    pub no_pdf: bool,
    /// Specimen id.
    #[arg(long)]
    pub specimen: Option<String>,
    /// Operator.
    #[arg(long)]
    pub operator: Option<String>,
    /// Cast date, YYYY-MM-DD.
    #[arg(long)]
    pub cast_date: Option<String>,
    /// Test date, YYYY-MM-DD (default: the feed's first line).
    #[arg(long)]
    pub test_date: Option<String>,
    /// Edition of the standard, e.g. C1609/C1609M-19a.
    #[arg(long)]
    pub edition: Option<String>,
    /// Testing machine.
    #[arg(long)]
    pub machine: Option<String>,
    /// Where the specimen broke.
    #[arg(long)]
    pub fracture: Option<String>,
    /// Laboratory name.
    #[arg(long)]
    pub laboratory: Option<String>,
}

/// `tagdeflect report` sub-commands.
#[derive(Debug, Clone, clap::Subcommand)]
pub enum ReportAction {
    /// Hash the inputs `DIR/report.json` lists again and say what changed (exit 2 when
    /// anything did).
    Verify {
        /// The report's folder.
        dir: PathBuf,
    },
}

/// `tagdeflect export` options.
#[derive(Debug, Clone, clap::Args)]
pub struct ExportArgs {
    /// The feed (JSON Lines).
    pub feed: PathBuf,
    /// The CSV file to write (`-` = stdout); its folder must exist.
    #[arg(long)]
    pub csv: PathBuf,
}

fn bad(msg: impl Into<String>) -> anyhow::Error {
    tagdeflect_core::BadInput::new(msg.into()).into()
}

/// The report's options: the config's `[report]` (when present), then the command line.
fn options(args: &ReportArgs, config: &Config, standard: Standard, out: &Path) -> anyhow::Result<ReportConfig> {
    let mut o = config.report.clone().unwrap_or_else(|| ReportConfig::new(standard, out.to_path_buf()));
    o.standard = standard;
    o.out = out.to_path_buf();
    if args.deflection_gauge.is_some() {
        o.deflection_gauge = args.deflection_gauge.clone();
    }
    if args.cmod_gauge.is_some() {
        o.cmod_gauge = args.cmod_gauge.clone();
    }
    if let Some(n) = args.smooth_points {
        o.smooth_points = n;
    }
    if let Some(r) = args.response {
        o.response = r;
    }
    if args.load_resolution_kn.is_some() {
        o.load_resolution_kn = args.load_resolution_kn;
    }
    for (dst, src) in
        [(&mut o.max_load_kn, args.max_load_kn), (&mut o.max_length_mm, args.max_length_mm), (&mut o.max_gap_s, args.max_gap_s)]
    {
        if let Some(v) = src {
            *dst = v;
        }
    }
    if args.no_pdf {
        o.pdf = false;
    }
    let lab = &mut o.lab;
    for (dst, src) in [
        (&mut lab.specimen, &args.specimen),
        (&mut lab.operator, &args.operator),
        (&mut lab.cast_date, &args.cast_date),
        (&mut lab.test_date, &args.test_date),
        (&mut lab.edition, &args.edition),
        (&mut lab.machine, &args.machine),
        (&mut lab.fracture, &args.fracture),
        (&mut lab.laboratory, &args.laboratory),
    ] {
        if src.is_some() {
            *dst = src.clone();
        }
    }
    // The same checks as `[report]` in a config, the key named as the flag.
    o.validate_with(config.specimen.beam.as_ref())
        .map_err(|p| bad(format!("--{}: {}", p.key.replace(['_', '.'], "-").trim_start_matches("lab-"), p.message)))?;
    Ok(o)
}

/// The calibration files a config names (`[[camera]] calibration`, resolved against its
/// folder by the config's loading; the camchain itself for `file.yaml#cam1`), each once.
fn calibration_files(config: &Config) -> Vec<PathBuf> {
    let mut files: Vec<PathBuf> = Vec::new();
    for p in &config.calibration_files {
        if p.is_file() && !files.contains(p) {
            files.push(p.clone());
        }
    }
    files
}

/// A feed path, or a test folder holding `feed.jsonl`.
fn feed_of(p: &Path) -> PathBuf {
    if p.is_dir() {
        p.join("feed.jsonl")
    } else {
        p.to_path_buf()
    }
}

/// Builds the reports of one feed file (one per run).
fn reports_of(
    feed_path: &Path,
    args: &ReportArgs,
    config: &Config,
    config_path: &Path,
    opts: &ReportConfig,
) -> anyhow::Result<Vec<(Report, Feed)>> {
    let runs = Feed::read_runs(feed_path, &ReadOptions { limits: opts.limits(), allow_restarts: args.allow_restarts })?;
    let utm_path = match &args.utm {
        Some(p) if args.series.is_empty() => Some(p.clone()),
        _ => feed_path.parent().map(|d| d.join("utm.jsonl")).filter(|p| p.is_file()),
    };
    let utm = utm_path.map(|p| UtmStream::read(&p, &opts.limits())).transpose()?;
    let mut inputs = vec![("config".to_string(), config_path.to_path_buf())];
    inputs.extend(calibration_files(config).into_iter().map(|p| ("calibration".to_string(), p)));
    let rig = config.test_rig();
    let mut out = Vec::new();
    for feed in runs {
        let mut r = build(&feed, utm.as_ref(), &rig, config_path, opts)?;
        r.inputs = inputs.clone();
        out.push((r, feed));
    }
    Ok(out)
}

/// Reads the config and feed(s) of `report` and writes the report(s); returns the files written.
pub fn run_cli(args: &ReportArgs) -> anyhow::Result<Vec<PathBuf>> {
    use anyhow::Context;
    if let Some(ReportAction::Verify { dir }) = &args.action {
        return verify_cli(dir).map(|_| Vec::new());
    }
    let (Some(config_path), Some(standard), Some(out)) = (&args.config, args.standard, &args.out) else {
        return Err(bad("report needs --config, --standard and --out"));
    };
    let config = Config::load(config_path)?;
    let opts = options(args, &config, standard, out)?;
    // Everything is read and computed before anything is written.
    let mut groups: Vec<(Report, Feed)> = Vec::new();
    let feeds: Vec<PathBuf> = match &args.feed {
        Some(f) => vec![f.clone()],
        None => args.series.iter().map(|p| feed_of(p)).collect(),
    };
    for f in &feeds {
        groups.extend(reports_of(f, args, &config, config_path, &opts)?);
    }
    let mut files = Vec::new();
    if groups.len() == 1 {
        let (report, feed) = &groups[0];
        files = write(report, feed, out).with_context(|| format!("writing the report into {}", out.display()))?;
        log_values(report);
    } else {
        let mut used = std::collections::HashSet::new();
        for (k, (report, feed)) in groups.iter().enumerate() {
            let mut name = match feed.run {
                Some((i, _)) if args.series.is_empty() => format!("run-{i}"),
                Some((i, _)) => format!("{}-run-{i}", series_folder(report)),
                None => series_folder(report),
            };
            if name.is_empty() || !used.insert(name.clone()) {
                name = format!("{name}-{}", k + 1);
                used.insert(name.clone());
            }
            let dir = out.join(&name);
            files.extend(write(report, feed, &dir).with_context(|| format!("writing the report into {}", dir.display()))?);
            tracing::info!("{name}: {}", if report.validity.valid { "valid" } else { "NOT VALID" });
        }
        let reports: Vec<Report> = groups.into_iter().map(|(r, _)| r).collect();
        files.extend(tagdeflect_report::series::write(&reports, out)?);
        if args.series.is_empty() {
            tracing::warn!("{} holds {} runs: each reported on its own under {}", feeds[0].display(), reports.len(), out.display());
        }
    }
    tracing::info!("report written into {} ({} files)", out.display(), files.len());
    Ok(files)
}

/// The folder of one specimen of a series under `--out`: a safe name, with a warning when
/// the specimen's name had to be changed for it.
fn series_folder(report: &Report) -> String {
    let (name, folder) = (tagdeflect_report::series::specimen_name(report), tagdeflect_report::series::folder_name(report));
    if name != folder {
        tracing::warn!("{}: specimen {:?} is not a safe folder name: reported into {folder}", report.feed_path.display(), name);
    }
    folder
}

fn log_values(report: &Report) {
    if !report.validity.valid {
        for r in &report.validity.reasons {
            tracing::warn!("not a valid test: {r}");
        }
    }
    for e in &report.entries {
        match &e.result {
            Ok(q) => tracing::info!("{} = {}", e.key, q.text()),
            Err(why) => tracing::warn!("{}: not determined: {why}", e.key),
        }
    }
}

/// `tagdeflect report verify DIR`.
fn verify_cli(dir: &Path) -> anyhow::Result<()> {
    use tagdeflect_report::verify::InputState;
    let (checked, version) = tagdeflect_report::verify::verify(dir)?;
    let mut changed = Vec::new();
    for c in &checked {
        match &c.state {
            InputState::Same => println!("same     {} {}", c.role, c.path),
            InputState::Changed => {
                println!("CHANGED  {} {}", c.role, c.path);
                changed.push(format!("{} {} changed", c.role, c.path));
            }
            InputState::Missing(e) => {
                println!("MISSING  {} {} ({e})", c.role, c.path);
                changed.push(format!("{} {} missing", c.role, c.path));
            }
        }
    }
    let here = env!("CARGO_PKG_VERSION");
    if version != here {
        println!("software: the report was made by tagdeflect {version}, this is {here}");
    }
    if changed.is_empty() {
        println!("{}: every input as when the report was made ({} files)", dir.display(), checked.len());
        Ok(())
    } else {
        Err(bad(format!("{}: {} input(s) differ from the report's: {}", dir.display(), changed.len(), changed.join("; "))))
    }
}

/// `tagdeflect export`: the feed as CSV.
pub fn export_cli(args: &ExportArgs) -> anyhow::Result<()> {
    if args.csv != Path::new("-") {
        let dir = args.csv.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(Path::new("."));
        if !dir.is_dir() {
            return Err(bad(format!("{}: the folder {} does not exist (create it first)", args.csv.display(), dir.display())));
        }
        let same = match (args.feed.canonicalize(), dir.canonicalize()) {
            (Ok(f), Ok(d)) => args.csv.file_name().is_some_and(|n| d.join(n) == f),
            _ => false,
        };
        if same {
            return Err(bad(format!("{}: the CSV would overwrite the feed it is made from; name another file", args.csv.display())));
        }
    }
    let feed = Feed::read(&args.feed)?;
    if args.csv == Path::new("-") {
        let mut out = std::io::stdout().lock();
        csv_out::write_curve_csv(&feed, &mut out).map_err(|e| bad(format!("writing the CSV to stdout: {e}")))?;
    } else {
        let mut buf = Vec::new();
        csv_out::write_curve_csv(&feed, &mut buf).map_err(|e| bad(format!("{}: {e}", args.csv.display())))?;
        write_atomic(&args.csv, &buf)?;
    }
    Ok(())
}
