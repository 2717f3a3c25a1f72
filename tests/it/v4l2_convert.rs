//! V4L2 buffer handling on captured-buffer fixtures: format conversion (GREY, Y16, YUYV,
//! MJPEG), `bytesused` (bytes beyond it are stale and must be ignored), row padding,
//! corrupted and truncated buffers (an error, never a panic or a half image), and the
//! mapping of driver timestamps from CLOCK_MONOTONIC to the Unix epoch.
//!
//! Real V4L2 devices cannot be created on the test machine; what only real hardware can
//! check is listed in the docs of `tagdeflect_io::sources::v4l2`.

use tagdeflect_core::clock::MonotonicToEpoch;
use tagdeflect_io::sources::convert::{ConvertError, PixelLayout};
use tagdeflect_io::sources::v4l2::{convert_buffer, fourcc_layout, map_buffer_timestamp, BufferOutcome, TimeSource, BUF_FLAG_ERROR};

const W: u32 = 37;
const H: u32 = 23;
/// Stale bytes the driver left in the mapping beyond `bytesused`.
const STALE: u8 = 0xEE;

/// The test picture: a value per pixel that depends on both coordinates.
fn pixel(x: u32, y: u32) -> u8 {
    ((x * 7 + y * 11) % 256) as u8
}

fn expected() -> Vec<u8> {
    (0..H).flat_map(|y| (0..W).map(move |x| pixel(x, y))).collect()
}

/// A mapped buffer of `stride`-byte rows built by `row`, padded with stale bytes inside each
/// row and after the last row; returns (mapping, bytesused).
fn mapped_buffer(stride: usize, row_bytes: usize, row: impl Fn(u32) -> Vec<u8>) -> (Vec<u8>, u32) {
    let mut buf = Vec::new();
    for y in 0..H {
        let mut r = row(y);
        assert_eq!(r.len(), row_bytes);
        r.resize(stride, STALE);
        buf.extend_from_slice(&r);
    }
    let used = buf.len() as u32;
    buf.resize(buf.len() + 4096, STALE);
    (buf, used)
}

fn image(out: BufferOutcome) -> Vec<u8> {
    match out {
        BufferOutcome::Image(img) => {
            assert_eq!((img.width, img.height), (W, H));
            img.data
        }
        other => panic!("expected an image, got {other:?}"),
    }
}

#[test]
fn grey_with_row_padding_and_stale_tail() {
    let stride = W as usize + 11;
    let (buf, used) = mapped_buffer(stride, W as usize, |y| (0..W).map(|x| pixel(x, y)).collect());
    let layout = fourcc_layout(*b"GREY").unwrap();
    assert_eq!(image(convert_buffer(layout, W, H, stride as u32, &buf, used, 0)), expected());
}

#[test]
fn y16_keeps_the_high_byte() {
    let stride = 2 * W as usize + 6;
    let (buf, used) =
        mapped_buffer(stride, 2 * W as usize, |y| (0..W).flat_map(|x| ((pixel(x, y) as u16) << 8 | 0x5A).to_le_bytes()).collect());
    let layout = fourcc_layout(*b"Y16 ").unwrap();
    assert_eq!(image(convert_buffer(layout, W, H, stride as u32, &buf, used, 0)), expected());
}

#[test]
fn y10_and_y12_scale_to_eight_bits() {
    for (fourcc, bits) in [(*b"Y10 ", 10u32), (*b"Y12 ", 12)] {
        let (buf, used) = mapped_buffer(2 * W as usize, 2 * W as usize, |y| {
            (0..W).flat_map(|x| (((pixel(x, y) as u16) << (bits - 8)) | 1).to_le_bytes()).collect()
        });
        let layout = fourcc_layout(fourcc).unwrap();
        assert_eq!(image(convert_buffer(layout, W, H, 0, &buf, used, 0)), expected(), "{bits}-bit");
    }
}

#[test]
fn yuyv_keeps_luma() {
    // W is odd: YUYV needs even widths, so use W-1 columns here.
    let w = W - 1;
    let stride = 2 * w as usize + 8;
    let (buf, used) =
        mapped_buffer(stride, 2 * w as usize, |y| (0..w).flat_map(|x| [pixel(x, y), if x % 2 == 0 { 0x30 } else { 0xC0 }]).collect());
    let layout = fourcc_layout(*b"YUYV").unwrap();
    match convert_buffer(layout, w, H, stride as u32, &buf, used, 0) {
        BufferOutcome::Image(img) => {
            let want: Vec<u8> = (0..H).flat_map(|y| (0..w).map(move |x| pixel(x, y))).collect();
            assert_eq!(img.data, want);
        }
        other => panic!("expected an image, got {other:?}"),
    }
}

fn smooth_picture(w: u32, h: u32) -> image::GrayImage {
    image::GrayImage::from_fn(w, h, |x, y| {
        let v = 128.0 + 100.0 * ((x as f64 / 9.0).sin() * (y as f64 / 13.0).cos());
        image::Luma([v.round() as u8])
    })
}

