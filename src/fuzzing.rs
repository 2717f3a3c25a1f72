//! Entry points of the fuzz targets (`fuzz/`, `scripts/fuzz.sh`), kept in the library so
//! the normal test suite replays every input that once crashed one of them
//! (`tests/fixtures/fuzz-regressions/<target>/`). Each takes arbitrary bytes and must
//! return without a panic, an abort or an allocation beyond the documented limits; the
//! results are checked for the invariants stated at each function.

use std::path::Path;

use crate::config::{Config, RegisterConfig, RegisterKind, ValueType, WordOrder};
use tagdeflect_core::frame::{Frame, GrayImage};
use tagdeflect_io::recording::{decode_gray_bytes, read_jsonl_from, FrameEntry, TruthLine};
use tagdeflect_io::utm::{UtmHistory, UtmSample};

/// The names of the targets, as in `fuzz/fuzz_targets/<name>.rs`.
pub const TARGETS: &[&str] = &[
    "image",
    "jsonl",
    "config",
    "calibration",
    "convert",
    "modbus",
    "modbus_peer",
    "assembly",
    "roi",
    "window_detect",
    "report_feed",
    "archive_message",
];

/// Runs target `name` on `data` (regression tests); `false` for an unknown name.
pub fn run(name: &str, data: &[u8]) -> bool {
    match name {
        "image" => image(data),
        "jsonl" => jsonl(data),
        "config" => config(data),
        "calibration" => calibration(data),
        "convert" => convert(data),
        "modbus" => modbus(data),
        "modbus_peer" => modbus_peer(data),
        "assembly" => assembly(data),
        "roi" => roi(data),
        "window_detect" => window_detect(data),
        "report_feed" => report_feed(data),
        #[cfg(feature = "archive")]
        "archive_message" => tagdeflect_archive::fuzz_message(data),
        _ => return false,
    }
    true
}

fn u32_at(d: &[u8], i: usize) -> u32 {
    let mut b = [0u8; 4];
    for (k, x) in b.iter_mut().enumerate() {
        *x = d.get(i + k).copied().unwrap_or(0);
    }
    u32::from_le_bytes(b)
}

fn i64_at(d: &[u8], i: usize) -> i64 {
    let mut b = [0u8; 8];
    for (k, x) in b.iter_mut().enumerate() {
        *x = d.get(i + k).copied().unwrap_or(0);
    }
    i64::from_le_bytes(b)
}

/// PNG and PGM frames: decoded with and without an expected size; a decoded image always
/// has `width × height` bytes, and with an expected size it has that size.
pub fn image(data: &[u8]) {
    let mut img = GrayImage::new(0, 0);
    if decode_gray_bytes(data, &mut img, None).is_ok() {
        assert_eq!(img.data.len(), img.width as usize * img.height as usize);
    }
    let expect = (u32_at(data, 16).clamp(1, 4096), u32_at(data, 20).clamp(1, 4096));
    let mut img = GrayImage::new(0, 0);
    if decode_gray_bytes(data, &mut img, Some(expect)).is_ok() {
        assert_eq!((img.width, img.height), expect);
        assert_eq!(img.data.len(), img.width as usize * img.height as usize);
    }
}

/// `frames.jsonl`, `utm.jsonl` and `truth.jsonl` lines.
pub fn jsonl(data: &[u8]) {
    let p = Path::new("fuzz.jsonl");
    let mut skipped = Vec::new();
    let _ = read_jsonl_from::<FrameEntry, _>(data, p, &mut skipped);
    let _ = read_jsonl_from::<UtmSample, _>(data, p, &mut skipped);
    let _ = read_jsonl_from::<TruthLine, _>(data, p, &mut skipped);
}

/// A config file; a config that loads also writes back and loads again.
pub fn config(data: &[u8]) {
    let Ok(text) = std::str::from_utf8(data) else { return };
    // Relative calibration paths resolve inside a folder that does not exist.
    let path = Path::new("/nonexistent-fuzz/rig.toml");
    if let Ok(cfg) = Config::from_toml_str(text, path) {
        let back = cfg.to_toml_string();
        Config::from_toml_str(&back, path).expect("a loaded config writes back loadable");
    }
}

