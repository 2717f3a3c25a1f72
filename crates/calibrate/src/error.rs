//! The errors of `tagdeflect calibrate`.

use std::fmt;
use std::path::PathBuf;

use crate::fit::Rejected;
use crate::solve::SolveError;
use crate::target::TargetError;

/// Why the caller's grab delivered no frame set (live mode): the frame source's message —
/// the source is the caller's, its errors are not this crate's types.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{message}")]
pub struct GrabError {
    /// What the frame source said.
    pub message: String,
}

/// Why `tagdeflect calibrate` (or one of its steps) failed.
///
/// **Bad input or runtime failure.** [`CalibrateError::is_bad_input`] tells the two apart:
///
/// - *Bad input* (the command line exits 2; the same input fails the same way again): a bad
///   `--target` ([`Target`](Self::Target)), an option out of range or options that do not
///   fit together ([`BadOption`](Self::BadOption)), an image folder that cannot be read or
///   holds no image ([`ReadFolder`](Self::ReadFolder), [`NoImages`](Self::NoImages)), an
///   image that cannot be read or decoded ([`Decode`](Self::Decode)), images of different
///   sizes ([`SizeMismatch`](Self::SizeMismatch)), views that do not show the target often
///   enough or do not determine a calibration ([`TooFewViews`](Self::TooFewViews),
///   [`Solve`](Self::Solve)), and detector options the AprilTag library refuses
///   ([`Detector`](Self::Detector) other than [`DetectError::Create`](tagdeflect_detect::DetectError::Create)).
/// - *Runtime failure* (exit 1): the AprilTag library failing to create its detector
///   ([`DetectError::Create`](tagdeflect_detect::DetectError::Create)), the live camera not
///   delivering frames ([`Grab`](Self::Grab)), and the outputs that cannot be written
///   ([`CreateDir`](Self::CreateDir), [`Write`](Self::Write)).
///
/// (A config that cannot be loaded or names no such camera is the caller's: the binary
/// reads the config and builds the camera's frame source for [`crate::live_views::grab_views`].)
///
/// **Messages.** A variant that adds context holds its cause in its own message
/// (`context: cause: cause of the cause`, what the command line's `{:#}` printed before) and
/// returns no [`source`](std::error::Error::source), so printing it with `{:#}` through
/// `anyhow` does not repeat the cause; a variant that wraps another error alone is
/// transparent (its message and sources are that error's).
#[derive(Debug, thiserror::Error)]
pub enum CalibrateError {
    /// A bad `--target` (bad input).
    #[error(transparent)]
    Target(#[from] TargetError),
    /// An option out of range, or options that do not fit together (bad input).
    #[error("{0}")]
    BadOption(String),
    /// The `--images` folder cannot be read (bad input).
    #[error("cannot read the image folder {}: {}", .dir.display(), Chain(.cause))]
    ReadFolder {
        /// The folder.
        dir: PathBuf,
        /// Why.
        cause: std::io::Error,
    },
    /// The `--images` folder holds no PNG or JPEG file (bad input).
    #[error("no PNG or JPEG images in {}", .0.display())]
    NoImages(PathBuf),
    /// An image cannot be read or decoded (bad input).
    #[error("cannot decode image {}: {}", .path.display(), Chain(.cause))]
    Decode {
        /// The image file.
        path: PathBuf,
        /// Why.
        cause: image::ImageError,
    },
    /// An image's header claims a size no calibration image has (bad input): refused before
    /// its pixels are decoded.
    #[error("image {} is {width}x{height} (from its header; nothing decoded): {why}", .path.display())]
    ImageSize {
        /// The image file.
        path: PathBuf,
        /// Its width, px.
        width: u32,
        /// Its height, px.
        height: u32,
        /// The limit it breaks.
        why: String,
    },
    /// Two images differ in size: they cannot come from one camera at one resolution (bad input).
    #[error(
        "image {} is {}x{} but {} is {}x{}: all views must come from one camera at one resolution",
        .path.display(),
        .size.0,
        .size.1,
        .first.display(),
        .first_size.0,
        .first_size.1
    )]
    SizeMismatch {
        /// The image that differs.
        path: PathBuf,
        /// Its width and height.
        size: (u32, u32),
        /// The first image.
        first: PathBuf,
        /// The first image's width and height.
        first_size: (u32, u32),
    },
    /// The target was found in fewer views than needed: [`crate::guard::MIN_VIEWS`], or three
    /// with `--force` (bad input).
    #[error("{}", too_few(*.found, *.need, *.forced, .not_found))]
    TooFewViews {
        /// Views in which the target was found.
        found: usize,
        /// Views needed.
        need: usize,
        /// Whether `--force` lowered the need to its absolute minimum.
        forced: bool,
        /// The images or frames where it was not, and why.
        not_found: Vec<Rejected>,
    },
    /// The `--target` is not the board the images show (bad input).
    #[error("{0}")]
    BoardMismatch(String),
    /// The views come from two cameras or two focus settings (bad input).
    #[error("{0}")]
    MixedViews(String),
    /// The views do not determine a calibration (bad input).
    #[error(transparent)]
    Solve(#[from] SolveError),
    /// The AprilTag detector of a tag board could not be created (runtime failure when the
    /// library failed to create it, bad input for options it refuses).
    #[error(transparent)]
    Detector(#[from] tagdeflect_detect::DetectError),
    /// Live mode: the camera delivered no frame set (runtime failure).
    #[error("camera {camera}: {message}")]
    Grab {
        /// The camera's name.
        camera: String,
        /// What the frame source said.
        message: String,
    },
    /// A folder for the outputs cannot be created (runtime failure).
    #[error("cannot create {}: {}", .path.display(), Chain(.cause))]
    CreateDir {
        /// The folder.
        path: PathBuf,
        /// Why.
        cause: std::io::Error,
    },
    /// The calibration was made and written, but its verdict is POOR: not fit for a test (the
    /// command line exits 3, [`tagdeflect_core::NotFit`]).
    #[error("calibration verdict POOR ({why}): not fit for a test; calibrate again (see the hints above)")]
    Poor {
        /// The report printed (the command prints it before the error).
        text: String,
        /// The criteria graded poor.
        why: String,
    },
    /// An output file (the FileStorage YAML, the coverage map) cannot be written (runtime failure).
    #[error("cannot write {}: {}", .path.display(), Chain(.cause))]
    Write {
        /// The file.
        path: PathBuf,
        /// Why.
        cause: std::io::Error,
    },
}

impl CalibrateError {
    /// True for bad input (the command line exits 2), false for a runtime failure (exit 1);
    /// see the type's documentation for which is which.
    pub fn is_bad_input(&self) -> bool {
        match self {
            CalibrateError::Target(_)
            | CalibrateError::BadOption(_)
            | CalibrateError::ReadFolder { .. }
            | CalibrateError::NoImages(_)
            | CalibrateError::Decode { .. }
            | CalibrateError::ImageSize { .. }
            | CalibrateError::SizeMismatch { .. }
            | CalibrateError::TooFewViews { .. }
            | CalibrateError::BoardMismatch(_)
            | CalibrateError::MixedViews(_)
            | CalibrateError::Solve(_) => true,
            CalibrateError::Detector(e) => !matches!(e, tagdeflect_detect::DetectError::Create(_)),
            CalibrateError::Grab { .. } | CalibrateError::CreateDir { .. } | CalibrateError::Write { .. } | CalibrateError::Poor { .. } => {
                false
            }
        }
    }
}

/// An error and its sources, `: `-separated (what `anyhow`'s `{:#}` printed for a context).
struct Chain<'a, E>(&'a E);

