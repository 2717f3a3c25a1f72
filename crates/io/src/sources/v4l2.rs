//! V4L2 cameras (`source = "v4l2:/dev/videoN"`) through the `v4l` crate.
//!
//! The device is opened, set to the configured size and the first pixel format it offers
//! among GREY, Y16, Y12, Y10, the raw colour mosaics RGGB, GRBG, GBRG, BA81, then YUYV and
//! MJPEG (in that order of preference: no decoding beats decoding, and a colour sensor's raw
//! mosaic, its sites' gains equalised, beats the luma of its demosaiced YUYV — see
//! `convert::bayer`; with the camera's `full_depth`, Y16, Y12, Y10 before GREY, kept at full
//! depth beside an 8-bit plane), and the configured frame rate when given; frames are streamed from
//! memory-mapped buffers. Of each buffer only `bytesused` bytes are read, buffers flagged
//! `V4L2_BUF_FLAG_ERROR` are counted as incomplete and never delivered, and the driver's
//! timestamp is mapped from CLOCK_MONOTONIC to the Unix epoch ([`map_buffer_timestamp`]).
//!
//! A camera that disappears (a read error such as ENODEV, or no frame for
//! `max(2 s, 10 frame periods)`) is reported as [`SourceEvent::Lost`] and reopened with
//! backoff (0.5 s doubling to 10 s) while the other cameras go on; streaming resumes with
//! [`SourceEvent::Reopened`]. The frame counter `seq` continues across reopenings and counts
//! every complete frame captured, so a gap in `seq` is a frame dropped on a full channel.
//!
//! The `v4l` crate's stream panics in `Drop` when `VIDIOC_STREAMOFF` fails with anything
//! but ENODEV (a device gone in another way). [`close_stream`] therefore stops the stream
//! itself first: after success or ENODEV (unplugged) the stream is dropped, which unmaps its
//! buffers and closes the file descriptor (under `catch_unwind` as a last guard); after any
//! other error it is leaked (its mappings and fd stay open until the process ends) rather
//! than risking an abort.
//!
//! Each wait for a buffer is a `poll` bounded by half a second (so the stop flag is seen);
//! the buffer is dequeued only once it is done, so a camera that pauses is never reported
//! lost for a buffer queued twice ([`ring_next`]).
//!
//! What is tested where: format conversion, `bytesused` handling and timestamp mapping are
//! pure functions tested on captured-buffer fixtures (tests/it/v4l2_convert.rs); the order of
//! queue/dequeue calls against a model of the kernel's buffer queue (unit tests below).
//! Opening a real device, format negotiation, frame-rate setting, the driver's timestamps,
//! unplugging and replugging are exercised against the kernel's virtual camera driver
//! (`vivid`) in a VM by `scripts/vivid-vm.sh` (not in CI); the README says what it showed
//! and which physical cameras have been checked.

use std::io;
use std::panic::AssertUnwindSafe;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::Duration;

use tokio::sync::mpsc::Sender;
use v4l::buffer::Type;
use v4l::io::mmap::Stream as MmapStream;
use v4l::io::traits::Stream as _;
use v4l::video::Capture;
use v4l::{Format, FourCC, Fraction};

mod ring;

use ring::{ring_next, RingNext, RingState};

use crate::sources::capture::{CaptureSession, Captured, LiveCamera, LoopTiming, SourceError, SourceEvent};
use crate::sources::convert::{to_gray8_into, BayerPattern, ConvertError, PixelLayout};
use tagdeflect_core::camera_config::CameraConfig;
use tagdeflect_core::clock::{now_epoch_ns, MonotonicToEpoch};
use tagdeflect_core::frame::GrayImage;

/// Pixel formats requested from the device, most preferred first.
pub(crate) const PREFERRED_FOURCCS: [[u8; 4]; 10] =
    [*b"GREY", *b"Y16 ", *b"Y12 ", *b"Y10 ", *b"RGGB", *b"GRBG", *b"GBRG", *b"BA81", *b"YUYV", *b"MJPG"];