/// A calibration file (OpenCV YAML and JSON).
pub fn calibration(data: &[u8]) {
    let Ok(text) = std::str::from_utf8(data) else { return };
    let p = Path::new("fuzz.yaml");
    let _ = crate::config::parse_calibration(text, false, p);
    let _ = crate::config::parse_calibration(text, true, p);
}

/// V4L2 / Aravis buffer conversion (GREY, Y10..Y16, YUYV, MJPEG, raw Bayer) with arbitrary sizes,
/// strides and buffers; a converted image always has `width × height` bytes.
pub fn convert(data: &[u8]) {
    use tagdeflect_io::sources::convert::{to_gray8, PixelLayout};
    if data.len() < 9 {
        return;
    }
    let layout = match data[0] % 5 {
        0 => PixelLayout::Gray8,
        1 => PixelLayout::Gray16Le { bits: 9 + data[1] % 8 },
        2 => PixelLayout::Yuyv,
        3 => PixelLayout::Mjpeg,
        _ => PixelLayout::Bayer8(tagdeflect_io::sources::convert::BayerPattern::Grbg),
    };
    let width = u32::from(u16::from_le_bytes([data[2], data[3]]));
    let height = u32::from(u16::from_le_bytes([data[4], data[5]]));
    let stride = usize::from(u16::from_le_bytes([data[6], data[7]]));
    if let Ok(img) = to_gray8(layout, width, height, stride, &data[8..]) {
        assert_eq!(img.data.len(), img.width as usize * img.height as usize);
    }
}

/// Modbus register decoding: every type, word order, scale and offset.
pub fn modbus(data: &[u8]) {
    if data.len() < 3 {
        return;
    }
    let value_type = [ValueType::F32, ValueType::I16, ValueType::U16, ValueType::I32, ValueType::U32][data[0] as usize % 5];
    let word_order = [WordOrder::Abcd, WordOrder::Cdab, WordOrder::Badc, WordOrder::Dcba][data[1] as usize % 4];
    let scale = f64::from_bits(i64_at(data, 3) as u64);
    let offset = f64::from_bits(i64_at(data, 11) as u64);
    let reg = RegisterConfig { register: 0, kind: RegisterKind::Input, value_type, word_order, scale, offset };
    let words: Vec<u16> =
        data[(data[2] as usize % 4).min(data.len())..].chunks(2).map(|c| u16::from_le_bytes([c[0], *c.get(1).unwrap_or(&0)])).collect();
    if let Ok(v) = tagdeflect_io::utm::decode(&reg, &words) {
        if scale.is_finite() && offset.is_finite() && scale != 0.0 {
            // What the daemon would put in the feed: never NaN from valid integer registers.
            if !matches!(value_type, ValueType::F32) {
                assert!(!v.is_nan(), "integer register decoded to NaN");
            }
        }
    }
    let _ = tagdeflect_io::utm::encode(&reg, scale);
}

