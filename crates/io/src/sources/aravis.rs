//! GigE Vision and USB3 Vision cameras (`source = "aravis:<device id>"`) through Aravis.
//!
//! The device id is what Aravis calls it (`arv-tool-0.8` lists them: e.g.
//! `Basler-21234567`), a GigE camera's IP address, or — for tests and demos — Aravis's
//! in-process fake camera (`Fake_1`, `Aravis-Fake-GV01`; any id starting with `Fake` or
//! `Aravis-Fake` enables Aravis's "Fake" interface first).
//!
//! Opening sets Mono8 when the camera offers it, else Mono16/Mono12/Mono10 (with the
//! camera's `full_depth`, the deep formats first; kept at full depth beside an 8-bit plane,
//! see [`crate::sources::convert`]), else a colour sensor's raw mosaic BayerRG8/GR8/GB8/BG8
//! (its sites' gains equalised, no demosaic: [`crate::sources::convert::bayer`]), the configured size as the region of interest, continuous
//! acquisition and the configured frame rate when the camera supports setting it. The
//! stream gets [`AravisOptions::n_buffers`] buffers of the camera's payload size; on GigE
//! packet resend is enabled. Every popped buffer's status is checked: only
//! `ARV_BUFFER_STATUS_SUCCESS` image buffers of the configured size are converted and
//! delivered; anything else (missing packets, timeout, wrong packet id, size mismatch,
//! aborted, a wrong image size) is counted as [`DropReason::Incomplete`] and the buffer
//! requeued — never fed to the detector. Frames the stream could not even start for lack
//! of a free buffer (underruns) are counted as incomplete too.
//!
//! Time stamps: each frame gets the buffer's *system timestamp*, which Aravis sets from the
//! host's realtime clock (`g_get_real_time`, µs resolution, Unix epoch) when the frame's
//! first packet arrives — the same clock as the UTM and the rest of the product. If that is
//! absent or implausible (more than 10 s from the receive time) the camera's own timestamp
//! is mapped with a [`DeviceClockMap`] anchored at the first frame, and failing that the
//! receive time is used.
//!
//! A camera that stops delivering complete frames for `max(2 s, 10 frame periods)` (cable
//! pulled, camera power-cycled) is reported [`SourceEvent::Lost`] and reopened with backoff
//! (0.5 s doubling to 10 s); [`SourceEvent::Reopened`] follows when it streams again.
//! Tested against Aravis's in-process fake camera and `arv-fake-gv-camera-0.8` on loopback,
//! with and without packet loss (tests/it/aravis_fake.rs).
#![allow(unsafe_code)] // FFI module: every `unsafe` block carries its SAFETY comment.

use std::ffi::CString;
use std::sync::atomic::AtomicBool;
use std::sync::{Arc, Mutex, Once};
use std::time::Duration;

use aravis::glib::prelude::Cast;
use aravis::prelude::*;
use aravis::{AcquisitionMode, Buffer, BufferPayloadType, BufferStatus, Camera, GvStream, GvStreamPacketResend, PixelFormat, Stream};
use tokio::sync::mpsc::Sender;

use crate::sources::capture::{CaptureSession, Captured, LiveCamera, LoopTiming, SourceError, SourceEvent};
use crate::sources::convert::{to_gray8_into, BayerPattern, ConvertError, PixelLayout};
use tagdeflect_core::camera_config::CameraConfig;
use tagdeflect_core::clock::{now_epoch_ns, DeviceClockMap};
use tagdeflect_core::frame::GrayImage;

/// Tuning of an Aravis stream (defaults suit the product; tests change them).
#[derive(Debug, Clone)]
pub struct AravisOptions {
    /// Buffers queued on the stream (frames in flight).
    pub n_buffers: usize,
    /// Ask a GigE camera to resend lost packets.
    pub packet_resend: bool,
    /// How long one pop waits before checking the stop flag.
    pub pop_timeout: Duration,
    /// No complete frame for this long means the camera is lost; `None`: `max(2 s, 10 periods)`.
    pub stall_timeout: Option<Duration>,
}

impl Default for AravisOptions {
    fn default() -> Self {
        Self { n_buffers: 8, packet_resend: true, pop_timeout: Duration::from_millis(200), stall_timeout: None }
    }
}

