//! The recording format: writer and reader round trip, PNG and PGM frames, and every kind
//! of broken recording (truncated line, bad line, missing/corrupt/wrong-size frame).

use crate::common;
use std::fs;
use std::path::Path;
use tagdeflect::config::Recording;
use tagdeflect_core::frame::{DeepPlane, GrayImage};
use tagdeflect_io::recording::{read_gray_into, FrameEntry, RecordingError, RecordingWriter, TruthLine, TruthTag};
use tagdeflect_io::utm::UtmSample;
use tagdeflect_sim::SimParams;

fn tiny_config() -> tagdeflect::config::Config {
    let rig = tagdeflect_sim::SimRig::new(&SimParams { cameras: 2, width: 64, height: 48, ..SimParams::default() }).unwrap();
    tagdeflect::config::Config::from_sim(&rig)
}

fn gradient(w: u32, h: u32) -> GrayImage {
    GrayImage { width: w, height: h, data: (0..w * h).map(|i| (i * 7 % 251) as u8).collect(), deep: None }
}

#[test]
fn writer_and_reader_round_trip() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = tiny_config();
    let mut w = RecordingWriter::create(dir.path(), &cfg).unwrap();
    let img = gradient(64, 48);
    // Written out of time order: the reader sorts.
    w.write_frame(&cfg.cameras[1].name, 0, 2_000, &img).unwrap();
    w.write_frame(&cfg.cameras[0].name, 0, 1_000, &img).unwrap();
    w.write_utm(&UtmSample { t_ns: 500, load_kn: 1.5, stroke_mm: Some(0.25) }).unwrap();
    w.write_truth(&TruthLine { t_ns: 1_500, tags: vec![TruthTag { id: 3, center_mm: [1.0, 2.0, 3.0] }] }).unwrap();
    w.finish().unwrap();
    let rec = Recording::open(dir.path()).unwrap();
    assert_eq!(rec.config, cfg);
    assert_eq!(rec.frames.iter().map(|f| f.t_ns).collect::<Vec<_>>(), vec![1_000, 2_000]);
    assert_eq!(rec.utm, vec![UtmSample { t_ns: 500, load_kn: 1.5, stroke_mm: Some(0.25) }]);
    assert_eq!(rec.truth[0].tags[0].center_mm, [1.0, 2.0, 3.0]);
    assert_eq!(rec.load_image(&rec.frames[0]).unwrap(), img);
    // The feed-facing names are SPEC's.
    let utm_text = fs::read_to_string(dir.path().join("utm.jsonl")).unwrap();
    assert!(utm_text.contains("\"load_kN\":1.5") && utm_text.contains("\"stroke_mm\":0.25"), "{utm_text}");
    // A second recording into the same folder is refused, the first left intact.
    assert!(RecordingWriter::create(dir.path(), &cfg).is_err());
    assert_eq!(Recording::open(dir.path()).unwrap().frames.len(), 2);
}

#[test]
fn binary_pgm_frames_are_read() {
    let dir = tempfile::tempdir().unwrap();
    let img = gradient(5, 3);
    let mut bytes = b"P5\n# a comment\n5 3\n255\n".to_vec();
    bytes.extend_from_slice(&img.data);
    let p = dir.path().join("f.pgm");
    fs::write(&p, &bytes).unwrap();
    let mut out = GrayImage::new(0, 0);
    read_gray_into(&p, &mut out, &mut Vec::new()).unwrap();
    assert_eq!(out, img);
    fs::write(&p, &bytes[..bytes.len() - 4]).unwrap();
    let e = read_gray_into(&p, &mut out, &mut Vec::new()).unwrap_err().to_string();
    assert!(e.contains("f.pgm") && e.contains("truncated PGM"), "{e}");
    fs::write(&p, b"P5\n5 3\n70000\n").unwrap();
    let e = read_gray_into(&p, &mut out, &mut Vec::new()).unwrap_err().to_string();
    assert!(e.contains("f.pgm") && e.contains("maxval 70000"), "{e}");
    // A 16-bit PGM (maxval 1023: 10 significant bits, big-endian samples) keeps its depth.
    let deep: Vec<u16> = (0..15u16).map(|i| i * 73).collect();
    let mut bytes = b"P5\n5 3\n1023\n".to_vec();
    bytes.extend(deep.iter().flat_map(|v| v.to_be_bytes()));
    fs::write(&p, &bytes).unwrap();
    read_gray_into(&p, &mut out, &mut Vec::new()).unwrap();
    assert_eq!(out.deep.as_ref().map(|d| (d.bits, d.data.clone())), Some((10, deep.clone())));
    assert_eq!(out.data, deep.iter().map(|&v| DeepPlane::to_8bit(10, v)).collect::<Vec<_>>());
    fs::write(&p, &bytes[..bytes.len() - 1]).unwrap();
    let e = read_gray_into(&p, &mut out, &mut Vec::new()).unwrap_err().to_string();
    assert!(e.contains("truncated PGM: 29 of 30"), "{e}");
}

