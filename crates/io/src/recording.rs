//! Recordings (SPEC "Recording"): a folder with `tagdeflect.toml`, `frames.jsonl`, the
//! frames as 8-bit grey PNG or binary PGM, optional `utm.jsonl` and `truth.jsonl`.
//!
//! Reading policy (documented decision): the index files are read whole when the
//! recording is opened. A *truncated last line* of `frames.jsonl`, `utm.jsonl` or
//! `truth.jsonl` (no trailing newline and not valid JSON — what a recorder killed
//! mid-write leaves) is skipped with a warning; any other malformed line is an error
//! naming the file and line. A frame whose file is missing, corrupt, not 8-bit grey or
//! of another size than the camera's is an error from [`Recording::load_image`] naming
//! the file; the replay pipeline logs it and skips that frame (the frame set is solved
//! from the other cameras), so a single bad frame never stops a long replay and never
//! yields a silently wrong result.
//!
//! Writing: [`RecordingWriter`] appends one JSON line per frame / sample and flushes it,
//! so a recording cut short by a crash or a full disk stays readable up to the last
//! complete line.

use serde::{Deserialize, Serialize};
use std::fs;
use std::io::{BufRead, BufReader, Read};
use std::path::{Path, PathBuf};

use crate::utm::UtmSample;
use tagdeflect_core::camera_config::CameraConfig;
use tagdeflect_core::frame::GrayImage;
use tagdeflect_core::linefile::LineFile;

mod frames;
mod image_file;
pub use frames::{CameraList, FrameReader, ReadFrame};
pub(crate) use image_file::read_gray_into_checked;
pub use image_file::{decode_gray_bytes, read_gray_into, ImageError};
pub use tagdeflect_core::frame::{encode_png, FrameFormat};

/// Name of the config file inside a recording.
pub const CONFIG_FILE: &str = "tagdeflect.toml";
/// Name of the frame index.
pub const FRAMES_FILE: &str = "frames.jsonl";
/// Name of the UTM samples file.
pub const UTM_FILE: &str = "utm.jsonl";
/// Name of the ground-truth file.
pub const TRUTH_FILE: &str = "truth.jsonl";

/// A problem with a recording, naming the file (and line) at fault.
#[derive(Debug, thiserror::Error)]
pub enum RecordingError {
    /// The folder or a file cannot be read or written.
    #[error("{path}: {source}")]
    Io {
        /// The file or folder.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// A line of an index file is malformed.
    #[error("{path}:{line}: {message}")]
    BadLine {
        /// The file.
        path: PathBuf,
        /// 1-based line.
        line: usize,
        /// What is wrong.
        message: String,
    },
    /// The recording's config is invalid (the config's own error, located in its file).
    #[error("{0}")]
    Config(Box<dyn std::error::Error + Send + Sync>),
    /// A frame image cannot be used.
    #[error("{path}: {message}")]
    BadImage {
        /// The image file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// The recording is unusable as a whole (e.g. no frames).
    #[error("{path}: {message}")]
    Invalid {
        /// The recording folder.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
}

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> RecordingError + '_ {
    move |source| RecordingError::Io { path: path.to_path_buf(), source }
}

/// One line of `frames.jsonl`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct FrameEntry {
    /// Camera name (a `[[camera]]` of the config).
    pub camera: String,
    /// That camera's frame counter.
    pub seq: u64,
    /// Capture time, ns since the Unix epoch.
    pub t_ns: i64,
    /// Image file, relative to the recording.
    pub file: String,
}

/// One specimen tag's true centre in a `truth.jsonl` line.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TruthTag {
    /// Specimen tag id.
    pub id: u32,
    /// Centre of the black square, world frame, mm.
    pub center_mm: [f64; 3],
}

/// One line of `truth.jsonl`: ground truth of one frame set.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TruthLine {
    /// The frame set's nominal time, ns since the Unix epoch.
    pub t_ns: i64,
    /// Every specimen tag's true centre.
    pub tags: Vec<TruthTag>,
}

/// The config a recording carries (`tagdeflect.toml`): the binary's whole config, of which a
/// recording needs only the cameras and the text to write.
pub trait RecordedConfig: Clone + std::fmt::Debug + Send + Sync + 'static {
    /// Why a config file cannot be used.
    type Error: std::error::Error + Send + Sync + 'static;
    /// Reads and validates a config file.
    fn load(path: &Path) -> Result<Self, Self::Error>;
    /// The cameras, in config order.
    fn cameras(&self) -> &[CameraConfig];
    /// The config as TOML (what a recording keeps).
    fn to_toml_string(&self) -> String;
    /// Index of the camera with this name.
    fn camera_index(&self, name: &str) -> Option<usize> {
        self.cameras().iter().position(|c| c.name == name)
    }
}