/// Aravis's device list and interface table are global and not thread-safe: every open
/// goes through this lock.
static OPEN_LOCK: Mutex<()> = Mutex::new(());
static FAKE_ENABLED: Once = Once::new();

/// Enables Aravis's in-process "Fake" interface (device id `Fake_1`), once per process.
pub(crate) fn enable_fake_interface() {
    FAKE_ENABLED.call_once(|| {
        let name = CString::new("Fake").unwrap_or_default();
        let _guard = OPEN_LOCK.lock().unwrap_or_else(|p| p.into_inner());
        // SAFETY: `name` is a valid NUL-terminated string alive for the call; the function
        // only looks the name up in Aravis's static interface table, and OPEN_LOCK keeps
        // other threads out of that table meanwhile.
        unsafe { aravis_sys::arv_enable_interface(name.as_ptr()) };
    });
}

/// Every device Aravis's discovery finds now (each enabled interface: GigE Vision, USB3
/// Vision, and the fake one when enabled).
pub(crate) fn list_devices() -> Vec<super::list::AravisDevice> {
    use std::ffi::CStr;
    let _guard = OPEN_LOCK.lock().unwrap_or_else(|p| p.into_inner());
    // SAFETY: Aravis's global device list is rebuilt and read under OPEN_LOCK, which every
    // other user of it in this process takes; the call has no arguments.
    let n = unsafe {
        aravis_sys::arv_update_device_list();
        aravis_sys::arv_get_n_devices()
    };
    let text = |p: *const std::os::raw::c_char| -> String {
        if p.is_null() {
            String::new()
        } else {
            // SAFETY: a non-null pointer from arv_get_device_* is a NUL-terminated string owned
            // by Aravis's device list, valid until the list is next updated (we hold the lock
            // and copy it at once).
            unsafe { CStr::from_ptr(p) }.to_string_lossy().into_owned()
        }
    };
    (0..n)
        .map(|i| {
            // SAFETY: `i` < arv_get_n_devices() for the list just updated under the lock; each
            // getter returns NULL or a string owned by the list (copied by `text`).
            unsafe {
                super::list::AravisDevice {
                    id: text(aravis_sys::arv_get_device_id(i)),
                    vendor: text(aravis_sys::arv_get_device_vendor(i)),
                    model: text(aravis_sys::arv_get_device_model(i)),
                    serial: text(aravis_sys::arv_get_device_serial_nbr(i)),
                    address: text(aravis_sys::arv_get_device_address(i)),
                    protocol: text(aravis_sys::arv_get_device_protocol(i)),
                }
            }
        })
        .collect()
}

/// Whether a device id names Aravis's in-process fake camera.
pub(crate) fn is_fake_id(id: &str) -> bool {
    id.starts_with("Fake") || id.starts_with("Aravis-Fake")
}

/// The converter for a GenICam pixel format, if supported.
pub(crate) fn pixel_layout(format: PixelFormat) -> Option<PixelLayout> {
    if format == PixelFormat::MONO_8 {
        Some(PixelLayout::Gray8)
    } else if format == PixelFormat::MONO_16 {
        Some(PixelLayout::Gray16Le { bits: 16 })
    } else if format == PixelFormat::MONO_12 {
        Some(PixelLayout::Gray16Le { bits: 12 })
    } else if format == PixelFormat::MONO_10 {
        Some(PixelLayout::Gray16Le { bits: 10 })
    } else if format == PixelFormat::BAYER_RG_8 {
        Some(PixelLayout::Bayer8(BayerPattern::Rggb))
    } else if format == PixelFormat::BAYER_GR_8 {
        Some(PixelLayout::Bayer8(BayerPattern::Grbg))
    } else if format == PixelFormat::BAYER_GB_8 {
        Some(PixelLayout::Bayer8(BayerPattern::Gbrg))
    } else if format == PixelFormat::BAYER_BG_8 {
        Some(PixelLayout::Bayer8(BayerPattern::Bggr))
    } else {
        None
    }
}

