use super::rects::{x1, y1};
use super::*;

fn det(id: u32, x: f64, y: f64, s: f64) -> Detection {
    Detection {
        family: TagFamily::Tag36h11,
        id,
        corners: [Point2::new(x, y + s), Point2::new(x + s, y + s), Point2::new(x + s, y), Point2::new(x, y)],
        decision_margin: 50.0,
        hamming: 0,
    }
}

fn bg(id: u32, x: f64, y: f64, s: f64) -> Detection {
    Detection { family: TagFamily::Tag25h9, ..det(id, x, y, s) }
}

fn intr() -> CameraIntrinsics {
    CameraIntrinsics { width: 1000, height: 800, fx: 1000.0, fy: 1000.0, cx: 499.5, cy: 399.5, dist: [0.0; 5] }
}

fn inside(rects: &[Rect], x: f64, y: f64, half: f64) -> bool {
    rects.iter().any(|r| (r.x as f64) < x - half && (x1(r) as f64) > x + half && (r.y as f64) < y - half && (y1(r) as f64) > y + half)
}

fn track(plan: Plan) -> (Vec<Rect>, Vec<Rect>) {
    match plan {
        Plan::Windows { tags, sweep, .. } => (merge_rects(tags.iter().map(|t| t.window).collect()), sweep),
        Plan::FullFrame => panic!("expected windows, got a full-frame search"),
    }
}

#[test]
fn first_frame_is_full_then_small_windows() {
    let img = GrayImage::new(1000, 800);
    let mut p = RoiPlanner::new(intr(), true, 1.0);
    assert_eq!(p.plan(0, &img), Plan::FullFrame);
    p.observe(0, &[], &[det(1, 100.0, 100.0, 40.0), det(2, 600.0, 500.0, 40.0)]);
    let (windows, _) = track(p.plan(33_000_000, &img));
    assert!(inside(&windows, 120.0, 120.0, 28.0) && inside(&windows, 620.0, 520.0, 28.0), "{windows:?}");
    let area: u64 = windows.iter().map(Rect::area).sum();
    assert!(area < 2 * 100 * 100, "windows cover {area} px");
}

#[test]
fn a_lost_tag_triggers_one_sweep_of_the_whole_frame() {
    let img = GrayImage::new(1000, 800);
    let mut p = RoiPlanner::new(intr(), true, 1.0);
    p.plan(0, &img);
    p.observe(0, &[], &[det(1, 100.0, 100.0, 40.0), det(2, 600.0, 500.0, 40.0)]);
    p.plan(33_000_000, &img);
    p.observe(33_000_000, &[], &[det(1, 100.0, 100.0, 40.0)]);
    let (_, sweep) = track(p.plan(66_000_000, &img));
    assert_eq!(sweep, vec![Rect { x: 0, y: 0, width: 1000, height: 800 }], "lost tag → whole frame swept");
    p.observe(66_000_000, &[], &[det(1, 100.0, 100.0, 40.0)]);
    let (_, sweep) = track(p.plan(99_000_000, &img));
    assert!(sweep.iter().map(Rect::area).sum::<u64>() < 1000 * 800 / 4, "still lost → back to the periodic sweep");
}

#[test]
fn sweep_tiles_cover_the_whole_frame_within_the_interval_and_spread() {
    let img = GrayImage::new(1000, 800);
    let mut p = RoiPlanner::new(intr(), true, 0.5).with_phase(1);
    p.plan(0, &img);
    let mut covered = vec![false; 1000 * 800];
    let mut worst = 0u64;
    let frames = 16; // 0.5 s at 30 fps: one sweep cycle
    for k in 1..=frames {
        let t = k * 33_333_333;
        p.observe(t - 33_333_333, &[], &[det(1, 100.0, 100.0, 40.0)]);
        let (_, sweep) = track(p.plan(t, &img));
        worst = worst.max(sweep.iter().map(Rect::area).sum());
        for r in &sweep {
            for y in r.y..y1(r) {
                covered[(y * 1000 + r.x) as usize..(y * 1000 + x1(r)) as usize].iter_mut().for_each(|c| *c = true);
            }
        }
    }
    assert!(covered.iter().all(|&c| c), "every pixel swept");
    assert!(worst < 1000 * 800 / 3, "at most a fraction of the frame per frame: {worst} px");
}

#[test]
fn tiles_overlap_by_more_than_a_tag() {
    let tiles = sweep_tiles(1920, 1080, 120.0);
    assert!(tiles.len() > 4);
    // Any 120 px square lies wholly inside some tile.
    for y in (0..=960).step_by(37) {
        for x in (0..=1800).step_by(41) {
            let t = Rect { x, y, width: 120, height: 120 };
            assert!(tiles.iter().any(|r| r.x <= t.x && r.y <= t.y && x1(r) >= x1(&t) && y1(r) >= y1(&t)), "{t:?} in no tile");
        }
    }
}