impl<E: std::error::Error> fmt::Display for Chain<'_, E> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}", self.0)?;
        let mut source = self.0.source();
        while let Some(s) = source {
            write!(f, ": {s}")?;
            source = s.source();
        }
        Ok(())
    }
}

/// The message of [`CalibrateError::TooFewViews`].
struct TooFew<'a> {
    found: usize,
    need: usize,
    forced: bool,
    not_found: &'a [Rejected],
}

fn too_few(found: usize, need: usize, forced: bool, not_found: &[Rejected]) -> TooFew<'_> {
    TooFew { found, need, forced, not_found }
}

impl fmt::Display for TooFew<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let views = if self.found == 1 { "view" } else { "views" };
        write!(f, "the target was found in {} {views}, need at least {}", self.found, self.need)?;
        if !self.forced {
            write!(
                f,
                " for parameters and σ to be trusted (15–30 views are best; --force calibrates from as few as {})",
                crate::guard::ABSOLUTE_MIN_VIEWS
            )?;
        }
        if self.not_found.is_empty() {
            write!(f, "; every image showed the target: take more views")
        } else {
            write!(
                f,
                "; not found in {} of {} images: {}",
                self.not_found.len(),
                self.found + self.not_found.len(),
                Reasons(self.not_found)
            )
        }
    }
}

/// `name: reason; name: reason` of views not used.
struct Reasons<'a>(&'a [Rejected]);

impl fmt::Display for Reasons<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (i, r) in self.0.iter().enumerate() {
            if i > 0 {
                f.write_str("; ")?;
            }
            write!(f, "{}: {}", r.name, r.reason)?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn messages_hold_their_cause_and_name_the_kind() {
        let dir = PathBuf::from("/nonexistent/calibration-images");
        let e = CalibrateError::ReadFolder { dir: dir.clone(), cause: std::fs::read_dir(&dir).unwrap_err() };
        let text = e.to_string();
        assert!(text.starts_with("cannot read the image folder /nonexistent/calibration-images: "), "{text}");
        assert!(text.contains("No such file"), "{text}");
        assert!(std::error::Error::source(&e).is_none(), "the cause is in the message, not repeated by `{{:#}}`");
        assert!(e.is_bad_input());
        let e = CalibrateError::TooFewViews {
            found: 1,
            need: 3,
            forced: true,
            not_found: vec![
                Rejected { name: "a.png".into(), reason: "no checkerboard found".into() },
                Rejected { name: "b.png".into(), reason: "too dark".into() },
            ],
        };
        assert_eq!(
            e.to_string(),
            "the target was found in 1 view, need at least 3; not found in 2 of 3 images: a.png: no checkerboard found; b.png: too dark"
        );
        let e = CalibrateError::TooFewViews { found: 2, need: 10, forced: false, not_found: vec![] };
        let text = e.to_string();
        assert!(text.starts_with("the target was found in 2 views, need at least 10 for "), "{text}");
        assert!(text.contains("--force") && text.ends_with("every image showed the target: take more views"), "{text}");
        assert!(!text.contains("()"), "{text}");
        let e = CalibrateError::Grab { camera: "left".into(), message: "no camera delivered a frame within 5 s".into() };
        assert_eq!(e.to_string(), "camera left: no camera delivered a frame within 5 s");
        assert!(!e.is_bad_input());
        let e = CalibrateError::Write { path: "out/cam.yml".into(), cause: std::io::Error::other("disk full") };
        assert_eq!(e.to_string(), "cannot write out/cam.yml: disk full");
        assert!(!e.is_bad_input());
        let e: CalibrateError = "checkerboard:9:25".parse::<crate::target::TargetSpec>().unwrap_err().into();
        assert!(e.is_bad_input() && e.to_string().contains("COLSxROWS"), "{e}");
        fn send_sync<T: Send + Sync + 'static>() {}
        send_sync::<CalibrateError>();
    }
}
