//! Detection on real test data (../shared/realdata, see its MANIFEST.md).
//!
//! The data folder must exist: a missing folder fails these tests loudly.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::time::Instant;

use tagdeflect_core::frame::GrayImage;
use tagdeflect_core::tags::TagFamily;
use tagdeflect_detect::apriltag::LIBRARY_TO_OPENCV;
use tagdeflect_detect::{Detector, DetectorOptions, Rect};

fn data_dir() -> PathBuf {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/realdata");
    assert!(
        dir.join("MANIFEST.md").is_file(),
        "real test data not found at {}: these tests need ../shared/realdata (see its MANIFEST.md)",
        dir.display()
    );
    dir
}

/// Decodes an image to grey with BT.601 luma (what a JPEG stores as Y, and what the AprilTag
/// library's own JPEG decoder hands to the detector).
fn load_gray(path: &Path) -> GrayImage {
    let img = image::open(path).unwrap_or_else(|e| panic!("cannot decode {}: {e}", path.display())).to_rgb8();
    let data = img
        .pixels()
        .map(|p| (0.299 * p.0[0] as f64 + 0.587 * p.0[1] as f64 + 0.114 * p.0[2] as f64).round().clamp(0.0, 255.0) as u8)
        .collect();
    GrayImage { width: img.width(), height: img.height(), data, deep: None }
}

/// A tag image from apriltag-imgs (1 px = 1 bit, RGBA), scaled by `scale` (nearest neighbour)
/// and padded with `pad` white pixels; returns the image and the bit grid size.
fn render_tag_png(path: &Path, scale: u32, pad: u32) -> (GrayImage, u32) {
    let tag = image::open(path).unwrap_or_else(|e| panic!("cannot decode {}: {e}", path.display())).to_luma8();
    let n = tag.width();
    let size = n * scale + 2 * pad;
    let mut img = GrayImage { width: size, height: size, data: vec![255; (size * size) as usize], deep: None };
    for y in 0..n * scale {
        for x in 0..n * scale {
            let v = tag.get_pixel(x / scale, y / scale).0[0];
            img.data[((y + pad) * size + x + pad) as usize] = if v < 128 { 0 } else { 255 };
        }
    }
    (img, n)
}

/// Expected detections of an apriltag-test `.txt`: (id, det->p corners, library convention).
fn parse_expected(path: &Path) -> Vec<(u32, [[f64; 2]; 4])> {
    let text = std::fs::read_to_string(path).unwrap_or_else(|e| panic!("cannot read {}: {e}", path.display()));
    let mut out = Vec::new();
    for (lineno, line) in text.lines().enumerate() {
        if line.trim().is_empty() {
            continue;
        }
        let cleaned: String = line.chars().map(|c| if c == '(' || c == ')' || c == ',' { ' ' } else { c }).collect();
        let nums: Vec<f64> = cleaned
            .split_whitespace()
            .map(|s| s.parse().unwrap_or_else(|_| panic!("{}:{}: not a number: {s}", path.display(), lineno + 1)))
            .collect();
        assert_eq!(nums.len(), 9, "{}:{}: expected id and 4 corners", path.display(), lineno + 1);
        let p = [[nums[1], nums[2]], [nums[3], nums[4]], [nums[5], nums[6]], [nums[7], nums[8]]];
        out.push((nums[0] as u32, p));
    }
    out
}

