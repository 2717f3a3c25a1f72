//! The test report (SPEC "Report"): standard quantities of a flexural test from a feed,
//! with their uncertainties, a QC section, the curve as CSV and plots.
//!
//! `tagdeflect report FEED --config FILE --standard astm-c1609|astm-c1856|en-14651 --out DIR`
//! writes `report.html` (self-contained, plots inline as SVG), `report.json`, `curve.csv`
//! and every plot as PNG and SVG; `tagdeflect export FEED --csv OUT` writes the CSV alone.
//! With `[report]` in the config, `run` writes a report of the run at its end ([`live`]).
//!
//! The steps: [`feed::Feed`] reads the feed; [`Curve`] holds load against net deflection
//! (ASTM) or CMOD (EN) in time order with σ and does the numerics (smoothing, crossings,
//! area, first peak); [`c1609`] and [`en14651`] compute each standard's quantities;
//! [`qc`] summarises the feed's health; `csv`, `plots` and `html` write the outputs.

pub mod c1609;
pub mod config;
pub mod csv_out;
pub mod curve;
pub mod en14651;
pub mod feed;
mod html;
mod plots;
pub mod qc;

pub use config::{BeamConfig, ReportConfig};
pub use curve::Curve;
pub use feed::Feed;

use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

use tagdeflect_core::rig::TagRole;
use tagdeflect_core::rig::{SpecimenConfig, WorldConfig};

/// The standard a report follows.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
pub enum Standard {
    /// ASTM C1609/C1609M: fibre-reinforced concrete, third-point loading, net deflection.
    #[serde(rename = "astm-c1609")]
    #[cfg_attr(feature = "clap", value(name = "astm-c1609"))]
    AstmC1609,
    /// ASTM C1856/C1856M (UHPC): the flexural test of C1609 on the specimens C1856 calls
    /// for; the quantities are C1609's, the geometry is taken from the config.
    #[serde(rename = "astm-c1856")]
    #[cfg_attr(feature = "clap", value(name = "astm-c1856"))]
    AstmC1856,
    /// EN 14651: notched beam, three-point loading, CMOD.
    #[serde(rename = "en-14651")]
    #[cfg_attr(feature = "clap", value(name = "en-14651"))]
    En14651,
}

impl Standard {
    /// The name as on the command line and in `report.json`.
    pub fn id(self) -> &'static str {
        match self {
            Standard::AstmC1609 => "astm-c1609",
            Standard::AstmC1856 => "astm-c1856",
            Standard::En14651 => "en-14651",
        }
    }

    /// The standard's title.
    pub fn title(self) -> &'static str {
        match self {
            Standard::AstmC1609 => {
                "ASTM C1609/C1609M — Flexural Performance of Fiber-Reinforced Concrete (Using Beam With Third-Point Loading)"
            }
            Standard::AstmC1856 => {
                "ASTM C1856/C1856M — Fabricating and Testing Specimens of Ultra-High Performance Concrete (flexure per ASTM C1609)"
            }
            Standard::En14651 => {
                "EN 14651 — Test method for metallic fibre concrete: flexural tensile strength (limit of proportionality, residual)"
            }
        }
    }
}

/// A reported value with its 1-σ uncertainty (`{"value", "sigma", "unit"}` in `report.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Quantity {
    /// The value.
    pub value: f64,
    /// Its 1-σ uncertainty.
    pub sigma: f64,
    /// Its unit.
    pub unit: String,
}

impl Quantity {
    /// A value in `unit`.
    pub fn new(value: f64, sigma: f64, unit: &str) -> Self {
        Self { value, sigma, unit: unit.to_string() }
    }
}

/// One line of a standard's results.
#[derive(Debug, Clone, PartialEq)]
pub struct Entry {
    /// The `report.json` key (SPEC).
    pub key: &'static str,
    /// Symbol as the standard writes it (HTML).
    pub symbol: &'static str,
    /// What it is, in words.
    pub name: &'static str,
    /// The value, or why it could not be determined.
    pub result: Result<Quantity, String>,
    /// How it is determined (formula, method), in words.
    pub method: String,
    /// The clause of the standard the definition follows.
    pub clause: &'static str,
}