fn jpeg_of(img: image::DynamicImage) -> Vec<u8> {
    let mut out = Vec::new();
    let enc = image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, 95);
    img.write_with_encoder(enc).expect("JPEG encoding");
    out
}

fn mean_abs_diff(a: &[u8], b: &[u8]) -> f64 {
    a.iter().zip(b).map(|(x, y)| (*x as f64 - *y as f64).abs()).sum::<f64>() / a.len() as f64
}

#[test]
fn mjpeg_grey_and_colour_decode_to_luma() {
    let (w, h) = (64, 48);
    let truth = smooth_picture(w, h);
    let layout = fourcc_layout(*b"MJPG").unwrap();
    for (what, jpeg) in [
        ("grey JPEG", jpeg_of(image::DynamicImage::ImageLuma8(truth.clone()))),
        ("colour JPEG", jpeg_of(image::DynamicImage::ImageRgb8(image::DynamicImage::ImageLuma8(truth.clone()).to_rgb8()))),
    ] {
        let used = jpeg.len() as u32;
        let mut mapped = jpeg.clone();
        mapped.resize(jpeg.len() + 10_000, STALE);
        match convert_buffer(layout, w, h, 0, &mapped, used, 0) {
            BufferOutcome::Image(img) => {
                let err = mean_abs_diff(&img.data, truth.as_raw());
                println!("{what}: {} bytes, mean |decoded − truth| = {err:.2} grey levels", jpeg.len());
                assert!(err < 2.0, "{what}: decoded image differs by {err} grey levels on average");
            }
            other => panic!("{what}: expected an image, got {other:?}"),
        }
        // UVC cameras pad MJPEG payloads with zeros after the end-of-image marker.
        let mut padded = jpeg.clone();
        padded.resize(jpeg.len() + 100, 0);
        assert!(
            matches!(convert_buffer(layout, w, h, 0, &padded, padded.len() as u32, 0), BufferOutcome::Image(_)),
            "{what}: zero padding"
        );
    }
}

#[test]
fn mjpeg_of_the_wrong_size_is_rejected() {
    let jpeg = jpeg_of(image::DynamicImage::ImageLuma8(smooth_picture(32, 32)));
    let out = convert_buffer(PixelLayout::Mjpeg, 64, 48, 0, &jpeg, jpeg.len() as u32, 0);
    assert!(matches!(out, BufferOutcome::Bad(ConvertError::JpegSize { got_w: 32, got_h: 32, .. })), "{out:?}");
}

#[test]
fn truncated_buffers_are_errors_not_panics() {
    let layout = fourcc_layout(*b"GREY").unwrap();
    let (buf, used) = mapped_buffer(W as usize, W as usize, |y| (0..W).map(|x| pixel(x, y)).collect());
    // bytesused one byte short: the stale bytes behind it must not complete the image.
    match convert_buffer(layout, W, H, 0, &buf, used - 1, 0) {
        BufferOutcome::Bad(ConvertError::Truncated { needed, got, .. }) => assert_eq!((needed, got), (used as usize, used as usize - 1)),
        other => panic!("expected Truncated, got {other:?}"),
    }
    // bytesused larger than the mapping (a confused driver): clamped, still an error.
    let short = &buf[..100];
    assert!(matches!(convert_buffer(layout, W, H, 0, short, used, 0), BufferOutcome::Bad(ConvertError::Truncated { .. })));
    // Empty buffer.
    assert!(matches!(convert_buffer(layout, W, H, 0, &buf, 0, 0), BufferOutcome::Bad(ConvertError::Truncated { .. })));
    // Y16 and YUYV cut in the middle of the last row.
    for fourcc in [*b"Y16 ", *b"YUYV"] {
        let l = fourcc_layout(fourcc).unwrap();
        let data = vec![0u8; 2 * W as usize * H as usize - 3];
        assert!(matches!(convert_buffer(l, W, H, 0, &data, data.len() as u32, 0), BufferOutcome::Bad(ConvertError::Truncated { .. })));
    }
    // A JPEG cut short (the USB transfer lost its tail): no end-of-image marker → rejected.
    let jpeg = jpeg_of(image::DynamicImage::ImageLuma8(smooth_picture(64, 48)));
    for cut in [jpeg.len() / 2, jpeg.len() - 2, 10, 0] {
        let out = convert_buffer(PixelLayout::Mjpeg, 64, 48, 0, &jpeg, cut as u32, 0);
        assert!(matches!(out, BufferOutcome::Bad(ConvertError::Jpeg(_))), "JPEG cut at {cut} of {}: {out:?}", jpeg.len());
    }
    // Garbage.
    let out = convert_buffer(PixelLayout::Mjpeg, 64, 48, 0, &[0xFF, 0xD8, 1, 2, 3, 0xFF, 0xD9], 7, 0);
    assert!(matches!(out, BufferOutcome::Bad(ConvertError::Jpeg(_))), "{out:?}");
}

