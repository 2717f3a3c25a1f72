//! What a calibration writes: the report text and the files (OpenCV FileStorage, the
//! coverage map).

use std::fmt::Write as _;
use std::path::PathBuf;

use nalgebra::Point2;

use crate::error::CalibrateError;
use crate::fit::{CalibrationRun, Rejected};
use crate::options::CalibrateOptions;
use crate::report::{uncertainty_at, Coverage};
use crate::solve::{Calibration, View, PARAM_NAMES};
use crate::spread::{view_spread, ViewSpread};
use crate::target::TargetSpec;
use crate::{guard, report, solve};

/// The text report of a calibration (what `tagdeflect calibrate` prints).
#[allow(clippy::too_many_arguments)]
pub(crate) fn report_text(
    run: &CalibrationRun,
    not_found: &[Rejected],
    coverage: &Coverage,
    distance_mm: f64,
    target: &str,
    verdict: &guard::Verdict,
    notes: &[String],
    spread: Option<&ViewSpread>,
) -> String {
    let c = &run.calibration;
    let k = &c.intrinsics;
    let s = c.sigmas();
    let vals = solve::to_vector(k);
    let mut out = String::new();
    let _ = writeln!(out, "calibration of a {}x{} camera from {} views of a {target}", k.width, k.height, run.views.len());
    let _ = writeln!(out, "start: {}; {} LM iterations; {} parameters", c.start, c.iterations, c.parameters);
    for i in 0..9 {
        let unit = if i < 4 { " px" } else { "" };
        let fixed = if s[i] == 0.0 { "  (fixed)" } else { "" };
        let _ = writeln!(out, "  {:<3} = {:>12.6}{unit} ± {:.6}{unit} (1σ){fixed}", PARAM_NAMES[i], vals[i], s[i]);
    }
    if !c.corner_bias.is_empty() {
        let (st, sy) = (c.statistical_sigmas(), c.systematic_sigmas());
        let modes: Vec<String> = c.corner_bias.iter().map(|b| format!("± {:.3} px {}", b.sigma_px, b.mode)).collect();
        let _ = writeln!(
            out,
            "  (σ includes the tag corners' systematic bias, {}: fx ± {:.6} px from the corner noise alone, ± {:.6} px from the bias)",
            modes.join(", "),
            st[0],
            sy[0]
        );
    }
    if let Some(sp) = spread {
        out.push_str(&sp.text());
    }
    let _ = writeln!(
        out,
        "reprojection RMS {:.4} px over {} points (residual scatter {:.4} px per axis)",
        c.rms_px,
        run.views.iter().map(|v| v.object.len()).sum::<usize>(),
        c.sigma_px
    );
    let _ = writeln!(out, "per view:");
    for (v, r) in run.views.iter().zip(&c.view_rms_px) {
        let _ = writeln!(out, "  {:<28} {:>3} points  RMS {:.4} px", v.name, v.object.len(), r);
    }
    for r in &run.rejected {
        let _ = writeln!(out, "rejected view {}: {}", r.name, r.reason);
    }
    for r in not_found {
        let _ = writeln!(out, "not used {}: {}", r.name, r.reason);
    }
    if run.dropped_points > 0 {
        let _ = writeln!(out, "dropped {} single outlier points (residual > max(5σ, 1 px))", run.dropped_points);
    }
    let _ = writeln!(
        out,
        "coverage: {:.0} % of {}x{} image cells hold target points",
        100.0 * coverage.covered_fraction,
        coverage.cols,
        coverage.rows
    );
    if let Some(w) = coverage.warning() {
        let _ = writeln!(out, "WARNING {w}");
    }
    let disp = 10.0;
    let _ = writeln!(out, "what the uncertainty means for a tag at {distance_mm:.0} mm (1σ, one camera, distance known):");
    for u in uncertainty_at(k, &c.covariance, distance_mm, disp) {
        let _ = writeln!(
            out,
            "  {:<6} (pixel {:>6.1}, {:>6.1}): position {}, a {disp:.0} mm deflection {}",
            u.place,
            u.pixel.x,
            u.pixel.y,
            guard::sigma_text(u.lateral_mm, distance_mm, 1.0, 4, "mm"),
            guard::sigma_text(u.displacement_error_mm, disp, 1e3, 2, "µm")
        );
    }
    let fy = guard::sigma_text(s[1] / k.fy, guard::UNDETERMINED_RELATIVE, 1e6, 0, "ppm");
    let _ = writeln!(out, "  focal length {fy}: distances from tag size and displacements scale by that much");
    for n in notes {
        let _ = writeln!(out, "WARNING {n}");
    }
    out.push_str(&verdict.text());
    out
}