/// `V4L2_BUF_FLAG_TIMESTAMP_MASK`.
pub(crate) const TIMESTAMP_MASK: u32 = 0x0000_e000;
/// `V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC`: the buffer time is on CLOCK_MONOTONIC.
pub(crate) const TIMESTAMP_MONOTONIC: u32 = 0x0000_2000;
/// `V4L2_BUF_FLAG_ERROR`: the buffer is done but its data is corrupted.
pub const BUF_FLAG_ERROR: u32 = 0x0000_0040;

/// Buffers in the memory-mapped ring.
const N_BUFFERS: u32 = 4;
/// How long one dequeue waits before checking the stop flag.
const DEQUEUE_TIMEOUT: Duration = Duration::from_millis(500);

/// The formats in the order a camera is asked for them: [`PREFERRED_FOURCCS`], or with
/// `full_depth` the 16-bit grey ones first (`Y16`, `Y12`, `Y10`, then `GREY`, ...).
pub(crate) fn preference(full_depth: bool) -> [[u8; 4]; 10] {
    let mut order = PREFERRED_FOURCCS;
    if full_depth {
        order[..4].rotate_left(1);
    }
    order
}

/// The converter for a V4L2 fourcc, if supported.
pub fn fourcc_layout(fourcc: [u8; 4]) -> Option<PixelLayout> {
    match &fourcc {
        b"GREY" => Some(PixelLayout::Gray8),
        b"Y16 " => Some(PixelLayout::Gray16Le { bits: 16 }),
        b"Y12 " => Some(PixelLayout::Gray16Le { bits: 12 }),
        b"Y10 " => Some(PixelLayout::Gray16Le { bits: 10 }),
        b"RGGB" => Some(PixelLayout::Bayer8(BayerPattern::Rggb)),
        b"GRBG" => Some(PixelLayout::Bayer8(BayerPattern::Grbg)),
        b"GBRG" => Some(PixelLayout::Bayer8(BayerPattern::Gbrg)),
        b"BA81" => Some(PixelLayout::Bayer8(BayerPattern::Bggr)),
        b"YUYV" => Some(PixelLayout::Yuyv),
        b"MJPG" | b"JPEG" => Some(PixelLayout::Mjpeg),
        _ => None,
    }
}

/// Which clock a frame's time came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TimeSource {
    /// The driver's CLOCK_MONOTONIC buffer timestamp, mapped to the epoch.
    Driver,
    /// The host's epoch clock when the buffer was dequeued (driver time unusable).
    Receive,
}

/// Maps a V4L2 buffer timestamp to ns since the Unix epoch.
///
/// The driver's time (`sec`, `usec`) is used when `flags` says it is on CLOCK_MONOTONIC,
/// it is non-zero, and once mapped it lies between 2 s before and 10 ms after the receive
/// time (a buffer cannot be stamped after it was dequeued; older than 2 s means a broken
/// stamp). Otherwise — `TIMESTAMP_UNKNOWN`, `TIMESTAMP_COPY` (an output's time copied
/// through), a zero or implausible stamp — the receive time is used.
pub fn map_buffer_timestamp(flags: u32, sec: i64, usec: i64, clock: MonotonicToEpoch, receive_epoch_ns: i64) -> (i64, TimeSource) {
    if flags & TIMESTAMP_MASK == TIMESTAMP_MONOTONIC && (sec != 0 || usec != 0) {
        let mono = sec.saturating_mul(1_000_000_000).saturating_add(usec.saturating_mul(1_000));
        let t = clock.to_epoch(mono);
        if t <= receive_epoch_ns + 10_000_000 && t >= receive_epoch_ns - 2_000_000_000 {
            return (t, TimeSource::Driver);
        }
    }
    (receive_epoch_ns, TimeSource::Receive)
}

/// What one dequeued buffer turned out to be.
#[derive(Debug)]
pub enum BufferOutcome {
    /// A complete converted image.
    Image(GrayImage),
    /// The driver flagged the buffer as corrupted.
    Corrupted,
    /// The bytes could not be converted.
    Bad(ConvertError),
}