#[test]
fn apriltag_test_images_match_expected_corners() {
    let dir = data_dir().join("apriltag-test");
    // The reference settings (MANIFEST): quad_decimate 1, refine_edges 0, defaults otherwise.
    let opts = DetectorOptions { refine_edges: false, subpixel: None, ..DetectorOptions::for_families(&[TagFamily::Tag36h11]) };
    let mut det = Detector::new(opts).unwrap();
    let (mut total, mut within_01, mut within_03, mut found) = (0, 0, 0, 0);
    let mut worst_matched: f64 = 0.0;
    let mut names: Vec<_> = std::fs::read_dir(&dir)
        .unwrap()
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "jpg"))
        .collect();
    names.sort();
    assert_eq!(names.len(), 3, "expected 3 photos in {}", dir.display());
    for jpg in &names {
        let img = load_gray(jpg);
        let expected = parse_expected(&jpg.with_extension("txt"));
        let raws = det.detect_raw(&img, None);
        // Conversion: product corners are exactly raw − 0.5, in the same (SPEC = det->p) order.
        for r in &raws {
            let d = r.to_detection();
            for i in 0..4 {
                assert_eq!(d.corners[i].x, r.p[i][0] + LIBRARY_TO_OPENCV);
                assert_eq!(d.corners[i].y, r.p[i][1] + LIBRARY_TO_OPENCV);
                assert_eq!(LIBRARY_TO_OPENCV, -0.5);
            }
        }
        let mut file_ok = 0;
        for (id, p) in &expected {
            total += 1;
            // Best raw detection of this id: smallest worst-corner distance (same order).
            let best = raws
                .iter()
                .filter(|r| r.id == *id)
                .map(|r| (0..4).map(|i| ((r.p[i][0] - p[i][0]).powi(2) + (r.p[i][1] - p[i][1]).powi(2)).sqrt()).fold(0.0, f64::max))
                .fold(f64::INFINITY, f64::min);
            if best < 2.0 {
                found += 1;
                worst_matched = worst_matched.max(best);
            }
            if best <= 0.1 {
                within_01 += 1;
            }
            if best <= 0.3 {
                within_03 += 1;
                file_ok += 1;
            }
        }
        println!(
            "{}: {} expected, {} detected, {} within 0.3 px (library convention)",
            jpg.file_name().unwrap().to_string_lossy(),
            expected.len(),
            raws.len(),
            file_ok
        );
    }
    println!(
        "apriltag-test: {total} expected tags, {found} found, {within_01} within 0.1 px, {within_03} within 0.3 px, worst matched {worst_matched:.3} px"
    );
    // MANIFEST: with a different JPEG decoder, ~43/47 within 0.1 px, the rest within ~0.3.
    // Measured here (image crate, BT.601 luma): 47 found, 43 within 0.1 px, 46 within 0.3 px.
    assert_eq!(total, 47);
    assert!(found >= 46, "only {found}/47 expected tags found");
    assert!(within_03 >= 45, "only {within_03}/47 expected tags within 0.3 px");
    assert!(within_01 >= 40, "only {within_01}/47 expected tags within 0.1 px");
}

#[test]
fn upright_tag_gives_spec_corner_order_and_opencv_pixels() {
    let dir = data_dir().join("apriltag-imgs");
    for (family, file, bits) in
        [(TagFamily::Tag36h11, "tag36h11/tag36_11_00007.png", 10u32), (TagFamily::Tag25h9, "tag25h9/tag25_09_00003.png", 9)]
    {
        let (scale, pad) = (20u32, 40u32);
        let (img, n) = render_tag_png(&dir.join(file), scale, pad);
        assert_eq!(n, bits);
        // The black square spans bits 1..n-1; pixel index k covers [k − 0.5, k + 0.5] in OpenCV.
        let lo = (pad + scale) as f64 - 0.5;
        let hi = (pad + (n - 1) * scale) as f64 - 0.5;
        let truth = [[lo, hi], [hi, hi], [hi, lo], [lo, lo]]; // BL, BR, TR, TL (y down)
        for subpixel in [false, true] {
            let mut opts = DetectorOptions::for_families(&[family]);
            if !subpixel {
                opts.subpixel = None;
            }
            let mut det = Detector::new(opts).unwrap();
            let dets = det.detect(&img);
            assert_eq!(dets.len(), 1, "{file}: {dets:?}");
            let d = &dets[0];
            let mut worst: f64 = 0.0;
            for (c, t) in d.corners.iter().zip(&truth) {
                worst = worst.max(((c.x - t[0]).powi(2) + (c.y - t[1]).powi(2)).sqrt());
            }
            println!("{file}: subpixel={subpixel} worst corner error {worst:.4} px vs the exact square");
            assert!(worst < 0.15, "{file}: corners {:?} vs truth {truth:?}", d.corners);
        }
    }
}

