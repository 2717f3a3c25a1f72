//! The missed window searched again at the configured resolution (the camera detector's
//! retry, `CameraDetector::retry_missed`).

use super::*;
use crate::apriltag::DetectorOptions;
use crate::confirm::ConfirmOptions;
use crate::family::tag_bitmap;
use nalgebra::Point2;

const WHITE: u8 = 220;
const BLACK: u8 = 30;

/// A grey image with tag36h11 `id` printed at `(x0, y0)`, `cell_px` pixels a cell (its
/// white ring included), edges on pixel boundaries.
fn image_with_tag(id: u32, x0: u32, y0: u32, cell_px: u32) -> GrayImage {
    let (width, height) = (240, 200);
    let mut data = vec![WHITE; (width * height) as usize];
    let bitmap = tag_bitmap(TagFamily::Tag36h11, id).expect("tag36h11 id");
    let n = bitmap.total_width;
    for cy in 0..n {
        for cx in 0..n {
            let level = if bitmap.white[(cy * n + cx) as usize] { WHITE } else { BLACK };
            for y in 0..cell_px {
                for x in 0..cell_px {
                    data[((y0 + cy * cell_px + y) * width + x0 + cx * cell_px + x) as usize] = level;
                }
            }
        }
    }
    GrayImage::from_8bit(width, height, data)
}

/// A rig of tag36h11 specimen tags 0…9, searched at full resolution without corner
/// refinement (what the retry decides does not depend on it).
fn rig() -> RigDetectors {
    let options = DetectorOptions { subpixel: None, ..DetectorOptions::for_families(&[TagFamily::Tag36h11]) };
    let roles = TagRoles {
        background_family: TagFamily::Tag36h11,
        background: HashSet::new(),
        specimen_family: TagFamily::Tag36h11,
        specimen: (0..10).collect(),
    };
    let confirmer = TagConfirmer::new(ConfirmOptions::default(), roles.known());
    RigDetectors { library: Detector::new(options).expect("detector"), confirmer, roles }
}

fn detector() -> CameraDetector {
    let intrinsics = CameraIntrinsics { width: 240, height: 200, fx: 300.0, fy: 300.0, cx: 120.0, cy: 100.0, dist: [0.0; 5] };
    CameraDetector::new(intrinsics, true, 10.0, 0)
}

fn planned(id: u32, window: Rect, expected: bool) -> PlannedTag {
    let predicted = [Point2::new(window.x as f64, window.y as f64); 4];
    PlannedTag { family: TagFamily::Tag36h11, id, predicted, window, expected }
}

fn found(id: u32) -> Detection {
    Detection { family: TagFamily::Tag36h11, id, corners: [Point2::origin(); 4], decision_margin: 50.0, hamming: 0 }
}

#[test]
fn only_the_windows_of_tags_seen_last_time_and_not_found_now_are_searched_again() {
    let (a, b, c) = (
        Rect { x: 10, y: 10, width: 40, height: 40 },
        Rect { x: 20, y: 20, width: 40, height: 40 },
        Rect { x: 150, y: 100, width: 50, height: 50 },
    );
    // Tag 1 missed and not found: retried; tag 2 found by the decimated search: not; tag 3
    // already missing the last time it was looked for (occluded): left to the sweep.
    let missed = [planned(1, a, true), planned(2, c, true), planned(3, c, false)];
    assert_eq!(retry_windows(&missed, &[found(2)]), vec![a]);
    // Two missed tags whose windows overlap enough are searched in one window.
    let both = retry_windows(&[planned(1, a, true), planned(4, b, true)], &[]);
    assert_eq!(both, vec![Rect { x: 10, y: 10, width: 50, height: 50 }]);
    assert!(retry_windows(&missed, &[found(1), found(2)]).is_empty());
}

#[test]
fn a_tag_the_decimated_window_search_misses_is_found_by_the_retry_in_the_same_frame() {
    let rig = rig();
    let mut camera = detector();
    // A small tag (3 px a cell: the black square 24 px) that a search at quad decimation 6
    // cannot find (its black square is 4 px across there) and a full-resolution one can.
    let image = image_with_tag(7, 100, 80, 3);
    let window = Rect { x: 80, y: 60, width: 70, height: 70 };
    let decimated = camera.search_options(&rig, 6.0);
    let lens = Lens::new(None);
    assert!(rig.library.search(&image, Some(window), &decimated, lens).is_empty(), "the decimated search of the window misses the tag");
    let missed = [planned(7, window, true)];
    let (again, retries) = camera.retry_missed(&rig, &image, &missed, &[], 6.0);
    assert_eq!(retries, 1, "one window searched again");
    assert_eq!(again.iter().map(|d| d.id).collect::<Vec<_>>(), vec![7], "found at the configured resolution");
    let centre = again[0].centre();
    assert!((centre.x - 115.0).abs() < 1.0 && (centre.y - 95.0).abs() < 1.0, "where it is printed: {centre:?}");
    // Not retried when it was already missing, or when the windows ran at the configured
    // options already (nothing a second search could add).
    let (none, retries) = camera.retry_missed(&rig, &image, &[planned(7, window, false)], &[], 6.0);
    assert!(none.is_empty() && retries == 0);
    let (none, retries) = camera.retry_missed(&rig, &image, &missed, &[], 1.0);
    assert!(none.is_empty() && retries == 0);
}