/// A raw-byte Modbus TCP peer driving the real poller ([`tagdeflect_io::utm::run_poller`]) over
/// loopback. The input is a script of replies: each chunk is a length byte followed by that
/// many bytes, written (possibly as a partial or oversized frame) in answer to one request
/// read from the poller; when the script ends the peer closes the connection and stops
/// listening. The poller must never panic, must report the broken link as `Down` (never a
/// sample that did not come from a well-formed reply of the right size), and must stop
/// when told to.
pub fn modbus_peer(data: &[u8]) {
    use std::sync::OnceLock;
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    static RT: OnceLock<tokio::runtime::Runtime> = OnceLock::new();
    let rt = RT.get_or_init(|| tokio::runtime::Builder::new_current_thread().enable_all().build().expect("a tokio runtime"));
    let script = data.to_vec();
    rt.block_on(async move {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.expect("bind a loopback port");
        let addr = listener.local_addr().expect("local address");
        let peer = tokio::spawn(async move {
            let Ok((mut sock, _)) = listener.accept().await else { return };
            drop(listener);
            let mut rest: &[u8] = &script;
            let mut request = [0u8; 260];
            while let Some((&n, tail)) = rest.split_first() {
                if sock.read(&mut request).await.unwrap_or(0) == 0 {
                    return;
                }
                let take = (n as usize).min(tail.len());
                if sock.write_all(&tail[..take]).await.is_err() {
                    return;
                }
                rest = &tail[take..];
            }
            // Script done: the connection closes here.
        });
        let reg = |register, value_type| RegisterConfig {
            register,
            kind: RegisterKind::Input,
            value_type,
            word_order: WordOrder::Abcd,
            scale: 1.0,
            offset: 0.0,
        };
        let cfg = crate::config::UtmConfig {
            address: tagdeflect_io::utm::UtmAddress::Tcp(addr.to_string()),
            unit: 1,
            poll_hz: 1000.0,
            timeout_ms: 20.0,
            load: reg(0, ValueType::F32),
            stroke: Some(reg(2, ValueType::I32)),
        };
        let (tx, mut rx) = tokio::sync::mpsc::channel(64);
        let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
        let poller = tokio::spawn(tagdeflect_io::utm::run_poller(cfg, tx, stop_rx));
        // Until the poller says the link is down (the script ends with a closed connection,
        // so that always comes).
        let deadline = tokio::time::Instant::now() + std::time::Duration::from_secs(5);
        loop {
            let ev = tokio::select! {
                ev = rx.recv() => ev,
                _ = tokio::time::sleep_until(deadline) => panic!("the poller did not report the link down within 5 s"),
            };
            match ev {
                Some(tagdeflect_io::utm::UtmEvent::Sample(s)) => assert!(s.t_ns > 0, "sample without a time"),
                Some(tagdeflect_io::utm::UtmEvent::Down { reason }) => {
                    assert!(reason.contains(&addr.to_string()), "a fault that does not name the address: {reason}");
                    break;
                }
                Some(tagdeflect_io::utm::UtmEvent::Up) => {}
                None => panic!("the poller stopped on its own"),
            }
        }
        let _ = stop_tx.send(true);
        let r = tokio::time::timeout(std::time::Duration::from_secs(5), poller).await.expect("the poller stops when told");
        assert!(r.expect("the poller task does not panic").is_ok());
        let _ = tokio::time::timeout(std::time::Duration::from_secs(5), peer).await;
    });
}

