//! The plots of a long feed's report are drawn through the points their pixels show
//! (`plot_points`), not through every line: a structural bound on what the SVGs hold and on
//! `report.html`'s size for a 100 000-line feed. Drawing every point again gives ~20× the
//! points and a page of ~12 MB (docs/performance.md, "The plots drawn through their pixels").

use tagdeflect_core::feed::{FeedLine, FeedTag};

use tagdeflect_report::{Feed, ReportConfig, Standard, TestRig};

/// A one-camera line: the supports (0, 2) and mid-span (1) tags with σ, a beam loaded to its
/// first peak and softening, its load noisy from line to line (each line a point of its own).
fn line(seq: u64, lines: u64) -> FeedLine {
    let d = 3.2 * seq as f64 / (lines - 1) as f64;
    let p = if d < 0.06 { 45.0 * d / 0.06 } else { 15.0 + 30.0 * (-(d - 0.06) / 0.4).exp() };
    let noise = 0.05 * (1.7 * seq as f64).sin();
    let tag = |id: u32, dz: f64| FeedTag {
        id,
        pos_mm: [100.0 * id as f64, 0.0, 1500.0],
        disp_mm: [0.0, 0.0, dz],
        views: 1,
        sigma_mm: Some([0.004, 0.004, 0.002]),
        disp_sigma_mm: None,
        reproj_px: Some(0.12),
    };
    FeedLine {
        seq,
        t_ns: 1_780_000_000_000_000_000 + seq as i64 * 33_333_333,
        load_kn: Some(p + noise),
        stroke_mm: Some(1.3 * d),
        tags: vec![tag(0, 0.0), tag(1, -d), tag(2, 0.0)],
        net_deflection_mm: Some(d),
        utm: Some("ok".into()),
        ..Default::default()
    }
}

fn rig() -> TestRig {
    let specimen = serde_json::from_value(serde_json::json!({
        "family": "tag36h11", "size_mm": 30.0,
        "tag": [{"id": 0, "role": "support"}, {"id": 1, "role": "midspan"}, {"id": 2, "role": "support"}],
        "beam": {"width_mm": 150.0, "depth_mm": 150.0, "span_mm": 450.0},
    }))
    .unwrap();
    TestRig { world: Default::default(), specimen, gauges: Vec::new() }
}

/// The points an SVG draws: each `<circle` (a marker) and each coordinate pair of its
/// polylines and paths.
fn drawn_points(svg: &str) -> usize {
    let markers = svg.matches("<circle").count();
    let pairs: usize = svg.split("points=\"").skip(1).map(|rest| rest.split('"').next().unwrap_or("").split_whitespace().count()).sum();
    markers + pairs
}

#[test]
fn a_long_feeds_plots_hold_what_their_pixels_show_not_every_line() {
    const LINES: u64 = 100_000;
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("feed.jsonl");
    let text: String = (0..LINES).map(|k| serde_json::to_string(&line(k, LINES)).unwrap() + "\n").collect();
    std::fs::write(&path, text).unwrap();
    let feed = Feed::read(&path).unwrap();
    let out = dir.path().join("report");
    let mut opts = ReportConfig::new(Standard::AstmC1609, out.clone());
    opts.pdf = false;
    let report = tagdeflect_report::build(&feed, None, &rig(), std::path::Path::new("rig.toml"), &opts).unwrap();
    tagdeflect_report::write(&report, &feed, &out).unwrap();

    let svg = |name: &str| std::fs::read_to_string(out.join(name)).unwrap_or_else(|e| panic!("{name}: {e}"));
    let (curve, time) = (drawn_points(&svg("load_deflection.svg")), drawn_points(&svg("time.svg")));
    let html_bytes = std::fs::metadata(out.join("report.html")).unwrap().len();
    eprintln!("{LINES} lines: load_deflection.svg draws {curve} points, time.svg {time}; report.html {html_bytes} B");
    // Each plot is ~1000 px wide: at most 4 points a pixel column per line drawn and a marker
    // a pixel; every point drawn would be ≥ LINES in each plot (a marker and a smoothed point
    // per line in the curve plot, a load and a deflection point per line in the time plot).
    // Measured 2026-12-07: 7 250 and 4 283 points, a page of 354 kB; the bounds ~1.6–2× that.
    assert!(curve > 1_000 && time > 1_000, "the plots draw the curve: {curve} and {time} points");
    assert!(curve <= 12_000, "load_deflection.svg draws {curve} points for {LINES} lines");
    assert!(time <= 8_000, "time.svg draws {time} points for {LINES} lines");
    assert!(html_bytes <= 700_000, "report.html is {html_bytes} B for {LINES} lines");
}