/// An opened recording: config and indexes in memory, images loaded on demand.
#[derive(Debug, Clone)]
pub struct Recording<C> {
    /// The recording folder.
    pub dir: PathBuf,
    /// The config in force when it was recorded (or the override given to `open_with`).
    pub config: C,
    /// Frames sorted by time (then camera index).
    pub frames: Vec<FrameEntry>,
    /// UTM samples sorted by time (empty without `utm.jsonl`).
    pub utm: Vec<UtmSample>,
    /// Ground truth lines sorted by time (empty without `truth.jsonl`).
    pub truth: Vec<TruthLine>,
    /// Lines skipped as truncated, for reporting.
    pub skipped_lines: Vec<String>,
}

impl<C: RecordedConfig> Recording<C> {
    /// Opens a recording with its own config.
    pub fn open(dir: &Path) -> Result<Recording<C>, RecordingError> {
        let config = C::load(&dir.join(CONFIG_FILE)).map_err(|e| RecordingError::Config(Box::new(e)))?;
        Self::open_with(dir, config)
    }

    /// Opens a recording with a given config (`replay --config`). Cameras are matched by
    /// name; frames of cameras the config does not name are an error.
    pub fn open_with(dir: &Path, config: C) -> Result<Recording<C>, RecordingError> {
        if !dir.is_dir() {
            return Err(RecordingError::Invalid {
                path: dir.to_path_buf(),
                message: "not a recording folder (it does not exist or is not a folder)".into(),
            });
        }
        let mut skipped = Vec::new();
        let frames_path = dir.join(FRAMES_FILE);
        if !frames_path.exists() {
            return Err(RecordingError::Invalid { path: frames_path, message: "missing: a recording needs frames.jsonl".into() });
        }
        let mut frames: Vec<FrameEntry> = read_jsonl(&frames_path, &mut skipped)?;
        for (i, f) in frames.iter().enumerate() {
            if config.camera_index(&f.camera).is_none() {
                return Err(RecordingError::BadLine {
                    path: frames_path.clone(),
                    line: i + 1,
                    message: format!("camera \"{}\" is not a [[camera]] of the config", f.camera),
                });
            }
            if Path::new(&f.file).is_absolute() || f.file.split(['/', '\\']).any(|c| c == "..") {
                return Err(RecordingError::BadLine {
                    path: frames_path.clone(),
                    line: i + 1,
                    message: format!("file \"{}\" must be relative to the recording", f.file),
                });
            }
        }
        if frames.is_empty() {
            return Err(RecordingError::Invalid { path: frames_path, message: "the recording holds no frames".into() });
        }
        frames.sort_by_key(|f| (f.t_ns, config.camera_index(&f.camera), f.seq));
        let utm_path = dir.join(UTM_FILE);
        let mut utm: Vec<UtmSample> = if utm_path.exists() { read_jsonl(&utm_path, &mut skipped)? } else { Vec::new() };
        utm.sort_by_key(|s| s.t_ns);
        let truth_path = dir.join(TRUTH_FILE);
        let mut truth: Vec<TruthLine> = if truth_path.exists() { read_jsonl(&truth_path, &mut skipped)? } else { Vec::new() };
        truth.sort_by_key(|s| s.t_ns);
        Ok(Recording { dir: dir.to_path_buf(), config, frames, utm, truth, skipped_lines: skipped })
    }

    /// Loads a frame's image and checks it against its camera's size.
    pub fn load_image(&self, entry: &FrameEntry) -> Result<GrayImage, RecordingError> {
        let mut img = GrayImage::new(0, 0);
        self.load_image_into(entry, &mut img, &mut Vec::new())?;
        Ok(img)
    }

