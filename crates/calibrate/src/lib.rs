//! `tagdeflect calibrate`: camera intrinsics from views of a target, with their
//! uncertainty and what it means for a measurement.
//!
//! [`target`] parses `--target` and finds the target in an image; [`solve`] runs Zhang's
//! closed-form start and the Levenberg–Marquardt fit over all views with the product's camera
//! model; [`calibrate_views`] adds the outlier policy, [`calibrate_target_views`] the tag
//! corners' systematic bias to the σ; [`report`] makes the coverage map, the
//! uncertainty at a distance and the OpenCV FileStorage file; [`live_views`] grabs views from a
//! camera whose frames the caller supplies; [`render`] renders targets with known intrinsics
//! for tests. Errors are [`CalibrateError`]s, which tell bad input from runtime failures.
//!
//! **Outliers.** After a fit, single points whose residual exceeds
//! `max(5 s, 1 px)` (`s` the residual scatter per axis) are dropped, then whole views whose
//! RMS exceeds `max(3 × median view RMS, 0.5 px)` are rejected and named with their RMS, and
//! the fit is repeated until nothing more is dropped (at least three views stay).
//!
//! **Guard rails** ([`guard`]): too few views, a `--target` that is not the board in the
//! images, and views of another camera or focus are refused or named; every calibration ends
//! with a verdict (good / usable / poor) with its reasons and hints.

mod error;
pub mod guard;
pub mod live_views;
pub mod render;
pub mod report;
pub mod solve;
pub mod target;

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use nalgebra::Point2;

pub use self::error::CalibrateError;
use self::report::{uncertainty_at, Coverage};
use self::solve::{Calibration, SolveOptions, View, PARAM_NAMES};
use self::target::{BoardSeen, TargetDetector, TargetSpec};
use tagdeflect_core::camera::CameraIntrinsics;
use tagdeflect_core::frame::{FrameSet, GrayImage};

/// Options of `tagdeflect calibrate`.
#[derive(Debug, Clone)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
pub struct CalibrateOptions {
    /// A folder of images of the target (PNG or JPEG), all from one camera.
    #[cfg_attr(feature = "clap", arg(long, conflicts_with_all = ["config", "camera"]))]
    pub images: Option<PathBuf>,
    /// Grab views live from a camera of this config (with --camera).
    #[cfg_attr(feature = "clap", arg(long, requires = "camera"))]
    pub config: Option<PathBuf>,
    /// The `[[camera]]` name to calibrate (with --config).
    #[cfg_attr(feature = "clap", arg(long, requires = "config"))]
    pub camera: Option<String>,
    /// The target: `checkerboard:COLSxROWS:SQUARE_MM` (inner corners),
    /// `tagboard:FAMILY:COLSxROWS:SIZE_MM:PITCH_MM[:FIRST_ID]` or Kalibr's
    /// `aprilgrid:COLSxROWS:TAG_M:SPACING_RATIO`.
    #[cfg_attr(feature = "clap", arg(long))]
    pub target: String,
    /// The OpenCV FileStorage YAML to write.
    #[cfg_attr(feature = "clap", arg(long))]
    pub out: PathBuf,
    /// Hold k3 at zero (OpenCV CALIB_FIX_K3).
    #[cfg_attr(feature = "clap", arg(long))]
    pub fix_k3: bool,
    /// Hold fx/fy at --aspect-ratio (OpenCV CALIB_FIX_ASPECT_RATIO).
    #[cfg_attr(feature = "clap", arg(long))]
    pub fix_aspect_ratio: bool,
    /// The ratio fx/fy held by --fix-aspect-ratio.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 1.0))]
    pub aspect_ratio: f64,
    /// Hold p1 = p2 = 0 (OpenCV CALIB_ZERO_TANGENT_DIST).
    #[cfg_attr(feature = "clap", arg(long))]
    pub zero_tangent_dist: bool,
    /// Hold the principal point at the image centre (OpenCV CALIB_FIX_PRINCIPAL_POINT).
    #[cfg_attr(feature = "clap", arg(long))]
    pub fix_principal_point: bool,
    /// Keep every view and point (no outlier rejection).
    #[cfg_attr(feature = "clap", arg(long))]
    pub keep_outliers: bool,
    /// Calibrate despite the guard rails that can be overruled: fewer than 10 views (at
    /// least 3), a checkerboard of which no view shows the whole board, a tag board with ids
    /// outside its range or never seen, views that look like two cameras or focus settings.
    #[cfg_attr(feature = "clap", arg(long))]
    pub force: bool,
    /// Distance of the tags in the test, mm, for the uncertainty report (default: the median
    /// distance of the target in the views).
    #[cfg_attr(feature = "clap", arg(long))]
    pub distance_mm: Option<f64>,
    /// The coverage map PNG (default: next to --out, `<out>.coverage.png`).
    #[cfg_attr(feature = "clap", arg(long))]
    pub coverage: Option<PathBuf>,
    /// Live mode: stop after this many views that added coverage.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 20))]
    pub views: usize,
    /// Live mode: give up after this many seconds.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 120.0))]
    pub duration_s: f64,
}