/// Errors of the report.
#[derive(Debug, thiserror::Error)]
pub enum ReportError {
    /// A feed line that cannot be read.
    #[error("{}:{line}: not a feed line: {message}", path.display())]
    BadLine {
        /// The feed file.
        path: PathBuf,
        /// 1-based line.
        line: usize,
        /// What is wrong.
        message: String,
    },
    /// A file that cannot be read or written.
    #[error("{}: {message}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// What failed.
        message: String,
    },
    /// The feed lacks what the standard needs.
    #[error("{}: {message}", path.display())]
    Data {
        /// The feed file.
        path: PathBuf,
        /// What is missing.
        message: String,
    },
    /// The config lacks what the report needs.
    #[error("{}: {message}", path.display())]
    Config {
        /// The config file.
        path: PathBuf,
        /// What is missing.
        message: String,
    },
    /// Drawing a plot failed.
    #[error("plot {name}: {message}")]
    Plot {
        /// The plot.
        name: String,
        /// What failed.
        message: String,
    },
}

/// What the report needs of the rig: the world's up direction (deflection is along it) and
/// the specimen — its tags' roles and `[specimen.beam]`.
#[derive(Debug, Clone, PartialEq)]
pub struct TestRig {
    /// `[world]`.
    pub world: WorldConfig,
    /// `[specimen]`.
    pub specimen: SpecimenConfig,
    /// `[[gauge]]`.
    pub gauges: Vec<tagdeflect_estimate::gauges::GaugeConfig>,
}

impl TestRig {
    /// Role of a specimen tag.
    pub fn role_of(&self, id: u32) -> Option<TagRole> {
        self.specimen.role_of(id)
    }
}

/// A computed report.
#[derive(Debug, Clone)]
pub struct Report {
    /// The standard.
    pub standard: Standard,
    /// The specimen's geometry (from the config).
    pub beam: BeamConfig,
    /// The standard's quantities in the standard's order.
    pub entries: Vec<Entry>,
    /// The curve the quantities come from.
    pub curve: Curve,
    /// What the curve's `x` is (e.g. `net deflection` or `CMOD (gauge cmod)`).
    pub x_name: String,
    /// Short name of `x` for axis labels and the CSV (e.g. `net deflection`).
    pub x_axis: String,
    /// Where `x` and its σ come from, in words.
    pub x_source: String,
    /// The QC section.
    pub qc: qc::Qc,
    /// Notes on the specimen and the standard (geometry, unchecked clauses).
    pub notes: Vec<String>,
    /// Where the feed was read.
    pub feed_path: PathBuf,
    /// Report options used.
    pub options: ReportConfig,
}

/// The statement every report carries about the clauses cited.
pub const CLAUSES_UNCHECKED: &str = "The definitions and clause numbers cited follow the standards as the authors of this \
     software know them; the text of the standards was not at hand when this was written, so \
     the clause numbers and the definitions have not been checked against it. Check them \
     against your copy before relying on this report.";

/// Builds the report of a feed.
pub fn build(feed: &Feed, config: &TestRig, config_path: &Path, opts: &ReportConfig) -> Result<Report, ReportError> {
    let beam = config.specimen.beam.clone().ok_or_else(|| ReportError::Config {
        path: config_path.to_path_buf(),
        message:
            "the report needs the specimen's geometry: add [specimen.beam] with width_mm, depth_mm, span_mm (and notch_mm for EN 14651)"
                .into(),
    })?;
    let data_err = |message: String| ReportError::Data { path: feed.path.clone(), message };
    let (curve, x_name, x_axis, x_source) = match opts.standard {
        Standard::AstmC1609 | Standard::AstmC1856 => deflection_curve(feed, config, opts).map_err(data_err)?,
        Standard::En14651 => {
            if beam.notch_mm.is_none() {
                return Err(ReportError::Config {
                    path: config_path.to_path_buf(),
                    message: "EN 14651 tests notched beams: give [specimen.beam] notch_mm".into(),
                });
            }
            cmod_curve(feed, config, opts).map_err(data_err)?
        }
    };
    let entries = match opts.standard {
        Standard::AstmC1609 | Standard::AstmC1856 => c1609::compute(&curve, &beam),
        Standard::En14651 => en14651::compute(&curve, &beam),
    };
    let mut notes = Vec::new();
    match opts.standard {
        Standard::AstmC1609 => notes.push(format!(
            "Geometry from the config ([specimen.beam]): b = {} mm, d = {} mm, L = {} mm; third-point loading assumed (four-point bending, loads at L/3).",
            beam.width_mm, beam.depth_mm, beam.span_mm
        )),
        Standard::AstmC1856 => notes.push(format!(
            "ASTM C1856 refers the flexural test to ASTM C1609 with specimens of its own; the quantities below are C1609's, computed with the geometry of the config ([specimen.beam]): b = {} mm, d = {} mm, L = {} mm. Whether these dimensions are the ones C1856 calls for was not checked.",
            beam.width_mm, beam.depth_mm, beam.span_mm
        )),
        Standard::En14651 => notes.push(format!(
            "Geometry from the config ([specimen.beam]): b = {} mm, depth {} mm, notch {} mm, h_sp = {} mm, l = {} mm; three-point loading of a notched beam assumed.",
            beam.width_mm,
            beam.depth_mm,
            beam.notch_mm.unwrap_or(0.0),
            beam.ligament_mm(),
            beam.span_mm
        )),
    }
    notes.push(CLAUSES_UNCHECKED.to_string());
    let qc = qc::Qc::of(feed, config, &curve, &x_name);
    Ok(Report {
        standard: opts.standard,
        beam,
        entries,
        curve,
        x_name,
        x_axis,
        x_source,
        qc,
        notes,
        feed_path: feed.path.clone(),
        options: opts.clone(),
    })
}

