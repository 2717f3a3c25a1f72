//! The build of a report: the curve the standard needs picked from the feed (net deflection
//! or a gauge for ASTM, the CMOD gauge for EN 14651) with its σ, the standard's quantities,
//! the notes and the QC section.

use std::path::Path;

use tagdeflect_core::gauge::GaugeKind;
use tagdeflect_core::rig::TagRole;

use crate::config::ReportConfig;
use crate::curve::{Curve, CurveError};
use crate::error::ReportError;
use crate::feed_reader::Feed;
use crate::report::{Entry, Report, TestRig};
use crate::standard::Standard;
use crate::tag_stats::TagStats;
use crate::utm_stream::UtmStream;
use crate::{c1609, en14651, qc, validity};

/// Where the geometry comes from outside a test folder, as the notes say it (a test folder's
/// report names its own sources in its place, `test_folder`).
pub(crate) const GEOMETRY_FROM_CONFIG: &str = "the config ([specimen.beam])";

/// Why the curve a standard needs cannot be taken from a feed (a [`ReportError::Data`] of
/// the feed).
#[derive(Debug, thiserror::Error)]
pub enum CurveChoiceError {
    /// The deflection gauge asked for (or configured) is in no line of the feed.
    #[error("no line carries the gauge `{gauge}` (gauges in the feed: {available:?})")]
    NoGauge {
        /// The gauge asked for.
        gauge: String,
        /// The gauges the feed carries.
        available: Vec<String>,
    },
    /// Neither roles nor a deflection gauge give the net deflection.
    #[error(
        "no line carries net_deflection_mm: give the specimen tags roles (support and midspan) in the config, or a deflection gauge (--deflection-gauge)"
    )]
    NoNetDeflection,
    /// The CMOD gauge asked for is not among the available gauges.
    #[error("no line carries the CMOD gauge `{gauge}` (gauges in the feed: {available:?})")]
    NoCmodGauge {
        /// The gauge asked for.
        gauge: String,
        /// The gauges available.
        available: Vec<String>,
    },
    /// No gauge looks like the CMOD.
    #[error(
        "EN 14651 needs the CMOD: no gauge named `cmod` in the feed (gauges: {available:?}); configure an `opening` gauge across the notch or name one with --cmod-gauge"
    )]
    NoCmod {
        /// The gauges available.
        available: Vec<String>,
    },
    /// Several gauges look like the CMOD.
    #[error("several gauges could be the CMOD ({candidates:?}): name one with --cmod-gauge")]
    SeveralCmod {
        /// The gauges named like an opening.
        candidates: Vec<String>,
    },
    /// The gathered columns do not make a curve.
    #[error(transparent)]
    Curve(#[from] CurveError),
}