impl CalibrateOptions {
    /// The solver flags.
    fn solve_options(&self) -> SolveOptions {
        SolveOptions {
            fix_k3: self.fix_k3,
            fix_aspect_ratio: self.fix_aspect_ratio,
            aspect_ratio: Some(self.aspect_ratio),
            zero_tangent_dist: self.zero_tangent_dist,
            fix_principal_point: self.fix_principal_point,
        }
    }

    fn flags_text(&self) -> String {
        let mut f = Vec::new();
        if self.fix_aspect_ratio {
            f.push(format!("fix-aspect-ratio {}", self.aspect_ratio));
        }
        if self.fix_k3 {
            f.push("fix-k3".into());
        }
        if self.zero_tangent_dist {
            f.push("zero-tangent-dist".into());
        }
        if self.fix_principal_point {
            f.push("fix-principal-point".into());
        }
        if f.is_empty() {
            "all parameters free".into()
        } else {
            f.join(", ")
        }
    }
}

/// A view that was not used, and why.
#[derive(Debug, Clone, PartialEq)]
pub struct Rejected {
    /// The view's name.
    pub name: String,
    /// Why.
    pub reason: String,
}

/// A calibration with its outlier bookkeeping.
#[derive(Debug, Clone, PartialEq)]
pub struct CalibrationRun {
    /// The fit over the views kept.
    pub calibration: Calibration,
    /// The views kept (same order as the calibration's poses).
    pub views: Vec<View>,
    /// Views rejected as outliers.
    pub rejected: Vec<Rejected>,
    /// Single points dropped as outliers.
    pub dropped_points: usize,
}

/// Calibrates from detected views with the outlier policy of the module docs (none when
/// `keep_outliers`).
pub fn calibrate_views(
    views: Vec<View>,
    width: u32,
    height: u32,
    options: &SolveOptions,
    keep_outliers: bool,
) -> Result<CalibrationRun, CalibrateError> {
    let mut views = views;
    let mut rejected = Vec::new();
    let mut dropped_points = 0;
    loop {
        let cal = solve::calibrate(&views, width, height, options)?;
        if keep_outliers {
            return Ok(CalibrationRun { calibration: cal, views, rejected, dropped_points });
        }
        // Points first: a single mislabelled corner should not cost its view.
        let limit = (5.0 * cal.sigma_px).max(1.0);
        let mut dropped = 0;
        for (v, pose) in views.iter_mut().zip(&cal.poses) {
            let res = solve::residuals(&cal.intrinsics, pose, v);
            let keep: Vec<bool> = res.iter().map(|r| r.x.abs() <= limit && r.y.abs() <= limit).collect();
            let n = keep.iter().filter(|k| !**k).count();
            if n > 0 && n < v.object.len() / 4 {
                let mut it = keep.iter();
                v.object.retain(|_| *it.next().unwrap());
                let mut it = keep.iter();
                v.image.retain(|_| *it.next().unwrap());
                dropped += n;
            }
        }
        dropped_points += dropped;
        if dropped > 0 {
            continue;
        }
        let med = tagdeflect_core::stats::median(&cal.view_rms_px).unwrap_or(0.0);
        let view_limit = (3.0 * med).max(0.5);
        let worst =
            cal.view_rms_px.iter().enumerate().filter(|(_, r)| **r > view_limit).max_by(|a, b| a.1.total_cmp(b.1)).map(|(i, r)| (i, *r));
        match worst {
            Some((i, rms)) if views.len() > 3 => {
                let v = views.remove(i);
                rejected.push(Rejected {
                    name: v.name,
                    reason: format!(
                        "reprojection RMS {rms:.3} px > {view_limit:.3} px (3 × the median view's {med:.3} px, at least 0.5 px)"
                    ),
                });
            }
            _ => return Ok(CalibrationRun { calibration: cal, views, rejected, dropped_points }),
        }
    }
}