/// A 10-bit image: a ramp over the full depth, the 8-bit plane rounded from it.
fn deep_gradient(w: u32, h: u32, bits: u8) -> GrayImage {
    let max = (1u32 << bits) - 1;
    let mut img = GrayImage::new(w, h);
    img.deep = Some(DeepPlane { bits, data: (0..w * h).map(|i| (i * 37 % (max + 1)) as u16).collect() });
    img.fill_8bit_from_deep();
    img
}

/// The bits of a PNG's IHDR (depth, colour type) and its sBIT chunk, if any.
fn png_depth_and_sbit(bytes: &[u8]) -> (u8, u8, Option<u8>) {
    let sbit = bytes.windows(4).position(|w| w == b"sBIT").map(|i| bytes[i + 4]);
    (bytes[24], bytes[25], sbit)
}

/// Frames with a full-depth plane are written as 16-bit PNG (sBIT = the significant bits) or
/// 16-bit PGM (maxval 2^bits − 1) and read back at full depth, both planes equal.
#[test]
fn full_depth_frames_are_written_and_read_at_16_bits() {
    use tagdeflect_io::recording::FrameFormat;
    let dir = tempfile::tempdir().unwrap();
    let cfg = tiny_config();
    for (format, bits) in [(FrameFormat::Png, 10u8), (FrameFormat::Png, 16), (FrameFormat::Pgm, 12)] {
        let out = dir.path().join(format!("{format:?}{bits}"));
        let img = deep_gradient(64, 48, bits);
        let mut w = RecordingWriter::create(&out, &cfg).unwrap().with_format(format);
        w.write_frame(&cfg.cameras[0].name, 1, 1_000, &img).unwrap();
        w.finish().unwrap();
        let rec = Recording::open(&out).unwrap();
        let bytes = fs::read(out.join(&rec.frames[0].file)).unwrap();
        match format {
            FrameFormat::Png => assert_eq!(png_depth_and_sbit(&bytes), (16, 0, Some(bits))),
            FrameFormat::Pgm => assert!(bytes.starts_with(format!("P5\n64 48\n{}\n", (1u32 << bits) - 1).as_bytes())),
        }
        let back = rec.load_image(&rec.frames[0]).unwrap();
        assert_eq!(back, img, "{format:?} at {bits} bits");
        // Other tools read the PNG as 16-bit grey with the samples in the high bits.
        if format == FrameFormat::Png {
            let other = image::load_from_memory(&bytes).unwrap().into_luma16();
            let shift = 16 - bits;
            assert!(other.as_raw().iter().zip(&img.deep.as_ref().unwrap().data).all(|(a, b)| *a == *b << shift));
        }
    }
}