/// The curve's columns as they are gathered from the feed.
struct Columns {
    t: Vec<i64>,
    p: Vec<f64>,
    x: Vec<f64>,
    sx: Vec<Option<f64>>,
}

fn gauge_columns(feed: &Feed, name: &str) -> Columns {
    let mut c = Columns { t: vec![], p: vec![], x: vec![], sx: vec![] };
    for l in &feed.lines {
        if let (Some(p), Some(g)) = (l.load_kn, l.gauges.get(name)) {
            c.t.push(l.t_ns);
            c.p.push(p);
            c.x.push(g.value);
            c.sx.push(g.sigma);
        }
    }
    c
}

fn curve_of(c: Columns, ref_sigma: f64, opts: &ReportConfig, what: &'static str) -> Result<Curve, String> {
    Curve::new(c.t, c.p, c.x, c.sx, ref_sigma, opts.smooth_points, opts.load_resolution_kn.unwrap_or(0.0), what).map_err(|e| e.to_string())
}

/// Load against net deflection: a gauge when asked for, else the feed's `net_deflection_mm`
/// with σ propagated from the role tags' `sigma_mm` along `world.up`.
fn deflection_curve(feed: &Feed, config: &TestRig, opts: &ReportConfig) -> Result<(Curve, String, String, String), String> {
    // Asked for, else the config's `net_deflection` gauge when the feed carries it (its σ
    // comes from the tags' covariance), else the feed's net_deflection_mm.
    let configured = config
        .gauges
        .iter()
        .find(|g| g.kind == tagdeflect_estimate::gauges::GaugeKind::NetDeflection && feed.gauge_names().contains(&g.name))
        .map(|g| g.name.clone());
    if let Some(g) = opts.deflection_gauge.as_ref().or(configured.as_ref()) {
        if !feed.gauge_names().contains(g) {
            return Err(format!("no line carries the gauge `{g}` (gauges in the feed: {:?})", feed.gauge_names()));
        }
        let curve = curve_of(gauge_columns(feed, g), 0.0, opts, "deflection")?;
        return Ok((curve, format!("net deflection (gauge {g})"), "net deflection".into(), format!("gauge `{g}` of the feed, with its σ")));
    }
    let up = config.world.up;
    let down_sigma = |s: [f64; 3]| ((up[0] * s[0]).powi(2) + (up[1] * s[1]).powi(2) + (up[2] * s[2]).powi(2)).sqrt();
    // σ of each role tag's zero reference: its σ in the first line that solved it.
    let mut first_sigma: std::collections::BTreeMap<u32, f64> = Default::default();
    let mut c = Columns { t: vec![], p: vec![], x: vec![], sx: vec![] };
    let mut any_net = false;
    for l in &feed.lines {
        for t in &l.tags {
            if let Some(s) = t.sigma_mm {
                first_sigma.entry(t.id).or_insert(down_sigma(s));
            }
        }
        let Some(net) = l.net_deflection_mm else { continue };
        any_net = true;
        let Some(p) = l.load_kn else { continue };
        c.t.push(l.t_ns);
        c.p.push(p);
        c.x.push(net);
        c.sx.push(role_sigma(l, config, &down_sigma));
    }
    if !any_net {
        return Err("no line carries net_deflection_mm: give the specimen tags roles (support and midspan) in the config, or a deflection gauge (--deflection-gauge)".into());
    }
    // Reference σ: the roles' first-line σ combined like the net deflection itself.
    let group =
        |role: TagRole| -> Vec<f64> { first_sigma.iter().filter(|(id, _)| config.role_of(**id) == Some(role)).map(|(_, s)| *s).collect() };
    let comb = |v: Vec<f64>| if v.is_empty() { 0.0 } else { v.iter().map(|s| s * s).sum::<f64>() / (v.len() * v.len()) as f64 };
    let ref_sigma = (comb(group(TagRole::Midspan)) + comb(group(TagRole::Support))).sqrt();
    let curve = curve_of(c, ref_sigma, opts, "net deflection")?;
    Ok((
        curve,
        "net deflection".into(),
        "net deflection".into(),
        "the feed's net_deflection_mm (midspan tags relative to the support tags); σ per point from the tags' sigma_mm along world.up, \
         midspan and support tags taken as independent, plus the σ of each tag's zero reference (its first solved frame set)"
            .into(),
    ))
}