/// Turns a dequeued buffer into an image: reads only the first `bytesused` bytes of the
/// mapping (the rest is stale data of earlier frames), rejects buffers flagged
/// [`BUF_FLAG_ERROR`], converts to 8-bit grey. `stride` is the format's `bytesperline`.
pub fn convert_buffer(
    layout: PixelLayout,
    width: u32,
    height: u32,
    stride: u32,
    mapped: &[u8],
    bytesused: u32,
    flags: u32,
) -> BufferOutcome {
    let mut img = GrayImage::new(0, 0);
    match convert_buffer_into(layout, width, height, stride, mapped, bytesused, flags, &mut img) {
        Ok(()) => BufferOutcome::Image(img),
        Err(BufferRejected::Corrupted) => BufferOutcome::Corrupted,
        Err(BufferRejected::Bad(e)) => BufferOutcome::Bad(e),
    }
}

/// Why a dequeued buffer gave no image.
#[derive(Debug)]
pub(crate) enum BufferRejected {
    /// The driver flagged the buffer as corrupted.
    Corrupted,
    /// The bytes could not be converted.
    Bad(ConvertError),
}

/// [`convert_buffer`] into `out` (a recycled frame buffer).
#[allow(clippy::too_many_arguments)]
pub(crate) fn convert_buffer_into(
    layout: PixelLayout,
    width: u32,
    height: u32,
    stride: u32,
    mapped: &[u8],
    bytesused: u32,
    flags: u32,
    out: &mut GrayImage,
) -> Result<(), BufferRejected> {
    if flags & BUF_FLAG_ERROR != 0 {
        return Err(BufferRejected::Corrupted);
    }
    let valid = &mapped[..(bytesused as usize).min(mapped.len())];
    to_gray8_into(layout, width, height, stride as usize, valid, out).map_err(BufferRejected::Bad)
}

/// An open, configured, streaming device.
struct Session {
    // Field order matters: the stream is closed (by `close_stream`) before the device.
    stream: Option<MmapStream<'static>>,
    /// Where the buffer ring stands (see [`ring_next`]).
    ring: RingState,
    _dev: v4l::Device,
    layout: PixelLayout,
    width: u32,
    height: u32,
    stride: u32,
}

/// Why a V4L2 device could not be opened as the config asks.
#[derive(Debug, thiserror::Error)]
pub enum V4l2OpenError {
    /// The device cannot be opened.
    #[error("cannot open {path}: {source}")]
    Device {
        /// The device.
        path: String,
        /// Why.
        source: io::Error,
    },
    /// The device gives another size than the config's.
    #[error("{path} offers {got_width}x{got_height} in {fourcc}, the config asks for {width}x{height} (the intrinsics are for that size)")]
    Size {
        /// The device.
        path: String,
        /// What it gives, px.
        got_width: u32,
        /// What it gives, px.
        got_height: u32,
        /// In this format.
        fourcc: String,
        /// What the config asks for, px.
        width: u32,
        /// What the config asks for, px.
        height: u32,
    },
    /// A format the device offers cannot be set.
    #[error("{path}: cannot set format {fourcc}: {source}")]
    SetFormat {
        /// The device.
        path: String,
        /// The format.
        fourcc: String,
        /// Why.
        source: io::Error,
    },
    /// The device offers none of the formats read.
    #[error("{path} offers none of GREY, Y16, Y12, Y10, RGGB, GRBG, GBRG, BA81, YUYV, MJPG (it offers {offered})")]
    NoFormat {
        /// The device.
        path: String,
        /// What it offers, comma-separated.
        offered: String,
    },
    /// The format set is not one that can be converted.
    #[error("{path}: unsupported format")]
    Unsupported {
        /// The device.
        path: String,
    },
    /// The capture buffers cannot be mapped.
    #[error("{path}: cannot map buffers: {source}")]
    Buffers {
        /// The device.
        path: String,
        /// Why.
        source: io::Error,
    },
}