/// `simulate --bit-depth 12` stores 16-bit PNGs (sBIT 12) holding the sensor's values; the
/// recording replays at full depth (the edge fit reads the 12-bit levels) to a valid feed,
/// and its 8-bit plane is the 8-bit render's within one grey level (the same light and
/// noise, rounded once or twice).
#[test]
fn twelve_bit_recordings_store_16_bit_pngs_and_replay_at_full_depth() {
    let dir = tempfile::tempdir().unwrap();
    let params = SimParams { cameras: 2, width: 320, height: 240, frame_sets: 3, noise_sigma: 0.5, ..SimParams::default() };
    let rec8 = common::simulate(dir.path(), "rec8", &params);
    let rec12 = common::simulate(dir.path(), "rec12", &SimParams { bit_depth: 12, ..params.clone() });
    let (r8, lines8, _) = common::replay_lines(&rec8, false);
    let (r12, lines12, summary) = common::replay_lines(&rec12, false);
    assert_eq!(summary.bad_frames, 0);
    assert_eq!((lines8.len(), lines12.len()), (3, 3));
    common::feedcheck(&lines12, &rec12.join("tagdeflect.toml"));
    for (a, b) in r8.frames.iter().zip(&r12.frames) {
        let bytes = fs::read(rec12.join(&b.file)).unwrap();
        assert_eq!(png_depth_and_sbit(&bytes), (16, 0, Some(12)), "{}", b.file);
        let (i8, i12) = (r8.load_image(a).unwrap(), r12.load_image(b).unwrap());
        let deep = i12.deep.as_ref().expect("a 12-bit frame keeps its depth");
        assert_eq!(deep.bits, 12);
        assert!(deep.data.iter().all(|&v| v <= 4095));
        assert!(deep.data.iter().any(|&v| v % 16 != 0), "the 12-bit values are not 8-bit ones scaled");
        assert!(i8.deep.is_none());
        let worst = i8.data.iter().zip(&i12.data).map(|(x, y)| (*x as i32 - *y as i32).abs()).max().unwrap();
        assert!(worst <= 1, "8-bit plane differs from the 8-bit render by {worst}");
    }
}

/// A 16-bit frame whose PNG header is malformed (an impossible depth for grey) is refused
/// before decoding, naming the file; with no other frame `check` exits 2.
#[test]
fn a_malformed_16_bit_png_header_is_refused_with_exit_2() {
    let dir = tempfile::tempdir().unwrap();
    let params = SimParams { cameras: 1, width: 320, height: 240, frame_sets: 1, bit_depth: 12, ..SimParams::default() };
    let rec_dir = common::simulate(dir.path(), "rec", &params);
    let rec = Recording::open(&rec_dir).unwrap();
    let f0 = rec.frames[0].clone();
    let path = rec_dir.join(&f0.file);
    let mut bytes = fs::read(&path).unwrap();
    assert_eq!(bytes[24], 16);
    bytes[24] = 12; // not a PNG depth
    fs::write(&path, &bytes).unwrap();
    let e = rec.load_image(&f0).unwrap_err().to_string();
    assert!(e.contains(&f0.file) && e.contains("at 12 bits") && e.contains("8- or 16-bit grayscale"), "{e}");
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_tagdeflect"))
        .args(["check", rec_dir.to_str().unwrap()])
        .env("TAGDEFLECT_LOG", "warn")
        .output()
        .unwrap();
    let (out, err) = (String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
    assert_eq!(o.status.code(), Some(2), "{out}{err}");
    assert!(out.contains(&f0.file) && out.contains("8- or 16-bit grayscale"), "{out}");
    assert!(err.contains("no frame could be read"), "{err}");
    // A 16-bit header that claims a huge image: refused from the header, nothing decoded.
    bytes[24] = 16;
    bytes[16..20].copy_from_slice(&100_000u32.to_be_bytes());
    fs::write(&path, &bytes).unwrap();
    let e = rec.load_image(&f0).unwrap_err().to_string();
    assert!(e.contains(&f0.file) && e.contains("image is 100000x240 but camera is 320x240"), "{e}");
}

fn small_recording(dir: &Path) -> std::path::PathBuf {
    common::simulate(dir, "rec", &SimParams { cameras: 2, width: 320, height: 240, frame_sets: 3, ..SimParams::default() })
}

#[test]
fn truncated_last_line_is_skipped_and_a_bad_line_is_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let rec = small_recording(dir.path());
    let frames = rec.join("frames.jsonl");
    let text = fs::read_to_string(&frames).unwrap();
    let n = text.lines().count();
    // A recorder killed mid-line.
    fs::write(&frames, format!("{text}{{\"camera\": \"left\", \"seq\": 9, \"t_n")).unwrap();
    let r = Recording::open(&rec).unwrap();
    assert_eq!(r.frames.len(), n);
    assert_eq!(r.skipped_lines.len(), 1);
    assert!(r.skipped_lines[0].contains(&format!("frames.jsonl:{}", n + 1)), "{:?}", r.skipped_lines);
    // A malformed line in the middle is an error naming file and line.
    let mut lines: Vec<&str> = text.lines().collect();
    lines[1] = "{\"camera\": \"left\", \"seq\": \"one\"}";
    fs::write(&frames, lines.join("\n") + "\n").unwrap();
    let e = Recording::open(&rec).unwrap_err();
    assert!(matches!(e, RecordingError::BadLine { line: 2, .. }), "{e}");
    assert!(e.to_string().contains("frames.jsonl:2"), "{e}");
}

