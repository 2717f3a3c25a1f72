//! The report's plots, drawn with `plotters` into SVG (inline in the HTML, and a file) and
//! PNG. Text in the PNG needs a TrueType font: the first found of `$TAGDEFLECT_FONT` and the
//! usual Debian font paths (`fonts-dejavu-core`, installed by `scripts/setup.sh`).
//!
//! The curves are drawn through the points their pixels show (`plot_points`: per pixel
//! column the first, lowest, highest and last point; a marker once per pixel), so a long
//! feed costs the plots no more than a short one; the numbers come from the full curve.

use plotters::coord::Shift;
use plotters::prelude::*;
use std::sync::OnceLock;

use crate::curve::Curve;
use crate::error::ReportError;
use crate::feed_reader::Feed;
use crate::plot_points::{line_points, scatter_points};
use crate::report::Report;
use crate::standard::Standard;
use crate::{c1609, en14651};

/// One plot in both formats.
#[derive(Debug, Clone)]
pub struct Plot {
    /// File stem, e.g. `load_deflection`.
    pub name: String,
    /// Caption.
    pub title: String,
    /// The SVG document.
    pub svg: String,
    /// The PNG file's bytes.
    pub png: Vec<u8>,
}

const W: u32 = 960;
const H: u32 = 600;
const FONT: &str = "sans-serif";

const FONT_PATHS: [&str; 5] = [
    "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/TTF/DejaVuSans.ttf",
    "/usr/share/fonts/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/truetype/liberation/LiberationSans-Regular.ttf",
    "/usr/share/fonts/truetype/noto/NotoSans-Regular.ttf",
];

/// Registers a TrueType font for plot text once per process.
pub(crate) fn ensure_font() -> Result<(), ReportError> {
    static DONE: OnceLock<Result<(), NoFont>> = OnceLock::new();
    DONE.get_or_init(|| {
        let mut tried: Vec<String> = Vec::new();
        let from_env = std::env::var("TAGDEFLECT_FONT").ok();
        for p in from_env.iter().map(String::as_str).chain(FONT_PATHS) {
            tried.push(p.to_string());
            let Ok(bytes) = std::fs::read(p) else { continue };
            // The font lives as long as the process (plotters keeps a 'static reference).
            let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
            if plotters::style::register_font(FONT, FontStyle::Normal, bytes).is_ok() {
                tracing::debug!("plot font: {p}");
                return Ok(());
            }
        }
        Err(NoFont { tried: tried.join(", ") })
    })
    .clone()
    .map_err(|e| ReportError::Plot { name: "font".into(), message: e.to_string() })
}

/// No font file of the list could be read and registered.
#[derive(Debug, Clone, thiserror::Error)]
#[error(
    "no TrueType font for the plots' text (tried {tried}): install Debian's fonts-dejavu-core (scripts/setup.sh does) or set TAGDEFLECT_FONT"
)]
struct NoFont {
    /// The paths tried, comma-separated.
    tried: String,
}