impl Session {
    fn open(path: &str, cfg: &CameraConfig) -> Result<Session, V4l2OpenError> {
        let dev = v4l::Device::with_path(path).map_err(|source| V4l2OpenError::Device { path: path.into(), source })?;
        let offered: Vec<[u8; 4]> = match dev.enum_formats() {
            Ok(list) => list.iter().map(|d| d.fourcc.repr).collect(),
            Err(_) => PREFERRED_FOURCCS.to_vec(),
        };
        let mut chosen = None;
        for want in preference(cfg.full_depth).iter().filter(|f| offered.contains(f)) {
            let req = Format::new(cfg.width, cfg.height, FourCC::new(want));
            match dev.set_format(&req) {
                Ok(got) if got.fourcc.repr == *want => {
                    if got.width != cfg.width || got.height != cfg.height {
                        return Err(V4l2OpenError::Size {
                            path: path.into(),
                            got_width: got.width,
                            got_height: got.height,
                            fourcc: String::from_utf8_lossy(want).into_owned(),
                            width: cfg.width,
                            height: cfg.height,
                        });
                    }
                    chosen = Some(got);
                    break;
                }
                Ok(_) => continue,
                Err(source) => {
                    return Err(V4l2OpenError::SetFormat { path: path.into(), fourcc: String::from_utf8_lossy(want).into_owned(), source })
                }
            }
        }
        let fmt = chosen.ok_or_else(|| {
            let names: Vec<String> = offered.iter().map(|f| String::from_utf8_lossy(f).into_owned()).collect();
            V4l2OpenError::NoFormat { path: path.into(), offered: names.join(", ") }
        })?;
        let layout = fourcc_layout(fmt.fourcc.repr).ok_or_else(|| V4l2OpenError::Unsupported { path: path.into() })?;
        if let Some(fps) = cfg.fps.filter(|f| *f > 0.0) {
            // Frame interval = numerator / denominator seconds.
            let params = v4l::video::capture::Parameters::new(Fraction::new(1000, (fps * 1000.0).round() as u32));
            match dev.set_params(&params) {
                Ok(p) if p.interval.numerator > 0 => {
                    let got = p.interval.denominator as f64 / p.interval.numerator as f64;
                    if (got - fps).abs() > 0.01 * fps {
                        tracing::warn!(path, requested = fps, got, "camera runs at a different frame rate");
                    }
                }
                Ok(_) => {}
                Err(e) => tracing::warn!(path, fps, error = %e, "cannot set the frame rate; using the device's"),
            }
        }
        let mut stream = MmapStream::with_buffers(&dev, Type::VideoCapture, N_BUFFERS)
            .map_err(|source| V4l2OpenError::Buffers { path: path.into(), source })?;
        stream.set_timeout(DEQUEUE_TIMEOUT);
        tracing::info!(path, fourcc = %String::from_utf8_lossy(&fmt.fourcc.repr), width = fmt.width, height = fmt.height, stride = fmt.stride, "v4l2 camera open");
        Ok(Session {
            stream: Some(stream),
            ring: RingState::Fresh,
            _dev: dev,
            layout,
            width: fmt.width,
            height: fmt.height,
            stride: fmt.stride,
        })
    }
}

impl CaptureSession for Session {
    /// Waits for and dequeues one buffer ([`ring_next`]).
    fn next(&mut self, into: &mut GrayImage) -> Captured {
        let Some(stream) = self.stream.as_mut() else {
            return Captured::Failed("stream closed".into());
        };
        let (layout, width, height, stride) = (self.layout, self.width, self.height, self.stride);
        let got = ring_next(stream, &mut self.ring, N_BUFFERS as usize, DEQUEUE_TIMEOUT, |b| {
            let receive = now_epoch_ns();
            // The process clock's current mapping: a wall-clock step re-maps every source at once.
            let clock = MonotonicToEpoch::current();
            let (t_ns, _) = map_buffer_timestamp(b.flags, b.sec, b.usec, clock, receive);
            match convert_buffer_into(layout, width, height, stride, b.data, b.bytesused, b.flags, into) {
                Ok(()) => Captured::Image(t_ns),
                Err(BufferRejected::Corrupted) => Captured::Incomplete("buffer flagged V4L2_BUF_FLAG_ERROR".into()),
                Err(BufferRejected::Bad(e)) => Captured::Bad(e.to_string()),
            }
        });
        match got {
            RingNext::Buffer(c) => c,
            RingNext::Timeout => Captured::Timeout,
            RingNext::Failed(e) => Captured::Failed(e.to_string()),
        }
    }
}

impl Drop for Session {
    fn drop(&mut self) {
        if let Some(stream) = self.stream.take() {
            close_stream(stream);
        }
    }
}