/// Builds the report of a feed, with the load-based values from the UTM's own samples when
/// `utm` is given (SPEC "Report").
pub fn build(
    feed: &Feed,
    utm: Option<&UtmStream>,
    config: &TestRig,
    config_path: &Path,
    opts: &ReportConfig,
) -> Result<Report, ReportError> {
    let beam = config.specimen.beam.clone().ok_or_else(|| ReportError::Config {
        path: config_path.to_path_buf(),
        message:
            "the report needs the specimen's geometry: add [specimen.beam] with width_mm, depth_mm, span_mm (and notch_mm for EN 14651)"
                .into(),
    })?;
    let data_err = |e: CurveChoiceError| ReportError::Data { path: feed.path.clone(), message: e.to_string() };
    // The tags are not held: read again, now that the config says which way is up.
    let tags = TagStats::of(feed, config)?;
    let (feed_curve, x_name, x_axis, x_source) = match opts.standard {
        Standard::AstmC1609 | Standard::AstmC1856 => deflection_curve(feed, config, &tags, opts).map_err(data_err)?,
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
    let mut notes = Vec::new();
    // The clock offset the feed reports (UTM time − camera time), its σ the alignment's.
    let clock = feed.summary.clock_offset_ms;
    let resolution = opts.load_resolution_kn.unwrap_or(0.0);
    let utm_shift_ns = match utm {
        Some(_) => clock.map_or(0, |c| (c.value * 1e6).round() as i64),
        None => 0,
    };
    let (curve, load_source) = match utm {
        Some(u) => {
            let (offset_ns, sigma_t) = (utm_shift_ns, clock.map_or(0.0, |c| c.sigma * 1e-3));
            let c = feed_curve
                .on_utm(&u.samples, offset_ns, sigma_t, resolution, opts.max_gap_s)
                .map_err(|e| ReportError::Data { path: u.path.clone(), message: e.to_string() })?;
            let align = match clock {
                Some(c) => format!(
                    "UTM times put on the cameras' clock with the feed's clock check ({:.1} ± {:.1} ms); its σ adds |d{}/dt|·σ_t to every point's σ",
                    c.value, c.sigma, x_axis
                ),
                None => "no clock check in the feed: UTM and camera clocks taken as one (no alignment σ)".to_string(),
            };
            let src = format!(
                "the UTM's own samples ({}: {} samples, every {:.1} ms), {x_axis} interpolated at their times from the feed; {align}",
                u.path.display(),
                u.samples.len(),
                1e3 * u.period_s()
            );
            (c, src)
        }
        None => {
            let period = feed_curve.load_period_s;
            notes.push(format!(
                "No UTM stream (utm.jsonl) was given: the loads are the feed's, sampled at the frame rate (every {:.0} ms). A peak \
                 between two frame sets is missed by up to the rise of the load over one frame period; that rise is in the σ of P1, \
                 Pp and F_L (r/√3). Give the UTM's own samples (--utm) for the peak as the machine saw it.",
                1e3 * period
            ));
            (feed_curve.clone(), format!("the feed's load_kN, sampled at the frame rate (every {:.0} ms)", 1e3 * period))
        }
    };
    let all = match opts.standard {
        Standard::AstmC1609 | Standard::AstmC1856 => c1609::compute(&curve, &beam),
        Standard::En14651 => en14651::compute(&curve, &beam),
    };
    let entries = method_results(all, opts.method.as_ref());
    let tol = |t: Option<f64>| t.map_or(String::new(), |t| format!(" ± {t}"));
    match opts.standard {
        Standard::AstmC1609 => notes.push(format!(
            "Geometry from {GEOMETRY_FROM_CONFIG}: b = {}{} mm, d = {}{} mm, L = {}{} mm; third-point loading assumed (four-point bending, loads at L/3).",
            beam.width_mm, tol(beam.width_tol_mm), beam.depth_mm, tol(beam.depth_tol_mm), beam.span_mm, tol(beam.span_tol_mm)
        )),
        Standard::AstmC1856 => notes.push(format!(
            "ASTM C1856 refers the flexural test to ASTM C1609 with specimens of its own; the quantities below are C1609's, computed with the geometry of {GEOMETRY_FROM_CONFIG}: b = {}{} mm, d = {}{} mm, L = {}{} mm. Whether these dimensions are the ones C1856 calls for was not checked.",
            beam.width_mm, tol(beam.width_tol_mm), beam.depth_mm, tol(beam.depth_tol_mm), beam.span_mm, tol(beam.span_tol_mm)
        )),
        Standard::En14651 => notes.push(format!(
            "Geometry from {GEOMETRY_FROM_CONFIG}: b = {}{} mm, depth {}{} mm, notch {}{} mm, h_sp = {} mm, l = {}{} mm; three-point loading of a notched beam assumed.",
            beam.width_mm,
            tol(beam.width_tol_mm),
            beam.depth_mm,
            tol(beam.depth_tol_mm),
            beam.notch_mm.unwrap_or(0.0),
            tol(beam.notch_tol_mm),
            beam.ligament_mm(),
            beam.span_mm,
            tol(beam.span_tol_mm)
        )),
    }
    if [beam.width_tol_mm, beam.depth_tol_mm, beam.span_tol_mm].iter().all(Option::is_none) {
        notes.push("No tolerances of the dimensions in the config (width_tol_mm, depth_tol_mm, span_tol_mm): the stresses' σ take the dimensions as exact.".into());
    }
    let utm_gaps: Vec<(f64, f64)> = utm.map_or(Vec::new(), |u| {
        let t = &feed.columns.t_ns;
        let t0 = t[0];
        let off = utm_shift_ns;
        let (first, last) = (t[0], t[t.len() - 1]);
        u.gaps(opts.max_gap_s)
            .into_iter()
            .map(|(a, b)| (a - off, b - off))
            .filter(|&(a, b)| b > first && a < last)
            .map(|(a, b)| ((a - t0) as f64 * 1e-9, (b - t0) as f64 * 1e-9))
            .collect()
    });
    let mut qc = qc::Qc::of(feed, config, tags, &feed_curve, &x_name, opts);
    if let Some(u) = utm {
        qc.warnings.extend(u.warnings.iter().cloned());
        let t = &feed.columns.t_ns;
        if u.samples.first().is_some_and(|s| s.t_ns > t[0]) || u.samples.last().is_some_and(|s| s.t_ns < t[t.len() - 1]) {
            qc.warnings
                .push(format!("the UTM stream {} does not cover the whole feed: the ends of the curve have no load", u.path.display()));
        }
    }
    qc.warnings.extend(glitch_warnings(&feed_curve, "feed line"));
    if utm.is_some() {
        qc.warnings.extend(glitch_warnings(&curve, "UTM sample"));
    }
    let utm_outages_s: f64 = qc.utm_outages.iter().map(|o| o.duration_s).sum();
    let validity = validity::check(&validity::Input {
        standard: opts.standard,
        response: opts.response,
        beam: &beam,
        feed_curve: &feed_curve,
        load_curve: &curve,
        feed,
        x_name: &x_name,
        max_gap_s: opts.max_gap_s,
        utm_gaps,
        utm_outages_s,
        method: opts.method.as_ref(),
    });
    let mut lab = opts.lab.clone();
    if lab.test_date.is_none() {
        lab.test_date = Some(chrono::DateTime::from_timestamp_nanos(feed.columns.t_ns[0]).format("%Y-%m-%d").to_string());
    }
    if let Some((k, n)) = feed.run {
        notes.insert(0, format!("Run {k} of {n} in {} (the feed restarts: --allow-restarts reports each run on its own).", feed.label()));
    }
    Ok(Report {
        standard: opts.standard,
        beam,
        entries,
        curve,
        feed_curve,
        x_name,
        x_axis,
        x_source,
        load_source,
        qc,
        validity,
        lab,
        notes,
        beam_source: "config [specimen.beam]".into(),
        feed_path: feed.path.clone(),
        run: feed.run,
        utm_path: utm.map(|u| u.path.clone()),
        utm_shift_ns,
        options: opts.clone(),
        inputs: Vec::new(),
        test: None,
        control: None,
        dimension_sources: Default::default(),
    })
}

/// One QC warning per glitched load reading left out of `curve` (at most 10, then a count).
/// The results the test's method names, in its order (every result of the standard without a
/// method). A method naming a result its standard does not give is refused when it is read.
fn method_results(all: Vec<Entry>, method: Option<&tagdeflect_core::method::Method>) -> Vec<Entry> {
    match method {
        Some(m) => m.results.iter().filter_map(|r| all.iter().find(|e| e.key == r.as_str()).cloned()).collect(),
        None => all,
    }
}

fn glitch_warnings(curve: &Curve, what: &str) -> Vec<String> {
    let t0 = curve.t_ns.first().copied().unwrap_or(0);
    let mut out: Vec<String> = curve
        .load_outliers
        .iter()
        .take(10)
        .map(|&(t, p)| {
            format!(
                "a glitched load of {} kN ({what} at {:.3} s) left out: a jump no testing machine makes within one sample and back; never the peak",
                crate::feed_reader::fmt_g(p),
                (t - t0) as f64 * 1e-9
            )
        })
        .collect();
    if curve.load_outliers.len() > 10 {
        out.push(format!("{} glitched loads ({what}s) left out in all", curve.load_outliers.len()));
    }
    out
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
    let (cols, Some(g)) = (&feed.columns, feed.columns.gauge(name)) else { return c };
    for k in 0..cols.len() {
        if let (Some(p), false) = (cols.load(k), g.value[k].is_nan()) {
            c.t.push(cols.t_ns[k]);
            c.p.push(p);
            c.x.push(g.value[k]);
            c.sx.push(Some(g.sigma[k]).filter(|s| !s.is_nan()));
        }
    }
    c
}

fn curve_of(c: Columns, ref_sigma: f64, opts: &ReportConfig, what: &'static str) -> Result<Curve, CurveError> {
    Curve::new(c.t, c.p, c.x, c.sx, ref_sigma, opts.smooth_points, opts.load_resolution_kn.unwrap_or(0.0), what)
}

/// Load against net deflection: a gauge when asked for, else the feed's `net_deflection_mm`
/// with σ propagated from the role tags' `sigma_mm` along `world.up`.
fn deflection_curve(
    feed: &Feed,
    config: &TestRig,
    tags: &TagStats,
    opts: &ReportConfig,
) -> Result<(Curve, String, String, String), CurveChoiceError> {
    // Asked for, else the config's `net_deflection` gauge when the feed carries it (its σ
    // comes from the tags' covariance), else the feed's net_deflection_mm.
    let configured =
        config.gauges.iter().find(|g| g.kind == GaugeKind::NetDeflection && feed.gauge_names().contains(&g.name)).map(|g| g.name.clone());
    if let Some(g) = opts.deflection_gauge.as_ref().or(configured.as_ref()) {
        if !feed.gauge_names().contains(g) {
            return Err(CurveChoiceError::NoGauge { gauge: g.clone(), available: feed.gauge_names() });
        }
        let (ref_sigma, ref_text) = gauge_reference_sigma(feed, g);
        let curve = curve_of(gauge_columns(feed, g), ref_sigma, opts, "deflection")?;
        return Ok((
            curve,
            format!("net deflection (gauge {g})"),
            "net deflection".into(),
            format!("gauge `{g}` of the feed, with its σ{ref_text}"),
        ));
    }
    // σ of each role tag's zero reference: its σ in the first line that solved it.
    let first_sigma = &tags.first_sigma_up_mm;
    let cols = &feed.columns;
    let mut c = Columns { t: vec![], p: vec![], x: vec![], sx: vec![] };
    let mut any_net = false;
    for k in 0..cols.len() {
        let net = cols.net_deflection_mm[k];
        if net.is_nan() {
            continue;
        }
        any_net = true;
        let Some(p) = cols.load(k) else { continue };
        c.t.push(cols.t_ns[k]);
        c.p.push(p);
        c.x.push(net);
        c.sx.push(tags.role_sigma(k));
    }
    if !any_net {
        return Err(CurveChoiceError::NoNetDeflection);
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

/// The CMOD gauge of `feed`: [`choose_cmod_gauge`] among the gauges the feed carries.
fn cmod_gauge_name(feed: &Feed, config: &TestRig, asked: Option<&str>) -> Result<String, CurveChoiceError> {
    choose_cmod_gauge(&config.gauges, &feed.gauge_names(), asked)
}

/// Which gauge is the CMOD (EN 14651) — one rule for the report and the daemon (the live
/// page's load–CMOD curve, `[output.auto_test]`'s 4 mm end): the one `asked` for (`[report]
/// cmod_gauge`, `--cmod-gauge`; it must be `available`), else the config's only `opening`
/// gauge among `available`, else the gauge named `cmod`, else the only one named like an
/// opening. `available`: the gauges a feed carries (the report), or all configured ones.
pub fn choose_cmod_gauge(
    gauges: &[tagdeflect_core::gauge::GaugeConfig],
    available: &[String],
    asked: Option<&str>,
) -> Result<String, CurveChoiceError> {
    let names = available;
    let openings: Vec<&str> =
        gauges.iter().filter(|g| g.kind == GaugeKind::Opening && names.contains(&g.name)).map(|g| g.name.as_str()).collect();
    if let (None, [one]) = (asked, openings.as_slice()) {
        return Ok(one.to_string());
    }
    if let Some(a) = asked {
        return if names.iter().any(|n| n == a) {
            Ok(a.to_string())
        } else {
            Err(CurveChoiceError::NoCmodGauge { gauge: a.to_string(), available: names.to_vec() })
        };
    }
    if let Some(n) = names.iter().find(|n| n.eq_ignore_ascii_case("cmod")) {
        return Ok(n.clone());
    }
    let like: Vec<&String> = names.iter().filter(|n| n.to_lowercase().contains("cmod") || n.to_lowercase().contains("opening")).collect();
    match like.as_slice() {
        [one] => Ok((*one).clone()),
        [] => Err(CurveChoiceError::NoCmod { available: names.to_vec() }),
        more => Err(CurveChoiceError::SeveralCmod { candidates: more.iter().map(|n| (*n).clone()).collect() }),
    }
}

fn cmod_curve(feed: &Feed, config: &TestRig, opts: &ReportConfig) -> Result<(Curve, String, String, String), CurveChoiceError> {
    let name = cmod_gauge_name(feed, config, opts.cmod_gauge.as_deref())?;
    let (ref_sigma, ref_text) = gauge_reference_sigma(feed, &name);
    let curve = curve_of(gauge_columns(feed, &name), ref_sigma, opts, "CMOD")?;
    Ok((
        curve,
        format!("CMOD (gauge {name})"),
        "CMOD".into(),
        format!("gauge `{name}` of the feed (an opening across the notch), with its σ{ref_text}"),
    ))
}

/// σ of a gauge's zero reference, common to every point of its curve, and the words for the
/// curve's source. A test's lines (`test` set) count from the test's zero, whose σ the daemon
/// already put into every σ: 0. Otherwise the gauge counts from its tags' first solved frame
/// set, whose own error the lines' σ leaves out (it is an offset common to the run, see
/// `tagdeflect_estimate::gauges`): its σ is taken as the median σ of the gauge's first 20
/// lines after the reference (the reference's own line reads σ 0). Measured on the image-simulated notched test
/// (200 frame sets, no test): CMOD errors −0.018 mm on average with 0.012 mm scatter about
/// that against a line σ of 0.014 mm — the first frame set's error, carried by every line.
fn gauge_reference_sigma(feed: &Feed, name: &str) -> (f64, String) {
    if feed.summary.any_test {
        return (0.0, " (the test's zero σ included by the daemon)".into());
    }
    // The reference frame set's own line reads (nearly) σ 0: the median of the next 20 lines'.
    let Some(g) = feed.columns.gauge(name) else { return (0.0, String::new()) };
    let mut first: Vec<f64> =
        g.value.iter().zip(&g.sigma).filter(|(v, _)| !v.is_nan()).map(|(_, s)| *s).filter(|s| !s.is_nan()).take(21).collect();
    if first.len() < 2 {
        return (0.0, String::new());
    }
    let s = crate::curve::median(&mut first[1..]);
    (s, format!(", plus the σ of its zero reference ({s:.4} mm: the median σ of its first lines), common to every point"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::BeamConfig;
    use tagdeflect_core::method::{results_of, Method, SHIPPED};

    /// A softening curve to 3.5 mm of the gauge: every result of either standard determined.
    fn curve() -> Curve {
        let n = 1801;
        let x: Vec<f64> = (0..n).map(|i| 0.002 * i as f64).collect();
        let load: Vec<f64> = x.iter().map(|&x| if x <= 0.05 { 600.0 * x } else { 30.0 - 2.0 * x }).collect();
        let t_ns: Vec<i64> = (0..n as i64).map(|i| i * 100_000_000).collect();
        Curve::new(t_ns, load, x, vec![Some(0.001); n], 0.001, 5, 0.01, "deflection").unwrap()
    }

    /// The results a method may name are those the report computes, in today's order; a method
    /// naming fewer gives only those, in its order.
    #[test]
    fn a_report_gives_the_method_s_results_in_its_order() {
        let beam = BeamConfig { width_mm: 150.0, depth_mm: 150.0, span_mm: 450.0, notch_mm: Some(25.0), ..Default::default() };
        let keys = |e: &[Entry]| e.iter().map(|e| e.key).collect::<Vec<_>>();
        let (c, en) = (c1609::compute(&curve(), &beam), en14651::compute(&curve(), &beam));
        assert_eq!(keys(&c), results_of("astm-c1609"));
        assert_eq!(keys(&c), results_of("astm-c1856"));
        assert_eq!(keys(&en), results_of("en-14651"));
        for (name, text) in SHIPPED {
            let m = Method::parse(text).unwrap();
            let all = if m.standard == "en-14651" { en.clone() } else { c.clone() };
            assert_eq!(keys(&method_results(all.clone(), Some(&m))), keys(&all), "{name} gives what its standard gives");
        }
        let short = Method::parse(&SHIPPED[0].1.replace(
            r#"results = ["P1", "delta1", "f1", "Pp", "deltap", "fp", "P600", "P150", "f600", "f150", "T150", "RT150"]"#,
            r#"results = ["f150", "f1", "T150"]"#,
        ))
        .unwrap();
        let picked = method_results(c.clone(), Some(&short));
        assert_eq!(keys(&picked), ["f150", "f1", "T150"]);
        assert_eq!(picked[1], c[2], "the entry itself, unchanged");
    }
}