#[test]
fn unknown_camera_and_escaping_paths_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let rec = small_recording(dir.path());
    let frames = rec.join("frames.jsonl");
    let entry = FrameEntry { camera: "nosuch".into(), seq: 0, t_ns: 1, file: "x.png".into() };
    fs::write(&frames, serde_json::to_string(&entry).unwrap() + "\n").unwrap();
    let e = Recording::open(&rec).unwrap_err().to_string();
    assert!(e.contains("frames.jsonl:1") && e.contains("\"nosuch\""), "{e}");
    let entry = FrameEntry { camera: "left".into(), seq: 0, t_ns: 1, file: "../../etc/passwd".into() };
    fs::write(&frames, serde_json::to_string(&entry).unwrap() + "\n").unwrap();
    let e = Recording::open(&rec).unwrap_err().to_string();
    assert!(e.contains("relative to the recording"), "{e}");
}

#[test]
fn missing_corrupt_and_wrong_size_frames_are_named() {
    let dir = tempfile::tempdir().unwrap();
    let rec_dir = small_recording(dir.path());
    let rec = Recording::open(&rec_dir).unwrap();
    let f0 = rec.frames[0].clone();
    let path = rec_dir.join(&f0.file);
    fs::write(&path, b"\x89PNG\r\n\x1a\nnot really").unwrap();
    let e = rec.load_image(&f0).unwrap_err().to_string();
    assert!(e.contains(&f0.file) && e.contains("corrupt PNG"), "{e}");
    fs::remove_file(&path).unwrap();
    let e = rec.load_image(&f0).unwrap_err().to_string();
    assert!(e.contains(&f0.file), "{e}");
    let small = tagdeflect_io::recording::encode_png(&gradient(10, 10)).unwrap();
    fs::write(&path, small).unwrap();
    let e = rec.load_image(&f0).unwrap_err().to_string();
    assert!(e.contains("image is 10x10 but camera"), "{e}");
    // An RGB PNG is not a grey frame.
    let rgb = image::RgbImage::new(320, 240);
    rgb.save(&path).unwrap();
    let e = rec.load_image(&f0).unwrap_err().to_string();
    assert!(e.contains("8- or 16-bit grayscale"), "{e}");
}

#[test]
fn replay_skips_a_corrupt_frame_and_solves_the_rest() {
    let dir = tempfile::tempdir().unwrap();
    let rec_dir = small_recording(dir.path());
    let rec = Recording::open(&rec_dir).unwrap();
    fs::write(rec_dir.join(&rec.frames[2].file), b"garbage").unwrap();
    let (_, lines, summary) = common::replay_lines(&rec_dir, false);
    assert_eq!(summary.bad_frames, 1);
    assert_eq!(lines.len(), 3, "every frame set still solved");
    common::feedcheck(&lines, &rec_dir.join("tagdeflect.toml"));
}