    /// [`Recording::load_image`] into `img`, with `scratch` for the compressed bytes
    /// (both reused between frames by a reader).
    pub fn load_image_into(&self, entry: &FrameEntry, img: &mut GrayImage, scratch: &mut Vec<u8>) -> Result<(), RecordingError> {
        let path = self.dir.join(&entry.file);
        let cams = self.config.cameras();
        let expect = self.config.camera_index(&entry.camera).map(|i| (cams[i].width, cams[i].height));
        read_gray_into_checked(&path, img, scratch, expect)?;
        if let Some(cam) = self.config.camera_index(&entry.camera).map(|i| &cams[i]) {
            if img.width != cam.width || img.height != cam.height {
                return Err(RecordingError::BadImage {
                    path,
                    message: format!("image is {}x{} but camera \"{}\" is {}x{}", img.width, img.height, cam.name, cam.width, cam.height),
                });
            }
        }
        Ok(())
    }
}

/// Longest line accepted in an index file (`frames.jsonl`, `utm.jsonl`, `truth.jsonl`):
/// real lines are a few hundred bytes; a longer one is corrupt.
pub(crate) const MAX_JSONL_LINE: usize = 1 << 20;

/// Reads a JSON Lines file line by line (never the whole file at once; each line at most
/// [`MAX_JSONL_LINE`] bytes), skipping (and recording) a truncated last line.
fn read_jsonl<T: for<'de> Deserialize<'de>>(path: &Path, skipped: &mut Vec<String>) -> Result<Vec<T>, RecordingError> {
    let file = tagdeflect_core::text_file::open_regular(path).map_err(io_err(path))?;
    read_jsonl_from(BufReader::new(file), path, skipped)
}

/// [`read_jsonl`] over any reader (`path` names it in errors); used by the fuzz targets.
pub fn read_jsonl_from<T: for<'de> Deserialize<'de>, R: BufRead>(
    mut reader: R,
    path: &Path,
    skipped: &mut Vec<String>,
) -> Result<Vec<T>, RecordingError> {
    let mut out = Vec::new();
    let mut buf = Vec::new();
    let mut lineno = 0;
    loop {
        buf.clear();
        let n = (&mut reader).take(MAX_JSONL_LINE as u64 + 1).read_until(b'\n', &mut buf).map_err(io_err(path))?;
        if n == 0 {
            break;
        }
        lineno += 1;
        let ends_with_newline = buf.last() == Some(&b'\n');
        if !ends_with_newline && buf.len() > MAX_JSONL_LINE {
            return Err(RecordingError::BadLine {
                path: path.to_path_buf(),
                line: lineno,
                message: format!("line longer than {MAX_JSONL_LINE} bytes: not a recording index line"),
            });
        }
        let text = match std::str::from_utf8(&buf) {
            Ok(t) => t,
            Err(e) => {
                return Err(RecordingError::BadLine { path: path.to_path_buf(), line: lineno, message: format!("not UTF-8 text: {e}") })
            }
        };
        let line = text.trim_end_matches(['\n', '\r']);
        if line.trim().is_empty() {
            continue;
        }
        match serde_json::from_str::<T>(line) {
            Ok(v) => out.push(v),
            Err(e) => {
                // The last line of the file (nothing follows) without its newline.
                let last = !ends_with_newline && reader.fill_buf().map_err(io_err(path))?.is_empty();
                if last && e.is_eof() {
                    let msg = format!("{}:{}: truncated last line skipped", path.display(), lineno);
                    tracing::warn!("{msg}");
                    skipped.push(msg);
                } else {
                    return Err(RecordingError::BadLine { path: path.to_path_buf(), line: lineno, message: e.to_string() });
                }
            }
        }
    }
    Ok(out)
}

/// Writes a recording: the config, frames (PNG unless [`RecordingWriter::with_format`]
/// says otherwise), and the index lines (each flushed).
pub struct RecordingWriter {
    dir: PathBuf,
    format: FrameFormat,
    frames: LineFile,
    utm: Option<LineFile>,
    truth: Option<LineFile>,
}

impl RecordingWriter {
    /// Creates the folder (it must not hold a recording already) and writes the config.
    pub fn create(dir: &Path, config: &impl RecordedConfig) -> Result<RecordingWriter, RecordingError> {
        if dir.join(FRAMES_FILE).exists() {
            return Err(RecordingError::Invalid {
                path: dir.to_path_buf(),
                message: "already holds a recording; choose a new folder".into(),
            });
        }
        fs::create_dir_all(dir).map_err(io_err(dir))?;
        for cam in config.cameras() {
            let p = dir.join(&cam.name);
            fs::create_dir_all(&p).map_err(io_err(&p))?;
        }
        let cfg_path = dir.join(CONFIG_FILE);
        fs::write(&cfg_path, config.to_toml_string()).map_err(io_err(&cfg_path))?;
        let frames_path = dir.join(FRAMES_FILE);
        let (frames, _) = LineFile::open_append(&frames_path).map_err(io_err(&frames_path))?;
        Ok(RecordingWriter { dir: dir.to_path_buf(), format: FrameFormat::Png, frames, utm: None, truth: None })
    }