/// σ of a line's net deflection from its role tags, `None` when a role tag has no σ.
fn role_sigma(l: &feed::FeedRecord, config: &TestRig, down_sigma: &dyn Fn([f64; 3]) -> f64) -> Option<f64> {
    let mut mid = Vec::new();
    let mut sup = Vec::new();
    for t in &l.tags {
        match config.role_of(t.id) {
            Some(TagRole::Midspan) => mid.push(down_sigma(t.sigma_mm?)),
            Some(TagRole::Support) => sup.push(down_sigma(t.sigma_mm?)),
            None => {}
        }
    }
    if mid.is_empty() || sup.is_empty() {
        return None;
    }
    let var = |v: &[f64]| v.iter().map(|s| s * s).sum::<f64>() / (v.len() * v.len()) as f64;
    Some((var(&mid) + var(&sup)).sqrt())
}

/// The CMOD gauge: the one asked for, else the config's only `opening` gauge in the feed,
/// else `cmod`, else the only gauge named like an opening.
pub fn cmod_gauge_name(feed: &Feed, config: &TestRig, asked: Option<&str>) -> Result<String, String> {
    let names = feed.gauge_names();
    let openings: Vec<&str> = config
        .gauges
        .iter()
        .filter(|g| g.kind == tagdeflect_estimate::gauges::GaugeKind::Opening && names.contains(&g.name))
        .map(|g| g.name.as_str())
        .collect();
    if let (None, [one]) = (asked, openings.as_slice()) {
        return Ok(one.to_string());
    }
    if let Some(a) = asked {
        return if names.iter().any(|n| n == a) {
            Ok(a.to_string())
        } else {
            Err(format!("no line carries the CMOD gauge `{a}` (gauges in the feed: {names:?})"))
        };
    }
    if let Some(n) = names.iter().find(|n| n.eq_ignore_ascii_case("cmod")) {
        return Ok(n.clone());
    }
    let like: Vec<&String> = names.iter().filter(|n| n.to_lowercase().contains("cmod") || n.to_lowercase().contains("opening")).collect();
    match like.as_slice() {
        [one] => Ok((*one).clone()),
        [] => Err(format!(
            "EN 14651 needs the CMOD: no gauge named `cmod` in the feed (gauges: {names:?}); configure an `opening` gauge across the notch or name one with --cmod-gauge"
        )),
        more => Err(format!("several gauges could be the CMOD ({more:?}): name one with --cmod-gauge")),
    }
}

fn cmod_curve(feed: &Feed, config: &TestRig, opts: &ReportConfig) -> Result<(Curve, String, String, String), String> {
    let name = cmod_gauge_name(feed, config, opts.cmod_gauge.as_deref())?;
    let curve = curve_of(gauge_columns(feed, &name), 0.0, opts, "CMOD")?;
    Ok((
        curve,
        format!("CMOD (gauge {name})"),
        "CMOD".into(),
        format!("gauge `{name}` of the feed (an opening across the notch), with its σ"),
    ))
}