#[test]
fn empty_recording_and_missing_folder_are_errors() {
    let dir = tempfile::tempdir().unwrap();
    let rec_dir = small_recording(dir.path());
    fs::write(rec_dir.join("frames.jsonl"), "").unwrap();
    let e = Recording::open(&rec_dir).unwrap_err().to_string();
    assert!(e.contains("no frames"), "{e}");
    let e = Recording::open(&dir.path().join("nope")).unwrap_err().to_string();
    assert!(e.contains("nope"), "{e}");
}

/// A PGM recording (what a recorder writes for high frame rates) holds the same pixels
/// as a PNG one and replays to the same feed; the writer names its frames `.pgm`.
#[test]
fn pgm_recordings_replay_like_png_ones() {
    use tagdeflect_io::recording::FrameFormat;
    let dir = tempfile::tempdir().unwrap();
    let params = SimParams { cameras: 2, width: 320, height: 240, frame_sets: 3, ..SimParams::default() };
    let png = common::simulate(dir.path(), "png", &params);
    let pgm = dir.path().join("pgm");
    tagdeflect::commands::simulate::simulate_as(&params, &pgm, FrameFormat::Pgm).unwrap();
    let (rec_png, lines_png, _) = common::replay_lines(&png, false);
    let (rec_pgm, lines_pgm, _) = common::replay_lines(&pgm, false);
    assert!(rec_pgm.frames.iter().all(|f| f.file.ends_with(".pgm")), "{:?}", rec_pgm.frames[0]);
    for (a, b) in rec_png.frames.iter().zip(&rec_pgm.frames) {
        assert_eq!(rec_png.load_image(a).unwrap(), rec_pgm.load_image(b).unwrap(), "{}", b.file);
    }
    assert_eq!(lines_png.len(), 3);
    assert_eq!(lines_png, lines_pgm);

    // The writer: `with_format(Pgm)` and `[output] record_format = "pgm"` in a config.
    let cfg = tiny_config();
    let out = dir.path().join("written");
    let mut w = RecordingWriter::create(&out, &cfg).unwrap().with_format(FrameFormat::Pgm);
    w.write_frame(&cfg.cameras[0].name, 7, 1_000, &gradient(64, 48)).unwrap();
    w.finish().unwrap();
    let rec = Recording::open(&out).unwrap();
    assert_eq!(rec.frames[0].file, format!("{}/000007.pgm", cfg.cameras[0].name));
    assert!(fs::read(out.join(&rec.frames[0].file)).unwrap().starts_with(b"P5\n64 48\n255\n"));
    assert_eq!(rec.load_image(&rec.frames[0]).unwrap(), gradient(64, 48));
    let mut cfg2 = cfg.clone();
    cfg2.output.record_format = FrameFormat::Pgm;
    let text = cfg2.to_toml_string();
    assert!(text.contains("record_format = \"pgm\""), "{text}");
}

/// The recorder keeps the depth: `record` from a live (simulated) 12-bit camera writes 16-bit
/// PNG frames with sBIT 12, which replay at full depth.
#[test]
fn the_recorder_keeps_the_full_depth() {
    let dir = tempfile::tempdir().unwrap();
    let params = SimParams { cameras: 1, width: 320, height: 240, fps: 5.0, bit_depth: 12, noise_sigma: 0.5, ..SimParams::default() };
    let cfg_path = dir.path().join("rig.toml");
    fs::write(&cfg_path, tagdeflect::config::Config::from_sim(&tagdeflect_sim::SimRig::new(&params).unwrap()).to_toml_string()).unwrap();
    let rec_dir = dir.path().join("rec");
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_tagdeflect"))
        .args(["record", "--config", cfg_path.to_str().unwrap(), "--out", rec_dir.to_str().unwrap(), "--duration-s", "1.5"])
        .env("TAGDEFLECT_LOG", "warn")
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let rec = Recording::open(&rec_dir).unwrap();
    assert!(!rec.frames.is_empty());
    for f in &rec.frames {
        assert_eq!(png_depth_and_sbit(&fs::read(rec_dir.join(&f.file)).unwrap()), (16, 0, Some(12)), "{}", f.file);
        let img = rec.load_image(f).unwrap();
        assert_eq!(img.deep.as_ref().map(|d| d.bits), Some(12), "{}", f.file);
    }
}