/// Chooses a frame's time (ns since the epoch): the buffer's system timestamp when
/// plausible, else the mapped device timestamp, else the receive time (module docs).
pub(crate) fn frame_time(system_ns: u64, device_ns: u64, receive_epoch_ns: i64, device_map: &mut DeviceClockMap) -> i64 {
    const PLAUSIBLE_NS: i64 = 10_000_000_000;
    let sys = system_ns as i64;
    if system_ns > 0 && system_ns <= i64::MAX as u64 && (sys - receive_epoch_ns).abs() < PLAUSIBLE_NS {
        return sys;
    }
    if device_ns > 0 && device_ns <= i64::MAX as u64 {
        return device_map.map(device_ns as i64, receive_epoch_ns);
    }
    receive_epoch_ns
}

/// What one popped buffer turned out to be.
#[derive(Debug)]
enum Popped {
    Image(i64),
    Incomplete(BufferStatus),
    Bad(ConvertError),
}

/// An open, acquiring camera with its stream.
struct Session {
    camera: Camera,
    stream: Stream,
    layout: PixelLayout,
    width: u32,
    height: u32,
    device_map: DeviceClockMap,
    underruns: u64,
    pop_timeout: Duration,
}

/// Why an Aravis camera could not be opened as the config asks.
#[derive(Debug, thiserror::Error)]
pub enum AravisOpenError {
    /// A call into Aravis failed.
    #[error("aravis:{id}: {what}: {source}")]
    Call {
        /// The camera.
        id: String,
        /// What was being done.
        what: String,
        /// Aravis' error.
        source: aravis::glib::Error,
    },
    /// The camera has no monochrome or raw Bayer pixel format.
    #[error("aravis:{id}: no monochrome or raw Bayer pixel format (Mono8/10/12/16, BayerRG8/GR8/GB8/BG8) available")]
    NoMono {
        /// The camera.
        id: String,
    },
    /// The config's width or height is outside what the camera can give.
    #[error("aravis:{id}: the config's {what} {want} is outside the camera's range {lo}..={hi}")]
    OutOfRange {
        /// The camera.
        id: String,
        /// `width` or `height`.
        what: &'static str,
        /// The config's, px.
        want: u32,
        /// The camera's least, px.
        lo: i64,
        /// The camera's most, px.
        hi: i64,
    },
    /// The camera gives another size than the config's.
    #[error("aravis:{id}: camera gives {got_width}x{got_height}, the config asks for {width}x{height} (the intrinsics are for that size)")]
    Size {
        /// The camera.
        id: String,
        /// What it gives, px.
        got_width: i32,
        /// What it gives, px.
        got_height: i32,
        /// What the config asks for, px.
        width: u32,
        /// What the config asks for, px.
        height: u32,
    },
}

/// A failed Aravis call, as an [`AravisOpenError`].
fn glib_err(what: &str, id: &str, source: aravis::glib::Error) -> AravisOpenError {
    AravisOpenError::Call { id: id.into(), what: what.into(), source }
}