#[test]
fn tag_images_decode_to_their_ids() {
    let dir = data_dir().join("apriltag-imgs");
    let mut det = Detector::new(DetectorOptions::for_families(&[TagFamily::Tag36h11, TagFamily::Tag25h9])).unwrap();
    let mut checked = 0;
    for (family, sub, prefix, count, step) in
        [(TagFamily::Tag25h9, "tag25h9", "tag25_09_", 35u32, 1usize), (TagFamily::Tag36h11, "tag36h11", "tag36_11_", 587, 25)]
    {
        for id in (0..count).step_by(step) {
            let path = dir.join(sub).join(format!("{prefix}{id:05}.png"));
            let (img, _) = render_tag_png(&path, 12, 30);
            let dets = det.detect(&img);
            assert_eq!(dets.len(), 1, "{}: {dets:?}", path.display());
            assert_eq!((dets[0].family, dets[0].id), (family, id), "{}", path.display());
            assert_eq!(dets[0].hamming, 0, "{}", path.display());
            checked += 1;
        }
    }
    println!("apriltag-imgs: {checked} tag images decoded to their ids");
    assert_eq!(checked, 35 + 24);
}

#[test]
fn frontal_photo_gives_its_80_ids() {
    let path = data_dir().join("amarburg-apriltags-test/test_36h11.jpg");
    let t0 = Instant::now();
    let img = load_gray(&path);
    let t_decode = t0.elapsed();
    let mut det = Detector::new(DetectorOptions { nthreads: 2, ..DetectorOptions::for_families(&[TagFamily::Tag36h11]) }).unwrap();
    let t1 = Instant::now();
    let dets = det.detect(&img);
    let t_detect = t1.elapsed();
    let ids: BTreeSet<u32> = dets.iter().map(|d| d.id).collect();
    let expected: BTreeSet<u32> = (0..8).flat_map(|r| (14 + 24 * r)..=(23 + 24 * r)).collect();
    let stats = det.refine_stats();
    println!(
        "test_36h11.jpg {}x{}: {} detections, {} distinct ids; decode {:?}, detect+refine {:?}; refined {} corners, kept {}",
        img.width,
        img.height,
        dets.len(),
        ids.len(),
        t_decode,
        t_detect,
        stats.corners_refined,
        stats.corners_kept
    );
    assert_eq!(dets.len(), 80);
    assert_eq!(ids, expected);
}

#[test]
fn window_detection_matches_full_frame_on_a_photo() {
    let path = data_dir().join("amarburg-apriltags-test/test_36h11_greyscale.jpg");
    let img = load_gray(&path);
    let mut det = Detector::new(DetectorOptions { nthreads: 2, ..DetectorOptions::for_families(&[TagFamily::Tag36h11]) }).unwrap();
    let full = det.detect(&img);
    assert!(full.len() >= 70, "only {} tags in the full frame", full.len());
    let mut compared = 0;
    let mut worst: f64 = 0.0;
    for d in full.iter().step_by(7) {
        let rect = Rect::bounding(&d.corners, 40.0, img.width, img.height).unwrap();
        let win = det.detect_window(&img, rect);
        let w = win.iter().find(|w| w.id == d.id).unwrap_or_else(|| panic!("tag {} not found in its window {rect:?}", d.id));
        for i in 0..4 {
            worst = worst.max((w.corners[i] - d.corners[i]).norm());
        }
        compared += 1;
    }
    println!("window vs full frame on a photo: {compared} tags, worst corner difference {worst:.2e} px");
    assert!(compared >= 10);
    // The refinement stops once a step moves an edge by less than 1e-4 px, so its start
    // (the library's quad, which depends on the window origin at the 1e-4 px level) still
    // shows at the 1e-5 px level: a thousandth of the corner noise.
    assert!(worst < 1e-4, "window corners differ from full-frame ones by {worst} px");
}