/// Frame-set assembly and the UTM history with arbitrary times (overflow checks on):
/// sets come out strictly in time order, each holding at most one frame per camera.
pub fn assembly(data: &[u8]) {
    use tagdeflect_io::sync::{FrameSetAssembler, WaitRule};
    if data.len() < 2 {
        return;
    }
    let cameras = 1 + data[0] as usize % 3;
    let tolerance_ms = [0.001, 1.0, 10.0, 10_000.0][data[1] as usize % 4];
    let mut a = FrameSetAssembler::with_open_sets(cameras, tolerance_ms, 1 + data[1] as usize % 3);
    let img = std::sync::Arc::new(GrayImage::new(1, 1));
    // A live assembler given the same frames at arbitrary arrival times and polls.
    let rule = WaitRule::for_fps([None, Some(1.0), Some(30.0), Some(f64::MAX)][data[0] as usize / 3 % 4]);
    let mut live = FrameSetAssembler::live((0..cameras).map(|c| c.to_string()).collect(), tolerance_ms, rule);
    let mut live_sets = Vec::new();
    let mut sets = Vec::new();
    let mut hist = UtmHistory::with_window(i64_at(data, 2).unsigned_abs() as i64).with_max_gap(i64_at(data, 10).max(0));
    for (k, chunk) in data[2..].chunks(9).enumerate() {
        let t = i64_at(chunk, 0);
        let camera = *chunk.get(8).unwrap_or(&0) as usize % cameras;
        sets.extend(a.push(Frame { camera, seq: k as u64, t_ns: t, image: img.clone() }));
        let arrival_ns = i64_at(chunk, 3);
        live_sets.extend(live.push_at(Frame { camera, seq: k as u64, t_ns: t, image: img.clone() }, arrival_ns));
        live_sets.extend(live.poll_at(arrival_ns.wrapping_add(i64_at(chunk, 5)), rule.base()));
        hist.push(UtmSample { t_ns: t, load_kn: (k as f64).sin(), stroke_mm: (k % 2 == 0).then_some(1.0) });
        let _ = hist.interpolate(t.wrapping_add(k as i64));
        let _ = hist.interpolate(i64_at(chunk, 1));
    }
    sets.extend(a.flush());
    live_sets.extend(live.flush());
    for w in live_sets.windows(2) {
        assert!(w[0].t_ns < w[1].t_ns, "live frame sets out of time order");
    }
    for s in &live_sets {
        let mut cams: Vec<usize> = s.frames.iter().map(|f| f.camera).collect();
        cams.sort_unstable();
        cams.dedup();
        assert_eq!(cams.len(), s.frames.len(), "two frames of one camera in a live set");
    }
    for w in sets.windows(2) {
        assert!(w[0].t_ns < w[1].t_ns, "frame sets out of time order");
    }
    for s in &sets {
        let mut cams: Vec<usize> = s.frames.iter().map(|f| f.camera).collect();
        cams.dedup();
        assert_eq!(cams.len(), s.frames.len(), "two frames of one camera in a set");
    }
}

/// The ROI rectangle helpers: windows around points, bounding boxes, alignment, clamping,
/// merging and sweep tiles always give rectangles inside the image.
pub fn roi(data: &[u8]) {
    use nalgebra::Point2;
    use tagdeflect_detect::plan::{merge_rects, sweep_tiles};
    use tagdeflect_detect::Rect;
    if data.len() < 8 {
        return;
    }
    let width = u32_at(data, 0) % 10_000 + 1;
    let height = u32_at(data, 4) % 10_000 + 1;
    let f = |i: usize| f64::from_bits(i64_at(data, i) as u64);
    let inside = |r: &Rect| {
        r.x as u64 + r.width as u64 <= width as u64 && r.y as u64 + r.height as u64 <= height as u64 && r.width > 0 && r.height > 0
    };
    let mut rects = Vec::new();
    for k in 0..(data.len() / 24).min(64) {
        let o = 8 + 24 * k;
        if let Some(r) = Rect::around(Point2::new(f(o), f(o + 8)), f(o + 16), width, height) {
            assert!(inside(&r), "around: {r:?} outside {width}x{height}");
            rects.push(r);
        }
        let pts = [Point2::new(f(o), f(o + 8)), Point2::new(f(o + 8), f(o + 16))];
        if let Some(r) = Rect::bounding(&pts, f(o + 16).abs().min(1e6), width, height) {
            assert!(inside(&r), "bounding: {r:?} outside {width}x{height}");
            let a = r.aligned(1 + data[o % data.len()] as u32 % 16);
            if let Some(c) = a.clamp_to(width, height) {
                assert!(inside(&c), "clamp_to: {c:?}");
            }
            let _ = r.contains(&pts[0]);
            let _ = r.area();
        }
        let raw = Rect { x: u32_at(data, o), y: u32_at(data, o + 4), width: u32_at(data, o + 8), height: u32_at(data, o + 12) };
        let _ = raw.aligned(u32_at(data, o + 16));
        if let Some(c) = raw.clamp_to(width, height) {
            assert!(inside(&c), "clamp_to: {c:?}");
        }
    }
    for r in merge_rects(rects) {
        assert!(inside(&r), "merge_rects: {r:?}");
    }
    if width <= 4096 && height <= 4096 {
        for r in sweep_tiles(width, height, f(0).abs().min(1.0)) {
            assert!(inside(&r), "sweep tile {r:?}");
        }
    }
}