/// What to do with a stream whose `STREAMOFF` returned `errno` (`None`: it succeeded).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum CloseAction {
    /// Drop it: its `Drop` unmaps the buffers and closes the fd without panicking — after a
    /// successful STREAMOFF, or on `ENODEV` (the device was unplugged), which the `v4l` crate's
    /// `Drop` impls ignore after unmapping.
    Release,
    /// Any other error: the crate's `Drop` would panic, and its buffer arena would panic again
    /// while unwinding (an abort), so the stream is kept alive (leaked, logged). A device that
    /// refuses STREAMOFF for another reason is still open and usable by nobody else anyway.
    Leak,
}

/// The decision of [`close_stream`], apart for testing.
pub(crate) fn close_action(streamoff_errno: Option<i32>) -> CloseAction {
    match streamoff_errno {
        None => CloseAction::Release,
        Some(libc::ENODEV) => CloseAction::Release,
        Some(_) => CloseAction::Leak,
    }
}

/// Stops and releases a stream without letting the `v4l` crate's `Drop` panic on a device
/// that is gone: stopped by hand first, then released ([`close_action`]): an unplugged camera
/// (`ENODEV`) gives back its fd and mappings, so unplugging and replugging a camera for hours
/// leaks nothing.
fn close_stream(mut stream: MmapStream<'static>) {
    let errno = match stream.stop() {
        Ok(()) => None,
        Err(e) => Some(e.raw_os_error().unwrap_or(libc::EIO)),
    };
    match close_action(errno) {
        CloseAction::Release => {
            if errno.is_some() {
                tracing::info!("v4l2 STREAMOFF: device gone; releasing its buffers and file descriptor");
            }
            if std::panic::catch_unwind(AssertUnwindSafe(move || drop(stream))).is_err() {
                tracing::warn!("v4l2 stream panicked while closing; ignored");
            }
        }
        CloseAction::Leak => {
            tracing::error!(errno, "v4l2 STREAMOFF failed: keeping the stream's buffers rather than risking an abort");
            std::mem::forget(stream);
        }
    }
}

/// Opens `path` in a new capture thread and returns once it streams (see [`crate::sources::spawn_camera`]).
pub(crate) fn spawn(
    index: usize,
    cfg: &CameraConfig,
    path: &str,
    policy: crate::sources::capture::OpenPolicy,
    tx: Sender<SourceEvent>,
    stop: Arc<AtomicBool>,
) -> Result<LiveCamera, SourceError> {
    let name = cfg.name.clone();
    let timing = LoopTiming::for_fps(cfg.fps);
    let source = format!("v4l2:{path}");
    let (cfg, path) = (cfg.clone(), path.to_string());
    crate::sources::capture::spawn_capture(index, &name, source, move || Session::open(&path, &cfg), timing, policy, tx, stop)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_preferred_fourcc_has_a_converter() {
        for f in PREFERRED_FOURCCS {
            assert!(fourcc_layout(f).is_some(), "{}", String::from_utf8_lossy(&f));
        }
        assert_eq!(fourcc_layout(*b"RGB3"), None);
    }

    #[test]
    fn an_unplugged_device_is_released_not_leaked() {
        assert_eq!(close_action(None), CloseAction::Release);
        assert_eq!(close_action(Some(libc::ENODEV)), CloseAction::Release);
        assert_eq!(close_action(Some(libc::EBUSY)), CloseAction::Leak);
    }

    #[test]
    fn opening_a_missing_device_is_an_error() {
        let cfg_err = Session::open("/dev/video-does-not-exist", &test_cfg());
        assert!(cfg_err.is_err());
        let msg = cfg_err.err().map(|e| e.to_string()).unwrap_or_default();
        assert!(msg.contains("/dev/video-does-not-exist"), "{msg}");
    }

    #[test]
    fn full_depth_asks_for_the_deep_formats_first() {
        assert_eq!(preference(false), PREFERRED_FOURCCS);
        assert_eq!(preference(true), [*b"Y16 ", *b"Y12 ", *b"Y10 ", *b"GREY", *b"RGGB", *b"GRBG", *b"GBRG", *b"BA81", *b"YUYV", *b"MJPG"]);
    }

    fn test_cfg() -> CameraConfig {
        toml::from_str("name = \"t\"\nsource = \"v4l2:/dev/video-does-not-exist\"\nwidth = 64\nheight = 48\nfx = 100.0\nfy = 100.0\ncx = 31.5\ncy = 23.5\n")
            .expect("test camera config")
    }
}
