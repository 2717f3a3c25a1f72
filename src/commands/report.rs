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
    /// present, the report's options); default for a test folder: its `tagdeflect.toml`.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// The standard; default for a test folder: its `test.json`'s.
    #[arg(long, value_enum)]
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
    /// A specimen of the series the lab excludes, with the reason (`B3="cast with a void"`):
    /// listed with it, left out of the statistics. Repeat for each.
    #[arg(long, value_parser = parse_exclude)]
    pub exclude: Vec<(String, String)>,
}

/// `ID=REASON` of `--exclude`.
fn parse_exclude(s: &str) -> Result<(String, String), String> {
    match s.split_once('=') {
        Some((id, why)) if !id.trim().is_empty() && !why.trim().is_empty() => Ok((id.trim().to_string(), why.trim().to_string())),
        _ => Err(format!("{s:?}: give ID=REASON (the specimen's id or folder, and why it is excluded)")),
    }
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

/// The report's options: the config's `[report]` (when present), then the command line
/// (the geometry is checked once the test's measured dimensions are in, [`check_geometry`]).
fn options(args: &ReportArgs, config: &Config, out: &Path) -> anyhow::Result<ReportConfig> {
    let standard = args.standard.or(config.report.as_ref().map(|r| r.standard)).unwrap_or(Standard::AstmC1609);
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
    lab_flags(args, &mut o.lab);
    // The same checks as `[report]` in a config, the key named as the flag.
    o.validate_options().map_err(|p| bad(format!("--{}: {}", p.key.replace(['_', '.'], "-").trim_start_matches("lab-"), p.message)))?;
    Ok(o)
}

/// The identification given on the command line, over the config's and `test.json`'s.
fn lab_flags(args: &ReportArgs, lab: &mut tagdeflect_report::LabInfo) {
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
}

/// The geometry the report computes with, checked as `[report]` checks it.
fn check_geometry(opts: &ReportConfig, rig: &tagdeflect_report::TestRig, config_path: &Path) -> anyhow::Result<()> {
    opts.validate_with(rig.specimen.beam.as_ref()).map_err(|p| bad(format!("{}: {}", config_path.display(), p.message)))
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

/// The config of a feed: `--config`, else the `tagdeflect.toml` of its test folder.
fn config_path_of(args: &ReportArgs, feed_path: &Path) -> anyhow::Result<PathBuf> {
    if let Some(c) = &args.config {
        return Ok(c.clone());
    }
    let folder = feed_path.parent().map(|d| d.join("tagdeflect.toml")).filter(|p| p.is_file());
    folder.ok_or_else(|| bad(format!("{}: not a test folder's feed (no tagdeflect.toml beside it): give --config", feed_path.display())))
}

/// Builds the reports of one feed file (one per run). A feed with `test.json` beside it is a
/// test folder's: its inputs are built as the report made at the test's stop builds them
/// ([`tagdeflect_report::test_folder::prepare`]).
fn reports_of(feed_path: &Path, args: &ReportArgs, out: &Path) -> anyhow::Result<Vec<(Report, Feed)>> {
    use tagdeflect_report::test_folder::{build_test, prepare, read_record, read_streams, record_of};
    let config_path = config_path_of(args, feed_path)?;
    let config = Config::load(&config_path)?;
    let opts = options(args, &config, out)?;
    let dir = feed_path.parent().unwrap_or(Path::new("."));
    let record = record_of(dir).filter(|_| feed_path.file_name().is_some_and(|n| n == "feed.jsonl"));
    let mut inputs = vec![("config".to_string(), config_path.clone())];
    if args.config.is_some() {
        inputs.extend(calibration_files(&config).into_iter().map(|p| ("calibration".to_string(), p)));
    }
    let mut out = Vec::new();
    if let Some(record_path) = record {
        let view = read_record(&record_path)?;
        let mut prepared = prepare(&view, &config.test_rig(), &opts, args.standard, &record_path, &config_path)?;
        lab_flags(args, &mut prepared.opts.lab);
        if args.standard.is_none() && view.meta.standard.is_none() && config.report.is_none() {
            return Err(bad(format!("{}: names no standard: give --standard", record_path.display())));
        }
        check_geometry(&prepared.opts, &prepared.rig, &config_path)?;
        let (runs, mut utm) = read_streams(dir, &prepared, args.allow_restarts)?;
        if let Some(u) = args.utm.as_ref().filter(|_| args.series.is_empty()) {
            utm = Some(UtmStream::read(u, &prepared.opts.limits())?);
        }
        for feed in runs {
            let mut r = build_test(&feed, utm.as_ref(), &prepared, &view, &config_path)?;
            r.inputs = inputs.clone();
            out.push((r, feed));
        }
        return Ok(out);
    }
    if args.standard.is_none() && config.report.is_none() {
        return Err(bad(format!("{}: not a test folder's feed (no test.json beside it): give --standard", feed_path.display())));
    }
    check_geometry(&opts, &config.test_rig(), &config_path)?;
    // A rotated run's feed: its rotated files are inputs too (hashed; `report verify` checks them).
    let rotated = tagdeflect_core::feed_rotation::feed_files(feed_path).unwrap_or_default();
    let rotated = rotated.into_iter().filter(|p| p != feed_path).map(|p| ("feed".to_string(), p));
    inputs.splice(0..0, rotated);
    let rig = config.test_rig();
    let read = ReadOptions { limits: opts.limits(), allow_restarts: args.allow_restarts };
    let runs = Feed::read_runs_for(feed_path, &read, Some(&rig))?;
    let utm_path = match &args.utm {
        Some(p) if args.series.is_empty() => Some(p.clone()),
        _ => feed_path.parent().map(|d| d.join("utm.jsonl")).filter(|p| p.is_file()),
    };
    let utm = utm_path.map(|p| UtmStream::read(&p, &opts.limits())).transpose()?;
    for feed in runs {
        let mut r = build(&feed, utm.as_ref(), &rig, &config_path, &opts)?;
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
    let Some(out) = &args.out else {
        return Err(bad("report needs --out"));
    };
    // Everything is read and computed before anything is written.
    let mut groups: Vec<(Report, Feed)> = Vec::new();
    let feeds: Vec<PathBuf> = match &args.feed {
        Some(f) => vec![feed_of(f)],
        None => args.series.iter().map(|p| feed_of(p)).collect(),
    };
    for f in &feeds {
        groups.extend(reports_of(f, args, out)?);
    }
    if args.standard.is_none() {
        one_standard(&groups)?;
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
        files.extend(tagdeflect_report::series::write(&reports, &args.exclude, out)?);
        if args.series.is_empty() {
            tracing::warn!("{} holds {} runs: each reported on its own under {}", feeds[0].display(), reports.len(), out.display());
        }
    }
    tracing::info!("report written into {} ({} files)", out.display(), files.len());
    Ok(files)
}

/// A series of one standard, or an error naming the folders of each (`--standard` picks one).
fn one_standard(groups: &[(Report, Feed)]) -> anyhow::Result<()> {
    let mut by: std::collections::BTreeMap<&str, Vec<String>> = Default::default();
    for (r, _) in groups {
        let folder = r.feed_path.parent().unwrap_or(&r.feed_path).display().to_string();
        by.entry(r.standard.id()).or_default().push(folder);
    }
    if by.len() < 2 {
        return Ok(());
    }
    let list: Vec<String> = by.iter().map(|(s, f)| format!("{s}: {}", f.join(", "))).collect();
    Err(bad(format!("the series mixes standards ({}): give --standard to report it as one", list.join("; "))))
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

/// `tagdeflect report verify DIR`: the folder as it lies (`tagdeflect_report::verify`) and
/// the tests folder's audit chain; exit 0 when nothing changed, 1 naming every change.
fn verify_cli(dir: &Path) -> anyhow::Result<()> {
    use tagdeflect_report::verify::{audit_log_of, chain_checked, InputState};
    let mut v = tagdeflect_report::verify::verify(dir)?;
    if let Some(t) = v.folders.test.clone() {
        let log = audit_log_of(&t);
        if log.is_file() {
            v.checked.push(chain_checked(&log, audit_chain(&log)));
        }
    }
    for c in &v.checked {
        let (word, why) = match &c.state {
            InputState::Same => ("same    ", String::new()),
            InputState::Changed => ("CHANGED ", String::new()),
            InputState::Missing(e) => ("MISSING ", format!(" ({e})")),
            InputState::Extra => ("EXTRA   ", " (not in test.json)".to_string()),
            InputState::Grown { then, now } => {
                ("grown   ", format!(" (written to since: {then} B hashed, unchanged; {now} B now, the rest not in the report)"))
            }
        };
        println!("{word} {} {}{why}", c.role, c.path);
    }
    let here = env!("CARGO_PKG_VERSION");
    if v.version != here {
        println!("software: the report was made by tagdeflect {}, this is {here}", v.version);
    }
    let changes: Vec<String> = v
        .changes()
        .iter()
        .map(|c| {
            let what = match c.state {
                InputState::Missing(_) => "missing",
                InputState::Extra => "extra",
                _ => "changed",
            };
            format!("{} {} {what}", c.role, c.path)
        })
        .collect();
    if changes.is_empty() {
        let grown = v.checked.iter().filter(|c| matches!(c.state, InputState::Grown { .. })).count();
        let note =
            if grown > 0 { format!("; {grown} input(s) written to since, the part the report read unchanged") } else { String::new() };
        println!("{}: every file as recorded ({} checked{note})", dir.display(), v.checked.len());
        Ok(())
    } else {
        Err(anyhow::anyhow!("{}: {} change(s): {}", dir.display(), changes.len(), changes.join("; ")))
    }
}

/// The audit chain of a tests folder, whole (its entries) or where it is broken.
fn audit_chain(log: &Path) -> tagdeflect_report::verify::Chain {
    tagdeflect_core::audit::verify_chain(log).map(|s| s.entries).map_err(|e| e.to_string())
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