#[test]
fn background_tags_rotate_once_settled_and_all_return_after_a_shift() {
    let img = GrayImage::new(1000, 800);
    let mut p = RoiPlanner::new(intr(), true, 1.0);
    p.plan(0, &img);
    let bgs: Vec<Detection> = (0..8).map(|i| bg(i, 50.0 + 110.0 * i as f64, 700.0, 40.0)).collect();
    let sp = [det(1, 400.0, 300.0, 40.0)];
    let mut t = 0;
    p.observe(t, &bgs, &sp);
    let windows_with_bg = |p: &mut RoiPlanner, t: i64| {
        let (w, _) = track(p.plan(t, &img));
        (0..8).filter(|&i| inside(&w, 70.0 + 110.0 * i as f64, 720.0, 21.0)).count()
    };
    let mut counts = Vec::new();
    for _ in 0..(SETTLE_FRAMES + 8) {
        t += 33_000_000;
        counts.push(windows_with_bg(&mut p, t));
        // Only the searched tags are reported (the others were not searched).
        p.observe(t, &bgs, &sp);
    }
    assert!(counts[..SETTLE_FRAMES as usize].iter().all(|&c| c == 8), "all while settling: {counts:?}");
    assert!(counts[SETTLE_FRAMES as usize + 1..].iter().all(|&c| c < 8), "a subset once settled: {counts:?}");
    // A bump: the background tags seen move by 3 px → all searched again.
    let bumped: Vec<Detection> = (0..8).map(|i| bg(i, 53.0 + 110.0 * i as f64, 702.0, 40.0)).collect();
    t += 33_000_000;
    p.plan(t, &img);
    p.observe(t, &bumped[..3], &sp);
    t += 33_000_000;
    assert_eq!(windows_with_bg(&mut p, t), 8);
}

#[test]
fn unsearched_background_tags_are_not_lost() {
    let img = GrayImage::new(1000, 800);
    let mut p = RoiPlanner::new(intr(), true, 1.0);
    p.plan(0, &img);
    let bgs: Vec<Detection> = (0..8).map(|i| bg(i, 50.0 + 110.0 * i as f64, 700.0, 40.0)).collect();
    p.observe(0, &bgs, &[]);
    for k in 1..=(SETTLE_FRAMES as i64 + 40) {
        let t = k * 33_000_000;
        let (w, sweep) = track(p.plan(t, &img));
        assert!(k <= 2 || sweep.iter().all(|r| r.area() < 1000 * 800 / 2), "frame {k}: no whole-frame sweep");
        // Report exactly the tags whose windows were searched.
        let seen: Vec<Detection> = bgs.iter().filter(|d| inside(&w, d.corners[0].x + 20.0, d.corners[0].y - 20.0, 21.0)).cloned().collect();
        p.observe(t, &seen, &[]);
    }
    assert_eq!(p.sightings.len(), 8);
}

#[test]
fn an_occluded_background_tag_is_searched_at_growing_intervals() {
    let img = GrayImage::new(1000, 800);
    let mut p = RoiPlanner::new(intr(), true, 1.0);
    p.plan(0, &img);
    let bgs: Vec<Detection> = (0..3).map(|i| bg(i, 50.0 + 300.0 * i as f64, 700.0, 40.0)).collect();
    p.observe(0, &bgs, &[]);
    // Tag 2 hidden from frame 1 on: the frames in which its window is searched.
    let mut searched = Vec::new();
    for k in 1..=40i64 {
        let t = k * 33_000_000;
        let (w, _) = track(p.plan(t, &img));
        if inside(&w, 670.0, 720.0, 21.0) {
            searched.push(k);
        }
        p.observe(t, &bgs[..2], &[]);
    }
    assert_eq!(searched, vec![1, 2, 4, 8, 16, 32], "searched at once, then after 1, 3, 7, 15 frames");
    // Seen again: searched every frame as before.
    p.observe(41 * 33_000_000, &bgs, &[]);
    let (w, _) = track(p.plan(42 * 33_000_000, &img));
    assert!(inside(&w, 670.0, 720.0, 21.0));
}

#[test]
fn overlapping_rects_merge() {
    let r = |x, y, w, h| Rect { x, y, width: w, height: h };
    let m = merge_rects(vec![r(0, 0, 10, 10), r(2, 2, 10, 10), r(50, 50, 10, 10)]);
    assert_eq!(m.len(), 2);
    assert!(m.contains(&r(0, 0, 12, 12)));
    // A full-width strip does not swallow a window that only touches it.
    let m = merge_rects(vec![r(0, 100, 1000, 50), r(400, 140, 40, 40)]);
    assert_eq!(m.len(), 2);
}