/// Why drawing a plot failed.
#[derive(Debug, thiserror::Error)]
pub(crate) enum PlotError {
    /// The drawing backend failed: its message (the error type differs per backend, SVG or
    /// bitmap).
    #[error("{0}")]
    Draw(String),
    /// The PNG could not be encoded.
    #[error(transparent)]
    Png(#[from] png::EncodingError),
}

/// A drawing backend's error as a [`PlotError`].
pub(crate) fn err<E: std::fmt::Display>(e: E) -> PlotError {
    PlotError::Draw(e.to_string())
}

/// A marked point on the curve.
struct Mark {
    x: f64,
    load: f64,
    label: String,
}

/// What the curve plot shows besides the curve.
struct Decor {
    marks: Vec<Mark>,
    verticals: Vec<(f64, String)>,
    area_to: Option<f64>,
}

fn decor(report: &Report) -> Decor {
    let c = &report.curve;
    let mut marks = Vec::new();
    let mut verticals = Vec::new();
    let mut area_to = None;
    match report.standard {
        Standard::AstmC1609 | Standard::AstmC1856 => {
            let l = report.beam.span_mm;
            if let Some(j) = c1609::first_peak(c) {
                marks.push(Mark { x: c.xs[j], load: c.load[j], label: "P1".into() });
            }
            let k = c.peak_index();
            marks.push(Mark { x: c.xs[k], load: c.load[k], label: "Pp".into() });
            for (div, name) in [(600.0, "L/600"), (150.0, "L/150")] {
                verticals.push((l / div, name.to_string()));
                if let Some((p, _, _)) = c.load_at(l / div) {
                    marks.push(Mark { x: l / div, load: p, label: format!("P{}", div as u32) });
                }
            }
            if c.crossing(l / 150.0).is_some() {
                area_to = Some(l / 150.0);
            }
        }
        Standard::En14651 => {
            verticals.push((en14651::LOP_CMOD_MM, "0.05".into()));
            if let Ok(l) = en14651::limit_of_proportionality(c, en14651::LOP_CMOD_MM) {
                marks.push(Mark { x: l.cmod_mm, load: l.load_kn, label: "FL".into() });
            }
            for (j, &cmod) in en14651::CMOD_J_MM.iter().enumerate() {
                verticals.push((cmod, format!("CMOD{}", j + 1)));
                if let Some((p, _, _)) = c.load_at(cmod) {
                    marks.push(Mark { x: cmod, load: p, label: format!("FR{}", j + 1) });
                }
            }
        }
    }
    marks.extend(event_marks(report));
    Decor { marks, verticals, area_to }
}

/// The test's marks and crack entries on the curve, at the point of their time on the
/// curve's clock (`event_loads`; a mark's note as its label, cut to 24 characters).
fn event_marks(report: &Report) -> Vec<Mark> {
    let c = &report.curve;
    let on = crate::event_loads::OnCurve::of(report);
    let Some(t) = &report.test else { return Vec::new() };
    let (Some(&first), Some(&last)) = (c.t_ns.first(), c.t_ns.last()) else { return Vec::new() };
    t.events
        .iter()
        .filter(|e| matches!(e.kind.as_str(), "mark" | "crack") && (first..=last).contains(&on.time_ns(e.t_ns)))
        .filter_map(|e| {
            let j = c.t_ns.partition_point(|&tn| tn < on.time_ns(e.t_ns)).min(c.len() - 1);
            let text = e.note.as_deref().unwrap_or(e.kind.as_str());
            let label: String = text.chars().take(24).collect();
            (c.xs[j].is_finite() && c.load[j].is_finite()).then(|| Mark { x: c.xs[j], load: c.load[j], label })
        })
        .collect()
}

fn range(v: impl Iterator<Item = f64>) -> (f64, f64) {
    let (lo, hi) = v.filter(|x| x.is_finite()).fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), x| (a.min(x), b.max(x)));
    if !lo.is_finite() {
        return (0.0, 1.0);
    }
    let pad = ((hi - lo) * 0.05).max(1e-6);
    (lo - pad, hi + pad)
}