/// Median distance of the target from the camera over the views, mm.
fn median_distance_mm(c: &Calibration, views: &[View]) -> f64 {
    let d: Vec<f64> = c
        .poses
        .iter()
        .zip(views)
        .map(|(p, v)| {
            let n = v.object.len().max(1) as f64;
            let mean = v.object.iter().fold(nalgebra::Vector3::zeros(), |a, x| a + x) / n;
            p.transform(&mean).z
        })
        .collect();
    tagdeflect_core::stats::median(&d).unwrap_or(1000.0)
}

/// Writes the FileStorage file and the coverage map, returns the text report (with the config
/// snippet).
pub(crate) fn write_outputs(
    run: &CalibrationRun,
    not_found: &[Rejected],
    spec: &TargetSpec,
    opts: &CalibrateOptions,
    notes: &[String],
) -> Result<String, CalibrateError> {
    let c = &run.calibration;
    let k = &c.intrinsics;
    let all_points: Vec<Point2<f64>> = run.views.iter().flat_map(|v| v.image.iter().copied()).collect();
    let coverage = Coverage::new(k.width, k.height, &all_points);
    let names: Vec<String> = run.views.iter().map(|v| v.name.clone()).collect();
    let distance = opts.distance_mm.unwrap_or_else(|| median_distance_mm(c, &run.views));
    let verdict = guard::verdict(run, &coverage, distance);
    let mut yaml = report::opencv_yaml(c, &spec.describe(), &opts.flags_text(), &names);
    for line in verdict.text().lines() {
        let _ = writeln!(yaml, "# {line}");
    }
    if let Some(parent) = opts.out.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).map_err(|cause| CalibrateError::CreateDir { path: parent.to_path_buf(), cause })?;
    }
    std::fs::write(&opts.out, yaml).map_err(|cause| CalibrateError::Write { path: opts.out.clone(), cause })?;
    let cov_path = opts.coverage.clone().unwrap_or_else(|| {
        let mut p = opts.out.clone().into_os_string();
        p.push(".coverage.png");
        PathBuf::from(p)
    });
    let per_view: Vec<Vec<Point2<f64>>> = run.views.iter().map(|v| v.image.clone()).collect();
    coverage.write_png(&cov_path, k.width, k.height, &per_view).map_err(|cause| CalibrateError::Write { path: cov_path.clone(), cause })?;
    let spread = view_spread(run, &opts.solve_options());
    let mut text = report_text(run, not_found, &coverage, distance, &spec.describe(), &verdict, notes, spread.as_ref());
    let _ = writeln!(text, "wrote {} and the coverage map {}", opts.out.display(), cov_path.display());
    let _ = writeln!(text, "config snippet (in the camera's [[camera]] section, instead of fx/fy/cx/cy/dist):");
    let _ = writeln!(text, "  calibration = \"{}\"", opts.out.display());
    if verdict.grade == guard::Grade::Poor {
        let why: Vec<&str> = verdict.reasons.iter().filter(|(g, _)| *g == guard::Grade::Poor).map(|(_, r)| r.as_str()).collect();
        return Err(CalibrateError::Poor { text, why: why.join("; ") });
    }
    Ok(text)
}