impl Session {
    fn open(id: &str, cfg: &CameraConfig, opts: &AravisOptions) -> Result<Session, AravisOpenError> {
        if is_fake_id(id) {
            enable_fake_interface();
        }
        let camera = {
            let _guard = OPEN_LOCK.lock().unwrap_or_else(|p| p.into_inner());
            Camera::new(Some(id)).map_err(|e| glib_err("cannot open the camera", id, e))?
        };
        let formats: Vec<i64> = camera.dup_available_pixel_formats().unwrap_or_default();
        // A colour sensor's raw mosaic after the monochrome formats (see `convert::bayer`).
        let mut candidates = [
            PixelFormat::MONO_8,
            PixelFormat::MONO_16,
            PixelFormat::MONO_12,
            PixelFormat::MONO_10,
            PixelFormat::BAYER_RG_8,
            PixelFormat::BAYER_GR_8,
            PixelFormat::BAYER_GB_8,
            PixelFormat::BAYER_BG_8,
        ];
        if cfg.full_depth {
            // The deepest first: the edge fit reads the full depth.
            candidates[..4].rotate_left(1);
        }
        let mut chosen = None;
        for f in candidates {
            if !formats.is_empty() && !formats.contains(&(f.raw() as i64)) {
                continue;
            }
            if camera.set_pixel_format(f).is_ok() {
                chosen = Some(f);
                break;
            }
        }
        let format = match chosen {
            Some(f) => f,
            None => camera.pixel_format().map_err(|e| glib_err("cannot read the pixel format", id, e))?,
        };
        let layout = pixel_layout(format).ok_or_else(|| AravisOpenError::NoMono { id: id.into() })?;
        camera.set_acquisition_mode(AcquisitionMode::Continuous).map_err(|e| glib_err("cannot set continuous acquisition", id, e))?;
        for (what, want, bounds) in [("width", cfg.width, camera.width_bounds()), ("height", cfg.height, camera.height_bounds())] {
            if let Ok((lo, hi)) = bounds {
                if (want as i64) < lo as i64 || want as i64 > hi as i64 {
                    return Err(AravisOpenError::OutOfRange { id: id.into(), what, want, lo: lo as i64, hi: hi as i64 });
                }
            }
        }
        camera
            .set_region(0, 0, cfg.width as i32, cfg.height as i32)
            .map_err(|e| glib_err(&format!("cannot set the region to {}x{}", cfg.width, cfg.height), id, e))?;
        let (_, _, w, h) = camera.region().map_err(|e| glib_err("cannot read the region", id, e))?;
        if w as u32 != cfg.width || h as u32 != cfg.height {
            return Err(AravisOpenError::Size { id: id.into(), got_width: w, got_height: h, width: cfg.width, height: cfg.height });
        }
        if let Some(fps) = cfg.fps.filter(|f| *f > 0.0) {
            if camera.is_frame_rate_available().unwrap_or(false) {
                if let Err(e) = camera.set_frame_rate(fps) {
                    tracing::warn!(id, fps, error = %e, "cannot set the frame rate; using the camera's");
                }
            } else {
                tracing::warn!(id, fps, "camera has no settable frame rate; using its own");
            }
        }
        let payload = camera.payload().map_err(|e| glib_err("cannot read the payload size", id, e))? as usize;
        let stream = camera.create_stream().map_err(|e| glib_err("cannot create a stream", id, e))?;
        if let Some(gv) = stream.downcast_ref::<GvStream>() {
            gv.set_packet_resend(if opts.packet_resend { GvStreamPacketResend::Always } else { GvStreamPacketResend::Never });
        }
        for _ in 0..opts.n_buffers.max(2) {
            stream.push_buffer(Buffer::new_allocate(payload));
        }
        camera.start_acquisition().map_err(|e| glib_err("cannot start acquisition", id, e))?;
        tracing::info!(id, width = w, height = h, ?layout, payload, "aravis camera open");
        Ok(Session {
            camera,
            stream,
            layout,
            width: cfg.width,
            height: cfg.height,
            device_map: DeviceClockMap::new(1_000_000_000),
            underruns: 0,
            pop_timeout: opts.pop_timeout,
        })
    }

    fn check(&mut self, buffer: &Buffer, receive: i64, into: &mut GrayImage) -> Popped {
        let status = buffer.status();
        if status != BufferStatus::Success {
            return Popped::Incomplete(status);
        }
        if buffer.payload_type() != BufferPayloadType::Image {
            return Popped::Incomplete(BufferStatus::PayloadNotSupported);
        }
        let (w, h) = (buffer.image_width(), buffer.image_height());
        if w != self.width as i32 || h != self.height as i32 || pixel_layout(buffer.image_pixel_format()) != Some(self.layout) {
            return Popped::Incomplete(BufferStatus::SizeMismatch);
        }
        let bpp = self.layout.bytes_per_pixel().unwrap_or(1);
        let (pad_x, _) = buffer.image_padding();
        let stride = self.width as usize * bpp + pad_x.max(0) as usize;
        let data = buffer.image_data();
        match to_gray8_into(self.layout, self.width, self.height, stride, &data, into) {
            Ok(()) => Popped::Image(frame_time(buffer.system_timestamp(), buffer.timestamp(), receive, &mut self.device_map)),
            Err(e) => Popped::Bad(e),
        }
    }
}