/// Tag detection (the AprilTag library through our wrapper, with sub-pixel refinement) on a
/// small random image and a random window: no crash, corners finite.
pub fn window_detect(data: &[u8]) {
    use tagdeflect_core::tags::TagFamily;
    use tagdeflect_detect::apriltag::{Detector, DetectorOptions};
    use tagdeflect_detect::refine::RefineOptions;
    use tagdeflect_detect::Rect;
    thread_local! {
        static DET: std::cell::RefCell<Option<Detector>> = const { std::cell::RefCell::new(None) };
    }
    if data.len() < 10 {
        return;
    }
    let width = 8 + u32::from(data[0]) % 120;
    let height = 8 + u32::from(data[1]) % 120;
    let rect = Rect { x: u32::from(data[2]), y: u32::from(data[3]), width: u32::from(data[4]) + 1, height: u32::from(data[5]) + 1 };
    let pixels = &data[6..];
    let mut img = GrayImage::new(width, height);
    for (i, p) in img.data.iter_mut().enumerate() {
        *p = pixels[i % pixels.len()];
    }
    DET.with(|d| {
        let mut d = d.borrow_mut();
        let det = d.get_or_insert_with(|| {
            let opts = DetectorOptions {
                nthreads: 1,
                subpixel: Some(RefineOptions::default()),
                ..DetectorOptions::for_families(&[TagFamily::Tag36h11, TagFamily::Tag25h9])
            };
            Detector::new(opts).expect("detector")
        });
        for det in det.detect_window(&img, rect).iter().chain(det.detect(&img).iter()) {
            assert!(det.corners.iter().all(|c| c.x.is_finite() && c.y.is_finite()), "non-finite corner");
        }
    });
}

/// The report's feed reader and the report built from what it accepts (curves, standards,
/// QC, validity, CSV), for both standards: any bytes give a report or an error, never a
/// panic or a loop; an accepted feed has lines in seq and time order with finite values.
pub fn report_feed(data: &[u8]) {
    use std::sync::OnceLock;
    use tagdeflect_report::{Feed, ReadOptions, ReportConfig, Standard, TestRig};
    static RIG: OnceLock<TestRig> = OnceLock::new();
    let rig = RIG.get_or_init(|| {
        // The shipped beam with a notch, so that every standard's report can be made.
        let text = include_str!("../config/one-camera.toml").replacen("span_mm = 450.0\n", "span_mm = 450.0\nnotch_mm = 25.0\n", 1);
        Config::from_toml_str(&text, Path::new("config/one-camera.toml")).expect("the one-camera config loads").test_rig()
    });
    let Ok(text) = std::str::from_utf8(data) else { return };
    let path = Path::new("fuzz.jsonl");
    for allow_restarts in [false, true] {
        let Ok(runs) = Feed::parse(text, path, &ReadOptions { allow_restarts, ..Default::default() }) else { continue };
        for feed in &runs {
            // seq increases but where a resumed lab test's line restarts it (a `resume` event).
            let c = &feed.columns;
            assert!((1..c.len()).all(|k| (c.seq[k - 1] < c.seq[k] || c.resumes.contains(&k)) && c.t_ns[k - 1] < c.t_ns[k]));
            let mut csv = Vec::new();
            let _ = tagdeflect_report::csv_out::write_curve_csv(feed, &mut csv);
            for standard in [Standard::AstmC1609, Standard::En14651] {
                let opts = ReportConfig::new(standard, "out".into());
                if let Ok(r) = tagdeflect_report::build(feed, None, rig, path, &opts) {
                    for e in &r.entries {
                        if let Ok(q) = &e.result {
                            assert!(q.value.is_finite(), "{}: {}", e.key, q.value);
                        }
                    }
                }
            }
        }
    }
}