/// [`calibrate_views`] for views of `spec`. For tag targets the covariance also holds the
/// sub-pixel refinement's systematic corner bias: every corner may sit out along its tag's
/// diagonal by an amount shared by every view, uniform and growing as the tags' bits shrink
/// in pixels, with the prior of [`TargetSpec::corner_bias_prior`]; the first-order effect of
/// each of the two patterns on the intrinsics ([`tag_corner_bias`]) is added to the
/// statistical covariance ([`Calibration::set_corner_bias`]). Checkerboard corners have no
/// such term.
pub fn calibrate_target_views(
    views: Vec<View>,
    width: u32,
    height: u32,
    spec: &TargetSpec,
    options: &SolveOptions,
    keep_outliers: bool,
) -> Result<CalibrationRun, CalibrateError> {
    let mut run = calibrate_views(views, width, height, options, keep_outliers)?;
    if let Some(prior) = spec.corner_bias_prior() {
        let modes = tag_corner_bias(&run, spec, options, &prior).ok_or(CalibrateError::Solve(solve::SolveError::Singular))?;
        run.calibration.set_corner_bias(modes);
    }
    Ok(run)
}

/// The two patterns of a tag target's systematic corner bias in `run` (views of `spec`),
/// with the σ of `prior` ([`target::CornerBiasPrior`]): every corner moved outwards along
/// the image of its tag's diagonal (from the projected tag centre through the projected
/// corner, under the run's intrinsics and poses) by 1 px ("uniform"), and by
/// `R / b − 1` px with `b` its tag's bit size in the image ("size": the projected black
/// square's mean edge over its bits; `R` = [`target::CORNER_BIAS_REFERENCE_BIT_PX`]).
/// `None` for a checkerboard, or when a direction or a sensitivity cannot be computed.
pub fn tag_corner_bias(
    run: &CalibrationRun,
    spec: &TargetSpec,
    options: &SolveOptions,
    prior: &target::CornerBiasPrior,
) -> Option<Vec<solve::CornerBias>> {
    use nalgebra::Vector2;
    let c = &run.calibration;
    let k = &c.intrinsics;
    // Per view and point: the unit diagonal (image) and the tag's bit size (px).
    let geometry: Vec<Vec<(Vector2<f64>, f64)>> = run
        .views
        .iter()
        .zip(&c.poses)
        .map(|(v, pose)| {
            v.object
                .iter()
                .map(|x| {
                    let project = |p: &nalgebra::Vector3<f64>| k.project(&pose.transform(p)).map(|q| q.coords);
                    let (square, bits) = spec.tag_square_of(x)?;
                    let centre = spec.tag_centre_of(x)?;
                    let d = project(x)? - project(&centre)?;
                    let corners = square.iter().map(project).collect::<Option<Vec<_>>>()?;
                    let perimeter_px: f64 = (0..4).map(|j| (corners[(j + 1) % 4] - corners[j]).norm()).sum();
                    let bit_px = perimeter_px / (4.0 * bits as f64);
                    let len = d.norm();
                    (len > 1e-9 && bit_px > 1e-9 && len.is_finite() && bit_px.is_finite()).then(|| (d / len, bit_px))
                })
                .collect::<Option<Vec<_>>>()
        })
        .collect::<Option<Vec<_>>>()?;
    let pattern = |amount: &dyn Fn(f64) -> f64| -> Vec<Vec<Vector2<f64>>> {
        geometry.iter().map(|g| g.iter().map(|(d, bit_px)| d * amount(*bit_px)).collect()).collect()
    };
    let uniform = solve::bias_sensitivity(c, &run.views, options, &pattern(&|_| 1.0))?;
    let size = solve::bias_sensitivity(c, &run.views, options, &pattern(&|b| target::CORNER_BIAS_REFERENCE_BIT_PX / b - 1.0))?;
    Some(vec![
        solve::CornerBias { mode: "uniform along the tags' diagonals", sigma_px: prior.uniform_px, sensitivity_per_px: uniform },
        solve::CornerBias { mode: "growing as the bits shrink", sigma_px: prior.size_px, sensitivity_per_px: size },
    ])
}