#[test]
fn buffers_flagged_as_corrupted_are_not_delivered() {
    let (buf, used) = mapped_buffer(W as usize, W as usize, |y| (0..W).map(|x| pixel(x, y)).collect());
    let out = convert_buffer(PixelLayout::Gray8, W, H, 0, &buf, used, BUF_FLAG_ERROR | 0x2000);
    assert!(matches!(out, BufferOutcome::Corrupted), "{out:?}");
}

#[test]
fn driver_timestamps_map_from_monotonic_to_epoch() {
    const MONO: u32 = 0x2000;
    const COPY: u32 = 0x4000;
    const SOE: u32 = 0x1_0000;
    let offset = 1_763_834_000_000_000_000i64; // epoch − monotonic
    let clock = MonotonicToEpoch::from_offset(offset);
    let (sec, usec) = (400i64, 123_456i64);
    let driver = offset + sec * 1_000_000_000 + usec * 1_000;
    let receive = driver + 4_000_000; // dequeued 4 ms after the stamp
    assert_eq!(map_buffer_timestamp(MONO, sec, usec, clock, receive), (driver, TimeSource::Driver));
    assert_eq!(map_buffer_timestamp(MONO | SOE | 0x1, sec, usec, clock, receive), (driver, TimeSource::Driver));
    // Not a monotonic stamp: the receive time.
    assert_eq!(map_buffer_timestamp(0, sec, usec, clock, receive), (receive, TimeSource::Receive));
    assert_eq!(map_buffer_timestamp(COPY, sec, usec, clock, receive), (receive, TimeSource::Receive));
    // Monotonic but zero, in the future, or far in the past: the receive time.
    assert_eq!(map_buffer_timestamp(MONO, 0, 0, clock, receive), (receive, TimeSource::Receive));
    assert_eq!(map_buffer_timestamp(MONO, sec, usec, clock, driver - 50_000_000), (driver - 50_000_000, TimeSource::Receive));
    assert_eq!(map_buffer_timestamp(MONO, sec, usec, clock, driver + 5_000_000_000), (driver + 5_000_000_000, TimeSource::Receive));
}

#[test]
fn measured_clock_offset_maps_the_current_monotonic_time_to_now() {
    let clock = MonotonicToEpoch::current();
    let mono = tagdeflect_core::clock::monotonic_ns();
    let now = tagdeflect_core::clock::now_epoch_ns();
    let (t, src) = map_buffer_timestamp(0x2000, mono / 1_000_000_000, (mono % 1_000_000_000) / 1_000, clock, now);
    println!("live monotonic→epoch mapping: {} µs from the realtime clock", (t - now) / 1_000);
    assert_eq!(src, TimeSource::Driver);
    assert!((t - now).abs() < 5_000_000, "mapped {t}, now {now}");
}

#[test]
fn full_hd_conversions_are_correct_and_timed() {
    // The capture thread converts every frame: print what that costs at 1920x1080.
    let (w, h) = (1920u32, 1080u32);
    let truth = smooth_picture(w, h);
    let yuyv: Vec<u8> = truth.as_raw().iter().enumerate().flat_map(|(i, y)| [*y, if i % 2 == 0 { 0x70 } else { 0x90 }]).collect();
    // Best of a few runs (the machine is shared).
    let timed = |f: &dyn Fn() -> BufferOutcome| {
        let mut best = f64::INFINITY;
        let mut out = None;
        for _ in 0..5 {
            let t = std::time::Instant::now();
            let o = f();
            best = best.min(t.elapsed().as_secs_f64() * 1e3);
            out = Some(o);
        }
        (out.expect("ran"), best)
    };
    let (out, yuyv_ms) = timed(&|| convert_buffer(PixelLayout::Yuyv, w, h, 0, &yuyv, yuyv.len() as u32, 0));
    match out {
        BufferOutcome::Image(img) => assert_eq!(&img.data, truth.as_raw()),
        other => panic!("{other:?}"),
    }
    let jpeg = jpeg_of(image::DynamicImage::ImageLuma8(truth.clone()));
    let (out, mjpeg_ms) = timed(&|| convert_buffer(PixelLayout::Mjpeg, w, h, 0, &jpeg, jpeg.len() as u32, 0));
    match out {
        BufferOutcome::Image(img) => {
            let err = mean_abs_diff(&img.data, truth.as_raw());
            assert!(err < 2.0, "1080p MJPEG decoded {err} grey levels off");
        }
        other => panic!("{other:?}"),
    }
    println!("1920x1080 conversion: YUYV {yuyv_ms:.2} ms, MJPEG ({} kB) {mjpeg_ms:.2} ms", jpeg.len() / 1024);
}