    /// Writes the frames in `format` from now on.
    pub fn with_format(mut self, format: FrameFormat) -> Self {
        self.format = format;
        self
    }

    /// The recording folder.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Writes a frame as `<camera>/<seq>.<png|pgm>` and its index line. The image is written
    /// under a temporary name (`.<seq>.<ext>.part`) and renamed once complete, so an image
    /// named in `frames.jsonl` is never a fragment; a failed write leaves no file behind.
    pub fn write_frame(&mut self, camera: &str, seq: u64, t_ns: i64, image: &GrayImage) -> Result<(), RecordingError> {
        let file = format!("{camera}/{seq:06}.{}", self.format.extension());
        let path = self.dir.join(&file);
        let bytes = self.format.encode(image).map_err(|m| RecordingError::BadImage { path: path.clone(), message: m.to_string() })?;
        let tmp = self.dir.join(format!("{camera}/.{seq:06}.{}.part", self.format.extension()));
        if let Err(e) = fs::write(&tmp, bytes).and_then(|_| fs::rename(&tmp, &path)) {
            let _ = fs::remove_file(&tmp);
            return Err(RecordingError::Io { path, source: e });
        }
        self.write_frame_entry(&FrameEntry { camera: camera.to_string(), seq, t_ns, file })
    }

    /// Writes a frame index line for an image already in place.
    pub fn write_frame_entry(&mut self, entry: &FrameEntry) -> Result<(), RecordingError> {
        let path = self.dir.join(FRAMES_FILE);
        write_line(&mut self.frames, entry).map_err(io_err(&path))
    }

    /// Appends a UTM sample to `utm.jsonl`.
    pub fn write_utm(&mut self, sample: &UtmSample) -> Result<(), RecordingError> {
        let path = self.dir.join(UTM_FILE);
        let w = open_append(&mut self.utm, &path)?;
        write_line(w, sample).map_err(io_err(&path))
    }

    /// Appends a ground-truth line to `truth.jsonl`.
    pub fn write_truth(&mut self, line: &TruthLine) -> Result<(), RecordingError> {
        let path = self.dir.join(TRUTH_FILE);
        let w = open_append(&mut self.truth, &path)?;
        write_line(w, line).map_err(io_err(&path))
    }

    /// `fdatasync` of the index files when the last one is a second old (see
    /// [`tagdeflect_core::linefile`]).
    pub fn sync_if_due(&mut self) -> Result<(), RecordingError> {
        let dir = self.dir.clone();
        for w in [Some(&mut self.frames), self.utm.as_mut(), self.truth.as_mut()].into_iter().flatten() {
            w.sync_if_due().map_err(io_err(&dir))?;
        }
        Ok(())
    }

    /// Syncs everything.
    pub fn finish(mut self) -> Result<(), RecordingError> {
        let dir = self.dir.clone();
        for w in [Some(&mut self.frames), self.utm.as_mut(), self.truth.as_mut()].into_iter().flatten() {
            w.sync().map_err(io_err(&dir))?;
        }
        Ok(())
    }
}

fn open_append<'a>(slot: &'a mut Option<LineFile>, path: &Path) -> Result<&'a mut LineFile, RecordingError> {
    if slot.is_none() {
        let (f, _) = LineFile::open_append(path).map_err(io_err(path))?;
        *slot = Some(f);
    }
    Ok(slot.as_mut().expect("just opened"))
}

/// One JSON line, written whole or not at all (a failed write is cut back).
fn write_line<T: Serialize>(w: &mut LineFile, value: &T) -> std::io::Result<()> {
    let mut text = serde_json::to_vec(value).map_err(std::io::Error::other)?;
    text.push(b'\n');
    w.write_line(&text)
}

/// Reads a JSON Lines file of any type (used by tests and tools), with the same
/// truncated-last-line policy as recordings.
pub fn read_jsonl_file<T: for<'de> Deserialize<'de>>(path: &Path) -> Result<Vec<T>, RecordingError> {
    let mut skipped = Vec::new();
    read_jsonl(path, &mut skipped)
}