/// Decodes an image file to 8-bit grey (BT.601 luma, as OpenCV's `cvtColor` and JPEG's Y).
fn load_gray(path: &Path) -> Result<GrayImage, CalibrateError> {
    let img = image::open(path).map_err(|cause| CalibrateError::Decode { path: path.to_path_buf(), cause })?;
    let rgb = img.to_rgb8();
    let data = rgb
        .pixels()
        .map(|p| (0.299 * p.0[0] as f64 + 0.587 * p.0[1] as f64 + 0.114 * p.0[2] as f64).round().clamp(0.0, 255.0) as u8)
        .collect();
    Ok(GrayImage { width: rgb.width(), height: rgb.height(), data })
}

/// The image files of a folder (PNG, JPEG), sorted by name.
pub fn image_files(dir: &Path) -> Result<Vec<PathBuf>, CalibrateError> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(|cause| CalibrateError::ReadFolder { dir: dir.to_path_buf(), cause })?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.is_file()
                && p.extension().and_then(|e| e.to_str()).is_some_and(|e| matches!(e.to_ascii_lowercase().as_str(), "png" | "jpg" | "jpeg"))
        })
        .collect();
    files.sort();
    if files.is_empty() {
        return Err(CalibrateError::NoImages(dir.to_path_buf()));
    }
    Ok(files)
}

/// Views detected in a set of images, the image size, and the images where the target was
/// not found (with the reason).
pub fn detect_views(files: &[PathBuf], spec: &TargetSpec) -> Result<(Vec<View>, u32, u32, Vec<Rejected>), CalibrateError> {
    detect_views_seen(files, spec).map(|d| (d.views, d.width, d.height, d.not_found))
}

/// What [`detect_views_seen`] found in a folder of images.
#[derive(Debug, Clone, PartialEq)]
pub struct Detected {
    /// The views where the target was found.
    pub views: Vec<View>,
    /// Image width, px.
    pub width: u32,
    /// Image height, px.
    pub height: u32,
    /// The images where it was not, and why.
    pub not_found: Vec<Rejected>,
    /// What the detector saw of the board in every view (name, seen), for
    /// [`guard::check_board`].
    pub seen: Vec<(String, BoardSeen)>,
}

/// [`detect_views`], with what the detector saw of the board in every view.
pub fn detect_views_seen(files: &[PathBuf], spec: &TargetSpec) -> Result<Detected, CalibrateError> {
    detect_views_seen_with(files, spec, None)
}

/// [`detect_views_seen`] with the tags' edges fitted through `intrinsics` (a first
/// calibration's; see [`TargetDetector::set_intrinsics`]).
pub fn detect_views_seen_with(
    files: &[PathBuf],
    spec: &TargetSpec,
    intrinsics: Option<&CameraIntrinsics>,
) -> Result<Detected, CalibrateError> {
    let mut det = TargetDetector::new(spec.clone())?;
    det.set_intrinsics(intrinsics.copied());
    let mut seen = Vec::new();
    let mut views = Vec::new();
    let mut failed = Vec::new();
    let mut size: Option<(u32, u32, &Path)> = None;
    for f in files {
        let img = load_gray(f)?;
        match size {
            None => size = Some((img.width, img.height, f)),
            Some((w, h, first)) if (w, h) != (img.width, img.height) => {
                return Err(CalibrateError::SizeMismatch {
                    path: f.clone(),
                    size: (img.width, img.height),
                    first: first.to_path_buf(),
                    first_size: (w, h),
                })
            }
            _ => {}
        }
        let name = f.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        match det.detect_seen(&img, &name) {
            Ok((v, s)) => {
                views.push(v);
                seen.push((name, s));
            }
            Err(reason) => failed.push(Rejected { name, reason }),
        }
    }
    let (width, height, _) = size.expect("at least one image");
    Ok(Detected { views, width, height, not_found: failed, seen })
}

