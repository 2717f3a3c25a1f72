//! The recording format: writer and reader round trip, PNG and PGM frames, and every kind
//! of broken recording (truncated line, bad line, missing/corrupt/wrong-size frame).

use crate::common;
use std::fs;
use std::path::Path;
use tagdeflect::config::Recording;
use tagdeflect_core::frame::GrayImage;
use tagdeflect_io::recording::{read_gray_into, FrameEntry, RecordingError, RecordingWriter, TruthLine, TruthTag};
use tagdeflect_io::utm::UtmSample;
use tagdeflect_sim::SimParams;

fn tiny_config() -> tagdeflect::config::Config {
    let rig = tagdeflect_sim::SimRig::new(&SimParams { cameras: 2, width: 64, height: 48, ..SimParams::default() }).unwrap();
    tagdeflect::config::Config::from_sim(&rig)
}

fn gradient(w: u32, h: u32) -> GrayImage {
    GrayImage { width: w, height: h, data: (0..w * h).map(|i| (i * 7 % 251) as u8).collect() }
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
    fs::write(&p, b"P5\n5 3\n65535\n").unwrap();
    let e = read_gray_into(&p, &mut out, &mut Vec::new()).unwrap_err().to_string();
    assert!(e.contains("8-bit"), "{e}");
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
    assert!(e.contains("8-bit grayscale"), "{e}");
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
