//! `tagdeflect report` and `tagdeflect export`: the command line of the report
//! (`tagdeflect_report` computes and writes it).

use std::path::{Path, PathBuf};

use tagdeflect_report::{build, csv_out, write, write_atomic, Feed, ReportConfig, Standard};

use crate::config::Config;

/// `tagdeflect report` options.
#[derive(Debug, Clone, clap::Args)]
pub struct ReportArgs {
    /// The feed (JSON Lines) of the test.
    pub feed: PathBuf,
    /// The config of the test (its `[specimen.beam]` gives the geometry).
    #[arg(long)]
    pub config: PathBuf,
    /// The standard.
    #[arg(long, value_enum)]
    pub standard: Standard,
    /// Output folder (created; existing report files in it are replaced).
    #[arg(long)]
    pub out: PathBuf,
    /// Use this gauge as the net deflection (default: the feed's `net_deflection_mm`).
    #[arg(long)]
    pub deflection_gauge: Option<String>,
    /// Use this gauge as the CMOD (EN 14651; default: the gauge named `cmod`).
    #[arg(long)]
    pub cmod_gauge: Option<String>,
    /// Points of the local-linear smoothing of deflection/CMOD over time (odd; 1 = none).
    #[arg(long, default_value_t = tagdeflect_report::config::default_smooth())]
    pub smooth_points: usize,
    /// Resolution of the load reading, kN (adds resolution/√12 to each load's σ).
    #[arg(long, default_value_t = 0.0)]
    pub load_resolution_kn: f64,
}

/// `tagdeflect export` options.
#[derive(Debug, Clone, clap::Args)]
pub struct ExportArgs {
    /// The feed (JSON Lines).
    pub feed: PathBuf,
    /// The CSV file to write (`-` = stdout).
    #[arg(long)]
    pub csv: PathBuf,
}

/// Reads the config and feed of `report` and writes the report; returns the files written.
pub fn run_cli(args: &ReportArgs) -> anyhow::Result<Vec<PathBuf>> {
    use anyhow::Context;
    if args.smooth_points == 0 || args.smooth_points.is_multiple_of(2) {
        return Err(crate::BadInput::new(format!("--smooth-points must be odd and at least 1, got {}", args.smooth_points)).into());
    }
    if !(args.load_resolution_kn.is_finite() && args.load_resolution_kn >= 0.0) {
        return Err(crate::BadInput::new("--load-resolution-kn must be a non-negative load in kN").into());
    }
    let config = Config::load(&args.config)?;
    let feed = Feed::read(&args.feed)?;
    let opts = ReportConfig {
        standard: args.standard,
        out: args.out.clone(),
        deflection_gauge: args.deflection_gauge.clone(),
        cmod_gauge: args.cmod_gauge.clone(),
        smooth_points: args.smooth_points,
        load_resolution_kn: Some(args.load_resolution_kn),
    };
    let report = build(&feed, &config.test_rig(), &args.config, &opts)?;
    let files = write(&report, &feed, &args.out).with_context(|| format!("writing the report into {}", args.out.display()))?;
    for e in &report.entries {
        match &e.result {
            Ok(q) => tracing::info!("{} = {:.4} ± {:.4} {}", e.key, q.value, q.sigma, q.unit),
            Err(why) => tracing::warn!("{}: not determined: {why}", e.key),
        }
    }
    tracing::info!("report written into {} ({} files)", args.out.display(), files.len());
    Ok(files)
}

/// `tagdeflect export`: the feed as CSV.
pub fn export_cli(args: &ExportArgs) -> anyhow::Result<()> {
    let feed = Feed::read(&args.feed)?;
    if args.csv == Path::new("-") {
        let mut out = std::io::stdout().lock();
        csv_out::write_curve_csv(&feed, &mut out).map_err(|e| crate::BadInput::new(format!("writing the CSV to stdout: {e}")))?;
    } else {
        let mut buf = Vec::new();
        csv_out::write_curve_csv(&feed, &mut buf).map_err(|e| crate::BadInput::new(format!("{}: {e}", args.csv.display())))?;
        write_atomic(&args.csv, &buf)?;
    }
    Ok(())
}
