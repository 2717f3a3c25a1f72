//! The command line of `tagdeflect calibrate` and its checks.

use std::path::PathBuf;

use crate::error::CalibrateError;
use crate::solve::SolveOptions;
use crate::target::TargetSpec;

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
    pub(crate) fn solve_options(&self) -> SolveOptions {
        SolveOptions {
            fix_k3: self.fix_k3,
            fix_aspect_ratio: self.fix_aspect_ratio,
            aspect_ratio: Some(self.aspect_ratio),
            zero_tangent_dist: self.zero_tangent_dist,
            fix_principal_point: self.fix_principal_point,
        }
    }

    pub(crate) fn flags_text(&self) -> String {
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