/// The text report of a calibration (what `tagdeflect calibrate` prints).
fn report_text(
    run: &CalibrationRun,
    not_found: &[Rejected],
    coverage: &Coverage,
    distance_mm: f64,
    target: &str,
    verdict: &guard::Verdict,
    notes: &[String],
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
            "  {:<6} (pixel {:>6.1}, {:>6.1}): position ± {:.4} mm, a {disp:.0} mm deflection ± {:.2} µm",
            u.place,
            u.pixel.x,
            u.pixel.y,
            u.lateral_mm,
            1000.0 * u.displacement_error_mm
        );
    }
    let _ = writeln!(out, "  focal length ±{:.0} ppm: distances from tag size and displacements scale by that much", 1e6 * s[1] / k.fy);
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
fn write_outputs(
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
    let mut text = report_text(run, not_found, &coverage, distance, &spec.describe(), &verdict, notes);
    let _ = writeln!(text, "wrote {} and the coverage map {}", opts.out.display(), cov_path.display());
    let _ = writeln!(text, "config snippet (in the camera's [[camera]] section, instead of fx/fy/cx/cy/dist):");
    let _ = writeln!(text, "  calibration = \"{}\"", opts.out.display());
    Ok(text)
}

/// Checks the options before anything is read (every error is bad input): the target, the
/// numbers, and that either `--images` or `--config` with `--camera` is given. Returns the
/// parsed target. [`run`] checks them too; a caller that has to open the live camera first
/// (from `--config`) calls this before.
pub fn check_options(opts: &CalibrateOptions) -> Result<TargetSpec, CalibrateError> {
    let spec: TargetSpec = opts.target.parse()?;
    if !(opts.aspect_ratio.is_finite() && opts.aspect_ratio > 0.0) {
        return Err(CalibrateError::BadOption(format!("--aspect-ratio must be a positive number, got {}", opts.aspect_ratio)));
    }
    if let Some(d) = opts.distance_mm {
        if !(d.is_finite() && d > 0.0) {
            return Err(CalibrateError::BadOption(format!("--distance-mm must be a positive distance, got {d}")));
        }
    }
    match (&opts.images, &opts.config, &opts.camera) {
        (Some(_), None, None) | (None, Some(_), Some(_)) => Ok(spec),
        _ => Err(CalibrateError::BadOption("calibrate takes either --images DIR or --config FILE --camera NAME".into())),
    }
}

/// `tagdeflect calibrate`: from a folder of images (`--images`) or live (`--config FILE
/// --camera NAME`), then writes the outputs and prints the report.
///
/// Live mode needs `grab`: the next frame set of that one camera (`Err` with the message
/// when none arrives in time), which the caller builds from the config's camera and its
/// source; see [`live_views::grab_views`]. With `--images`, `grab` must be `None`.
pub fn run(opts: &CalibrateOptions, grab: Option<&mut dyn FnMut() -> Result<FrameSet, String>>) -> Result<(), CalibrateError> {
    let spec = check_options(opts)?;
    let (run, notes, not_found) = match (&opts.images, &opts.camera, grab) {
        (Some(dir), None, None) => calibrate_folder(dir, &spec, opts)?,
        (None, Some(cam), Some(grab)) => calibrate_live(grab, cam, &spec, opts)?,
        _ => return Err(CalibrateError::BadOption("calibrate takes either --images DIR or --config FILE --camera NAME".into())),
    };
    let text = write_outputs(&run, &not_found, &spec, opts, &notes)?;
    print!("{text}");
    Ok(())
}

/// A folder of images calibrated as `calibrate --images DIR` does: detected, calibrated with
/// the guard rails, and — for tag targets — detected again with the tag edges fitted through
/// that first calibration and calibrated again (tag edges are straight only without the lens:
/// the second pass removes the bias of fitting lines to bent edges; module docs). Returns the
/// run, its warnings and the images the target was not found in.
pub fn calibrate_folder(
    dir: &Path,
    spec: &TargetSpec,
    opts: &CalibrateOptions,
) -> Result<(CalibrationRun, Vec<String>, Vec<Rejected>), CalibrateError> {
    let files = image_files(dir)?;
    let d = detect_views_seen(&files, spec)?;
    let (run, notes) = calibrate_guarded(d.views, d.width, d.height, &d.not_found, &d.seen, spec, opts)?;
    if !spec.has_tags() {
        return Ok((run, notes, d.not_found));
    }
    let d = detect_views_seen_with(&files, spec, Some(&run.calibration.intrinsics))?;
    let (run, notes) = calibrate_guarded(d.views, d.width, d.height, &d.not_found, &d.seen, spec, opts)?;
    Ok((run, notes, d.not_found))
}