fn draw_curve<DB: DrawingBackend>(root: &DrawingArea<DB, Shift>, report: &Report, title: &str) -> Result<(), PlotError> {
    let c: &Curve = &report.curve;
    let d = decor(report);
    root.fill(&WHITE).map_err(err)?;
    let (x0, x1) = range(c.xs.iter().chain(&c.x).cloned().chain([0.0]).chain(d.verticals.iter().map(|v| v.0).filter(|v| {
        // Show a reference line only when the curve gets near it.
        let max = c.xs.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
        *v <= max * 1.2
    })));
    let (_, y1) = range(c.load.iter().cloned().chain([0.0]));
    let y0 = c.load.iter().cloned().fold(0.0f64, f64::min);
    let x_label = format!("{} [mm]", report.x_axis);
    let mut chart = ChartBuilder::on(root)
        .caption(title, (FONT, 22))
        .margin(14)
        .x_label_area_size(46)
        .y_label_area_size(62)
        .build_cartesian_2d(x0..x1, y0..y1 * 1.08)
        .map_err(err)?;
    chart
        .configure_mesh()
        .x_desc(x_label)
        .y_desc("load [kN]")
        .label_style((FONT, 15))
        .light_line_style(RGBColor(235, 235, 235))
        .draw()
        .map_err(err)?;
    if let Some(end) = d.area_to {
        let upto = c.xs.iter().cloned().zip(c.load.iter().cloned()).take_while(|(x, _)| *x < end);
        let pts = line_points(upto.chain(c.load_at(end).map(|(p, _, _)| (end, p))), |p| chart.backend_coord(p));
        chart
            .draw_series(AreaSeries::new(pts, 0.0, RGBColor(70, 130, 180).mix(0.18)))
            .map_err(err)?
            .label("T150 (area to L/150)")
            .legend(|(x, y)| Rectangle::new([(x, y - 5), (x + 18, y + 5)], RGBColor(70, 130, 180).mix(0.3).filled()));
    }
    let grey = RGBColor(150, 150, 150);
    let measured = scatter_points(c.x.iter().cloned().zip(c.load.iter().cloned()), |p| chart.backend_coord(p));
    chart
        .draw_series(measured.into_iter().map(|p| Circle::new(p, 2, grey.filled())))
        .map_err(err)?
        .label(format!("measured ({} points)", c.len()))
        .legend(move |(x, y)| Circle::new((x + 9, y), 3, grey.filled()));
    let blue = RGBColor(20, 70, 160);
    let smoothed = line_points(c.xs.iter().cloned().zip(c.load.iter().cloned()), |p| chart.backend_coord(p));
    chart
        .draw_series(LineSeries::new(smoothed, blue.stroke_width(2)))
        .map_err(err)?
        .label(format!("smoothed (up to {} points)", c.smooth_points))
        .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], blue.stroke_width(2)));
    for (v, name) in &d.verticals {
        if *v < x0 || *v > x1 {
            continue;
        }
        chart.draw_series(DashedLineSeries::new(vec![(*v, y0), (*v, y1 * 1.08)], 6, 4, grey.stroke_width(1))).map_err(err)?;
        chart.draw_series(std::iter::once(Text::new(name.clone(), (*v, y1 * 1.06), (FONT, 14).into_font().color(&grey)))).map_err(err)?;
    }
    let red = RGBColor(190, 30, 30);
    // Marks on the same point share one label ("P1 = Pp").
    let mut merged: Vec<Mark> = Vec::new();
    for m in d.marks {
        match merged.iter_mut().find(|o| (o.x - m.x).abs() < 1e-9 && (o.load - m.load).abs() < 1e-9) {
            Some(o) => o.label = format!("{} = {}", o.label, m.label),
            None => merged.push(m),
        }
    }
    for m in &merged {
        chart
            .draw_series(std::iter::once(
                EmptyElement::at((m.x, m.load))
                    + Cross::new((0, 0), 6, red.stroke_width(2))
                    + Text::new(m.label.clone(), (8, -18), (FONT, 15).into_font().color(&red)),
            ))
            .map_err(err)?;
    }
    draw_legend(&mut chart, SeriesLabelPosition::UpperRight)?;
    root.present().map_err(err)?;
    Ok(())
}

