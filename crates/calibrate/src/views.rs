//! Views from image files: the folder's images, the target found in each, the images it
//! was not found in named.

use std::path::{Path, PathBuf};

use crate::error::CalibrateError;
use crate::fit::Rejected;
use crate::solve::View;
use crate::target::{BoardSeen, TargetDetector, TargetSpec};
use tagdeflect_core::camera::CameraIntrinsics;
use tagdeflect_core::frame::GrayImage;

/// Largest calibration image, pixels: 256 Mpx, the cap of every image the product reads
/// without a known camera size (docs/operations.md, the fault table).
pub const MAX_IMAGE_PIXELS: u64 = 1 << 28;
/// Smallest side of a calibration image, pixels: no target's corners fit in less.
pub const MIN_IMAGE_SIDE_PX: u32 = 32;

/// Decodes an image file to 8-bit grey (BT.601 luma, as OpenCV's `cvtColor` and JPEG's Y);
/// its size is read from the header first and checked against [`MAX_IMAGE_PIXELS`] and
/// [`MIN_IMAGE_SIDE_PX`] before any pixel is decoded.
pub(crate) fn load_gray(path: &Path) -> Result<GrayImage, CalibrateError> {
    let decode = |cause| CalibrateError::Decode { path: path.to_path_buf(), cause };
    let (width, height) = image::image_dimensions(path).map_err(decode)?;
    let refuse = |why: String| Err(CalibrateError::ImageSize { path: path.to_path_buf(), width, height, why });
    if width as u64 * height as u64 > MAX_IMAGE_PIXELS {
        return refuse(format!("more than {MAX_IMAGE_PIXELS} pixels (256 Mpx)"));
    }
    if width.min(height) < MIN_IMAGE_SIDE_PX {
        return refuse(format!("a side under {MIN_IMAGE_SIDE_PX} px holds no target"));
    }
    let img = image::open(path).map_err(decode)?;
    let rgb = img.to_rgb8();
    let data = rgb
        .pixels()
        .map(|p| (0.299 * p.0[0] as f64 + 0.587 * p.0[1] as f64 + 0.114 * p.0[2] as f64).round().clamp(0.0, 255.0) as u8)
        .collect();
    Ok(GrayImage { width: rgb.width(), height: rgb.height(), data, deep: None })
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
            Err(e) => failed.push(Rejected { name, reason: e.to_string() }),
        }
    }
    let (width, height, _) = size.expect("at least one image");
    Ok(Detected { views, width, height, not_found: failed, seen })
}