/// Live calibration (`calibrate --config FILE --camera NAME`): views grabbed while they add
/// coverage ([`live_views::grab_views_kept`]), calibrated with the guard rails, and — for tag
/// targets — the kept frames detected again through that first calibration and calibrated
/// again, exactly as [`calibrate_folder`] does with files (the same frames give the same
/// result either way).
pub fn calibrate_live(
    grab: &mut dyn FnMut() -> Result<FrameSet, String>,
    camera: &str,
    spec: &TargetSpec,
    opts: &CalibrateOptions,
) -> Result<(CalibrationRun, Vec<String>, Vec<Rejected>), CalibrateError> {
    let g = live_views::grab_views_kept(grab, camera, spec, opts.views, opts.duration_s)?;
    let (run, notes) = calibrate_guarded(g.views, g.width, g.height, &g.skipped, &[], spec, opts)?;
    if !spec.has_tags() {
        return Ok((run, notes, g.skipped));
    }
    let mut det = TargetDetector::new(spec.clone())?;
    det.set_intrinsics(Some(run.calibration.intrinsics));
    let mut views = Vec::new();
    let mut skipped = g.skipped;
    for (name, img) in &g.images {
        match det.detect(img, name) {
            Ok(v) => views.push(v),
            Err(reason) => skipped.push(Rejected { name: name.clone(), reason: format!("second pass: {reason}") }),
        }
    }
    let (run, notes) = calibrate_guarded(views, g.width, g.height, &skipped, &[], spec, opts)?;
    Ok((run, notes, skipped))
}

/// The guard rails around [`calibrate_views`] (see [`guard`]): the board check, the minimum
/// number of views, and views of another camera or focus — a minority of them (under a
/// third of the views) rejected and named, a larger group refused unless `--force`. Returns
/// the run and the warnings to print.
pub fn calibrate_guarded(
    views: Vec<View>,
    width: u32,
    height: u32,
    not_found: &[Rejected],
    seen: &[(String, BoardSeen)],
    spec: &TargetSpec,
    opts: &CalibrateOptions,
) -> Result<(CalibrationRun, Vec<String>), CalibrateError> {
    guard::check_board(spec, &opts.target, seen, opts.force)?;
    let need = if opts.force { guard::ABSOLUTE_MIN_VIEWS } else { guard::MIN_VIEWS };
    if views.len() < need {
        return Err(CalibrateError::TooFewViews { found: views.len(), need, forced: opts.force, not_found: not_found.to_vec() });
    }
    let mut notes = Vec::new();
    if views.len() < guard::MIN_VIEWS {
        notes.push(format!("--force: calibrated from {} views, fewer than the {} needed for trustworthy σ", views.len(), guard::MIN_VIEWS));
    }
    let options = opts.solve_options();
    let mut run = calibrate_target_views(views, width, height, spec, &options, opts.keep_outliers)?;
    if let Some(split) = guard::split_views(&run, &options) {
        let what = split.describe(&run.views);
        if 3 * split.minority.len() < run.views.len() {
            let mut keep = Vec::new();
            let mut rejected = std::mem::take(&mut run.rejected);
            for (i, v) in run.views.into_iter().enumerate() {
                if split.minority.contains(&i) {
                    rejected.push(Rejected {
                        name: v.name,
                        reason: "another camera or focus setting: its views fit other intrinsics (see the warning)".into(),
                    });
                } else {
                    keep.push(v);
                }
            }
            let dropped = run.dropped_points;
            run = calibrate_target_views(keep, width, height, spec, &options, opts.keep_outliers)?;
            rejected.append(&mut run.rejected);
            run.rejected = rejected;
            run.dropped_points += dropped;
            notes.push(format!("views of another camera or focus setting rejected: {what}"));
        } else if opts.force {
            notes.push(format!("--force: the views look like two cameras or focus settings, calibrated as one: {what}"));
        } else {
            return Err(CalibrateError::MixedViews(format!(
                "the views look like two cameras or two focus settings: {what}. Calibrate each camera (and focus) from its own \
                 folder; --force calibrates them as one"
            )));
        }
    }
    Ok((run, notes))
}