fn draw_time<DB: DrawingBackend>(root: &DrawingArea<DB, Shift>, report: &Report, feed: &Feed, title: &str) -> Result<(), PlotError> {
    let c = &report.feed_curve;
    let cols = &feed.columns;
    let t0 = cols.t_ns[0];
    let ts = |t: i64| (t - t0) as f64 * 1e-9;
    // The load from the UTM's samples or the feed's lines; each read twice (its range, then
    // its pixels) rather than held.
    let utm = report.curve.load_from_utm;
    let load = || {
        let from_utm = report.curve.t_ns.iter().zip(&report.curve.load).filter(move |_| utm);
        let from_feed = cols.t_ns.iter().zip(&cols.load_kn).filter(move |(_, p)| !utm && !p.is_nan());
        from_utm.chain(from_feed).map(|(&t, &p)| (ts(t), p))
    };
    let xs = || c.t_ns.iter().zip(&c.xs).map(|(&t, &x)| (ts(t), x));
    root.fill(&WHITE).map_err(err)?;
    let (tmin, tmax) = range(cols.t_ns.iter().map(|&t| ts(t)));
    let (p0, p1) = range(load().map(|p| p.1).chain([0.0]));
    let (x0, x1) = range(xs().map(|p| p.1).chain([0.0]));
    let mut chart = ChartBuilder::on(root)
        .caption(title, (FONT, 22))
        .margin(14)
        .x_label_area_size(46)
        .y_label_area_size(62)
        .right_y_label_area_size(62)
        .build_cartesian_2d(tmin..tmax, p0..p1)
        .map_err(err)?
        .set_secondary_coord(tmin..tmax, x0..x1);
    chart
        .configure_mesh()
        .x_desc("time [s]")
        .y_desc("load [kN]")
        .label_style((FONT, 15))
        .light_line_style(RGBColor(235, 235, 235))
        .draw()
        .map_err(err)?;
    chart.configure_secondary_axes().y_desc(format!("{} [mm]", report.x_axis)).label_style((FONT, 15)).draw().map_err(err)?;
    // UTM outages shaded.
    let shade = RGBColor(230, 120, 30).mix(0.15);
    for o in &report.qc.utm_outages {
        chart.draw_series(std::iter::once(Rectangle::new([(ts(o.from_t_ns), p0), (ts(o.to_t_ns), p1)], shade.filled()))).map_err(err)?;
    }
    let blue = RGBColor(20, 70, 160);
    let red = RGBColor(190, 30, 30);
    let load = line_points(load(), |p| chart.backend_coord(p));
    let xs = line_points(xs(), |p| chart.borrow_secondary().backend_coord(p));
    chart
        .draw_series(LineSeries::new(load, blue.stroke_width(2)))
        .map_err(err)?
        .label("load (left axis)")
        .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], blue.stroke_width(2)));
    chart
        .draw_secondary_series(LineSeries::new(xs, red.stroke_width(2)))
        .map_err(err)?
        .label(format!("{} (right axis)", report.x_axis))
        .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], red.stroke_width(2)));
    draw_legend(std::ops::DerefMut::deref_mut(&mut chart), SeriesLabelPosition::UpperMiddle)?;
    root.present().map_err(err)?;
    Ok(())
}

/// The legend of both plots, at `position`.
fn draw_legend<'a, DB: DrawingBackend + 'a, CT: CoordTranslate>(
    chart: &mut ChartContext<'a, DB, CT>,
    position: SeriesLabelPosition,
) -> Result<(), PlotError> {
    chart
        .configure_series_labels()
        .position(position)
        .label_font((FONT, 14))
        .background_style(WHITE.mix(0.85))
        .border_style(RGBColor(180, 180, 180))
        .draw()
        .map_err(err)
}

fn encode_png(rgb: &[u8]) -> Result<Vec<u8>, PlotError> {
    let mut out = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut out, W, H);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        let mut w = enc.write_header()?;
        w.write_image_data(rgb)?;
    }
    Ok(out)
}

/// Draws both plots of a report.
pub fn draw_all(report: &Report, feed: &Feed) -> Result<Vec<Plot>, ReportError> {
    ensure_font()?;
    let (curve_name, curve_title) = match report.standard {
        Standard::En14651 => ("load_cmod", "Load against CMOD".to_string()),
        _ => ("load_deflection", "Load against net deflection".to_string()),
    };
    let time_title = format!("Load and {} over time", report.x_axis);
    let mut plots = Vec::new();
    for (name, title, which) in [(curve_name, curve_title, 0), ("time", time_title, 1)] {
        let plot_err = |e: PlotError| ReportError::Plot { name: name.to_string(), message: e.to_string() };
        let mut svg = String::new();
        {
            let root = SVGBackend::with_string(&mut svg, (W, H)).into_drawing_area();
            if which == 0 { draw_curve(&root, report, &title) } else { draw_time(&root, report, feed, &title) }.map_err(plot_err)?;
        }
        let mut rgb = vec![0u8; (W * H * 3) as usize];
        {
            let root = BitMapBackend::with_buffer(&mut rgb, (W, H)).into_drawing_area();
            if which == 0 { draw_curve(&root, report, &title) } else { draw_time(&root, report, feed, &title) }.map_err(plot_err)?;
        }
        let png = encode_png(&rgb).map_err(plot_err)?;
        plots.push(Plot { name: name.to_string(), title, svg, png });
    }
    Ok(plots)
}