impl CaptureSession for Session {
    /// Pops one buffer (or times out), checks it, requeues it.
    fn next(&mut self, into: &mut GrayImage) -> Captured {
        let Some(buffer) = self.stream.timeout_pop_buffer(self.pop_timeout.as_micros() as u64) else {
            return Captured::Timeout;
        };
        let receive = now_epoch_ns();
        let out = self.check(&buffer, receive, into);
        self.stream.push_buffer(buffer);
        match out {
            Popped::Image(t) => Captured::Image(t),
            Popped::Incomplete(status) => Captured::Incomplete(format!("buffer status {status:?}")),
            Popped::Bad(e) => Captured::Bad(e.to_string()),
        }
    }

    /// Frames the stream dropped for lack of a free buffer since the last call.
    fn take_missed(&mut self) -> u64 {
        let (_, _, underruns) = self.stream.statistics();
        let new = underruns.saturating_sub(self.underruns);
        self.underruns = underruns;
        new
    }
}

impl Drop for Session {
    fn drop(&mut self) {
        if let Err(e) = self.camera.stop_acquisition() {
            tracing::debug!(error = %e, "aravis stop_acquisition failed (camera gone?)");
        }
        if let Some(gv) = self.stream.downcast_ref::<GvStream>() {
            let (resent, missing) = gv.statistics();
            tracing::info!(resent, missing, "aravis GigE stream packet statistics");
        }
    }
}

/// Opens the camera `id` in a new capture thread and returns once it acquires.
///
/// [`crate::sources::spawn_camera`] calls this with default options; tests call it directly.
pub fn spawn(
    index: usize,
    cfg: &CameraConfig,
    id: &str,
    opts: AravisOptions,
    tx: Sender<SourceEvent>,
    stop: Arc<AtomicBool>,
) -> Result<LiveCamera, SourceError> {
    spawn_with(index, cfg, id, opts, crate::sources::capture::OpenPolicy::Require, tx, stop)
}

/// [`spawn`] with a policy for a camera that is not there yet.
pub(crate) fn spawn_with(
    index: usize,
    cfg: &CameraConfig,
    id: &str,
    opts: AravisOptions,
    policy: crate::sources::capture::OpenPolicy,
    tx: Sender<SourceEvent>,
    stop: Arc<AtomicBool>,
) -> Result<LiveCamera, SourceError> {
    let name = cfg.name.clone();
    let mut timing = LoopTiming::for_fps(cfg.fps);
    if let Some(stall) = opts.stall_timeout {
        timing.stall = stall;
    }
    let source = format!("aravis:{id}");
    let (cfg, id) = (cfg.clone(), id.to_string());
    crate::sources::capture::spawn_capture(index, &name, source, move || Session::open(&id, &cfg, &opts), timing, policy, tx, stop)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn system_timestamp_preferred_then_device_then_receive() {
        let now = 1_763_834_400_000_000_000i64;
        let mut map = DeviceClockMap::new(1_000_000_000);
        assert_eq!(frame_time((now - 3_000_000) as u64, 5, now, &mut map), now - 3_000_000);
        // No system time: device clock anchored on the first receive time.
        assert_eq!(frame_time(0, 1_000, now, &mut map), now);
        assert_eq!(frame_time(0, 40_001_000, now + 41_000_000, &mut map), now + 40_000_000);
        // Neither: receive time.
        assert_eq!(frame_time(0, 0, now + 7, &mut map), now + 7);
        // An implausible system time (a device clock in the system field) is not trusted.
        assert_eq!(frame_time(12_345, 0, now, &mut map), now);
    }

    #[test]
    fn mono_formats_have_converters() {
        assert_eq!(pixel_layout(PixelFormat::MONO_8), Some(PixelLayout::Gray8));
        assert_eq!(pixel_layout(PixelFormat::MONO_12), Some(PixelLayout::Gray16Le { bits: 12 }));
        assert_eq!(pixel_layout(PixelFormat::BAYER_RG_8), Some(PixelLayout::Bayer8(BayerPattern::Rggb)));
        assert_eq!(pixel_layout(PixelFormat::BAYER_BG_8), Some(PixelLayout::Bayer8(BayerPattern::Bggr)));
        assert_eq!(pixel_layout(PixelFormat::RGB_8_PACKED), None);
    }
}