/// Two real photos of the same sheet, frontal then oblique (amarburg), as two frames of one
/// camera that moved between them: the tracking detector's windows, placed where the tags
/// were, lose the background tags; that is reported ([`DetectReport::background`]), the
/// moved frame searched whole finds what a full-frame search of it finds, and the next frame
/// follows those tags from where they are now, without any whole-frame search. (There is no
/// metric truth for these photos — no intrinsics, no tag size — so only the detection half
/// of a moved camera is checked here; the pose half is in `tracking` on renders.)
#[test]
fn a_camera_moved_between_real_photos_is_searched_whole_and_followed_from_there() {
    use std::sync::Arc;
    use tagdeflect_core::camera::{CameraIntrinsics, Lens};
    use tagdeflect_detect::{CameraDetector, ConfirmOptions, RefineOptions, RigDetectors, SearchOptions, TagConfirmer, TagRoles};
    let dir = data_dir().join("amarburg-apriltags-test");
    let frontal = load_gray(&dir.join("test_36h11_greyscale.jpg"));
    let oblique = load_gray(&dir.join("test_36h11_oblique_greyscale.jpg"));
    assert_eq!((frontal.width, frontal.height), (oblique.width, oblique.height));
    let (w, h) = (frontal.width, frontal.height);
    // No calibration is published: a distortion-free pinhole (corners are compared in pixels).
    let intr = CameraIntrinsics {
        width: w,
        height: h,
        fx: w as f64,
        fy: w as f64,
        cx: 0.5 * (w as f64 - 1.0),
        cy: 0.5 * (h as f64 - 1.0),
        dist: [0.0; 5],
    };
    // The sheet's top and bottom rows as background tags, the rest as specimen tags.
    let background: std::collections::HashSet<u32> = (14..=23).chain((14 + 24 * 7)..=(23 + 24 * 7)).collect();
    let specimen = (0..8).flat_map(|r| (14 + 24 * r)..=(23 + 24 * r)).filter(|id| !background.contains(id)).collect();
    let roles = TagRoles { background_family: TagFamily::Tag36h11, background, specimen_family: TagFamily::Tag36h11, specimen };
    let opts =
        DetectorOptions { nthreads: 1, subpixel: Some(RefineOptions::default()), ..DetectorOptions::for_families(&[TagFamily::Tag36h11]) };
    let library = Detector::with_workers(opts, 2).unwrap();
    let confirmer = TagConfirmer::new(ConfirmOptions::default(), roles.known());
    let rig = Arc::new(RigDetectors { library, confirmer, roles });
    let full_search = |img: &GrayImage| {
        let found = rig.library.search(img, None, &SearchOptions::of(rig.library.options()), Lens::new(Some(&intr)));
        let mut ids: Vec<u32> = found.iter().map(|d| d.id).collect();
        ids.sort_unstable();
        (ids, found)
    };
    let ids = |d: &tagdeflect_detect::CameraDetections| {
        let mut v: Vec<u32> = d.background.iter().chain(&d.specimen).map(|d| d.id).collect();
        v.sort_unstable();
        v
    };
    let (full_ids, full) = full_search(&oblique);
    let mut cam = CameraDetector::new(intr, true, 1.0, 0);
    let (first, _) = cam.detect(0, &frontal, &rig);
    assert!(
        first.background.len() >= 18 && first.specimen.len() >= 55,
        "frontal photo: {} + {} tags",
        first.background.len(),
        first.specimen.len()
    );
    // The camera moved: the oblique photo.
    let t1 = 100_000_000;
    let (windows, report) = cam.detect(t1, &oblique, &rig);
    println!(
        "REALDATA moved camera: windows found {} of the {} tags of the oblique photo; background lost {}, shift {:?} px",
        ids(&windows).len(),
        full_ids.len(),
        report.background.lost,
        report.background.shift_px
    );
    assert!(full_ids.len() >= 25, "the oblique photo shows {} tags", full_ids.len());
    assert_eq!(report.full_frame_searches, 0);
    assert!(report.background.lost, "the background tags left their windows and that is reported");
    let (again, again_report) = cam.search_again(t1, &oblique, &rig);
    assert_eq!(again_report.full_frame_searches, 1);
    assert_eq!(ids(&again), full_ids, "the moved frame searched whole finds what a full-frame search finds");
    // The next frame of the moved camera: followed from where the tags are now.
    let (next, next_report) = cam.detect(2 * t1, &oblique, &rig);
    println!("REALDATA moved camera, next frame: {} tags, {:?}", ids(&next).len(), next_report);
    // Every tag of the whole-frame search is followed (the windows, searched with the
    // tracking mode's contrast filter, may find a few more than it).
    let next_ids = ids(&next);
    // (Measured: 27 of 29; tags 119 and 159, at the photo's far edge, are not followed.)
    let missed: Vec<u32> = full_ids.iter().copied().filter(|id| !next_ids.contains(id)).collect();
    println!("REALDATA moved camera, next frame: tags of the whole-frame search not followed {missed:?}");
    assert!(
        missed.len() * 10 <= full_ids.len(),
        "the next frame follows {} of {} tags: missed {missed:?}",
        full_ids.len() - missed.len(),
        full_ids.len()
    );
    assert_eq!((next_report.full_frame_searches, next_report.background_searches), (0, 0), "no whole-frame search needed");
    // Where the followed corners differ from the whole-frame search's. Measured (before it
    // was asserted): the largest differences lie along the long edges of the steepest tags
    // (~60 × 400 px here, where a corner's place along an edge is poorly determined by either
    // search), and the worst of all (6.95 px) on tag 45, whose corner is cut by the photo's
    // top border. So the tags wholly inside the photo are bounded relative to their longest
    // edge, and the tags cut by the border by an absolute bound.
    let (wf, hf) = (oblique.width as f64, oblique.height as f64);
    let (mut worst_inside, mut worst_inside_px, mut worst_cut_px) = ((0.0_f64, 0), 0.0_f64, (0.0_f64, 0));
    for d in next.background.iter().chain(&next.specimen) {
        let Some(f) = full.iter().find(|f| f.id == d.id) else { continue };
        let inside = f.corners.iter().chain(&d.corners).all(|c| c.x >= 2.0 && c.y >= 2.0 && c.x <= wf - 3.0 && c.y <= hf - 3.0);
        let longest_edge_px = (0..4).map(|k| (f.corners[(k + 1) % 4] - f.corners[k]).norm()).fold(0.0, f64::max);
        let diff_px = (0..4).map(|k| (d.corners[k] - f.corners[k]).norm()).fold(0.0, f64::max);
        if inside {
            if diff_px / longest_edge_px > worst_inside.0 {
                worst_inside = (diff_px / longest_edge_px, d.id);
            }
            worst_inside_px = worst_inside_px.max(diff_px);
        } else if diff_px > worst_cut_px.0 {
            worst_cut_px = (diff_px, d.id);
        }
    }
    println!(
        "REALDATA moved camera, next frame: worst corner difference from full-frame: tags inside the photo \
         {:.3} % of the longest edge (tag {}; {worst_inside_px:.3} px), tags cut by the border {:.3} px (tag {})",
        100.0 * worst_inside.0,
        worst_inside.1,
        worst_cut_px.0,
        worst_cut_px.1
    );
    assert!(
        worst_inside.0 <= MOVED_WORST_INSIDE_OF_EDGE,
        "tag {}: followed corner {:.3} % of its edge from the whole-frame search's",
        worst_inside.1,
        100.0 * worst_inside.0
    );
    assert!(
        worst_cut_px.0 <= MOVED_WORST_CUT_PX,
        "tag {} (cut by the border): followed corner {:.3} px from the whole-frame search's",
        worst_cut_px.1,
        worst_cut_px.0
    );
}

/// The followed corners' largest difference from the whole-frame search's, for tags wholly
/// inside the oblique photo, as a fraction of the tag's longest edge: measured 1.74 % (tag
/// 114, 4.98 px on a ~290 px edge), bound at 1.3× that.
const MOVED_WORST_INSIDE_OF_EDGE: f64 = 0.023;
/// The same for tags cut by the photo's border, in px: measured 6.95 px (tag 45, a corner
/// above the photo's top edge), bound at 1.3× that.
const MOVED_WORST_CUT_PX: f64 = 9.0;