/// Writes a file through a temporary sibling and a rename: a reader never sees half a file,
/// and an older file of the same name stays whole until the new one is complete.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), ReportError> {
    let io = |e: std::io::Error| ReportError::Io { path: path.to_path_buf(), message: e.to_string() };
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(io)?;
    }
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let tmp = path.with_file_name(format!(".{name}.tmp"));
    std::fs::write(&tmp, bytes).map_err(io)?;
    std::fs::rename(&tmp, path).map_err(io)
}

/// Writes every output of a report into `dir`; returns the files written.
pub fn write(report: &Report, feed: &Feed, dir: &Path) -> Result<Vec<PathBuf>, ReportError> {
    std::fs::create_dir_all(dir)
        .map_err(|e| ReportError::Io { path: dir.to_path_buf(), message: format!("cannot create the folder: {e}") })?;
    let mut files = Vec::new();
    let mut put = |name: &str, bytes: &[u8]| -> Result<(), ReportError> {
        let p = dir.join(name);
        write_atomic(&p, bytes)?;
        files.push(p);
        Ok(())
    };
    let mut csv_bytes = Vec::new();
    csv_out::write_curve_csv(feed, &mut csv_bytes).map_err(|e| ReportError::Io { path: dir.join("curve.csv"), message: e.to_string() })?;
    put("curve.csv", &csv_bytes)?;
    let plots = plots::draw_all(report, feed)?;
    for p in &plots {
        put(&format!("{}.svg", p.name), p.svg.as_bytes())?;
        put(&format!("{}.png", p.name), &p.png)?;
    }
    let json = serde_json::to_string_pretty(&to_json(report)).expect("report serialises");
    put("report.json", json.as_bytes())?;
    put("report.html", html::render(report, &plots).as_bytes())?;
    Ok(files)
}

/// `report.json`: every quantity as `{"value", "sigma", "unit"}` under the SPEC keys, plus
/// `standard`, `specimen`, `qc`, and how each value was found.
pub fn to_json(report: &Report) -> serde_json::Value {
    use serde_json::{json, Map, Value};
    let mut root = Map::new();
    root.insert("standard".into(), json!(report.standard.id()));
    root.insert("standard_title".into(), json!(report.standard.title()));
    let b = &report.beam;
    let mut spec = json!({
        "width_mm": b.width_mm, "depth_mm": b.depth_mm, "span_mm": b.span_mm,
        "source": "config [specimen.beam]",
        "loading": match report.standard { Standard::En14651 => "three-point, notched at midspan", _ => "four-point, loads at the third points" },
    });
    if let Some(n) = b.notch_mm {
        spec["notch_mm"] = json!(n);
        spec["h_sp_mm"] = json!(b.ligament_mm());
    }
    root.insert("specimen".into(), spec);
    let mut undetermined = Map::new();
    let mut defs = Map::new();
    for e in &report.entries {
        match &e.result {
            Ok(q) => {
                root.insert(e.key.into(), serde_json::to_value(q).expect("quantity"));
            }
            Err(why) => {
                undetermined.insert(e.key.into(), json!(why));
            }
        }
        defs.insert(e.key.into(), json!({"name": e.name, "method": e.method, "clause": e.clause, "checked_against_text": false}));
    }
    root.insert("undetermined".into(), Value::Object(undetermined));
    root.insert("definitions".into(), Value::Object(defs));
    let c = &report.curve;
    root.insert(
        "curve".into(),
        json!({
            "x": report.x_name, "x_source": report.x_source, "points": c.len(),
            "smooth_points": c.smooth_points,
            "load_sigma_kN": c.load_sigma, "load_noise_kN": c.load_noise,
            "load_resolution_kN": report.options.load_resolution_kn.unwrap_or(0.0),
            "x_scatter_mm": c.x_noise, "x_reference_sigma_mm": c.x_ref_sigma,
            "max_x_mm": c.xs.iter().cloned().fold(f64::NEG_INFINITY, f64::max),
        }),
    );
    root.insert("notes".into(), json!(report.notes));
    root.insert("feed".into(), json!(report.feed_path.display().to_string()));
    root.insert("qc".into(), serde_json::to_value(&report.qc).expect("qc"));
    Value::Object(root)
}
