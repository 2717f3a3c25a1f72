//! Each fitted edge against the true edge line, per image formation (docs/accuracy.md, "The
//! edge's bias against its angle and its phase"): the three-camera 1280x960 scene of
//! `formations::` rendered with no read noise, every camera's frames through the product's
//! camera detector (tracking, the learned edge profile), and every specimen and background
//! tag's four edges compared with the simulator's projected truth.
//!
//! Per edge (corners `a`, `b` fitted, `A`, `B` true; `n` the true edge's unit normal): the
//! fitted line's normal offset at each end, `n·(a − A)` and `n·(b − B)`, and at its middle
//! (their mean). What a displacement sees is an edge's offset *changing* between frames, so
//! the table gives, binned by the edge's angle to the pixel grid (folded into 0–45°): the
//! offsets' mean and RMS, and the RMS of each edge's middle and end offsets about that edge's
//! own mean over the frames. Then, for edges within 2° of the grid, the middle offset against
//! the edge's sub-pixel phase (the true line's coordinate across it, modulo 1 px): a profile
//! that is wrong on aligned edges shows as a curve over the phase.
//!
//! Then the specimen edges' mean middle offset per frame set: a shift common to a set's
//! edges (a rebuilt profile moves every edge at once).
//!
//! `cargo test --test it edge_bias:: -- --ignored --nocapture` (about a minute per scene);
//! `TAGDEFLECT_EDGE_MODEL=kernel2d` (or `kernel2d-sites`) fits the edges with the 2-D kernel;
//! `TAGDEFLECT_FORMATIONS=sharpen` (substrings of the scenes' names) chooses scenes.

use std::collections::HashMap;
use std::sync::Arc;

use nalgebra::{Point2, Vector2, Vector3};
use tagdeflect_core::tags::TagFamily;
use tagdeflect_detect::{
    CameraDetector, ConfirmOptions, Detection, Detector, DetectorOptions, RefineOptions, RigDetectors, TagConfirmer, TagRoles,
};
use tagdeflect_sim::{render_frame_set, SimParams, SimRig};

/// One edge seen in one frame: its key, angle to the grid (degrees, 0–45), sub-pixel phase
/// (px, 0–1), and the normal offsets (px) at its ends `a`, `b`; for the edge's Cramér–Rao
/// bound (`edge_bound::`) also its true geometry: the middle point (pixels), the length
/// (px), and the direction (degrees, 0–360) of a line whose normal `(−sin, cos)` points out
/// of the tag.
pub(crate) struct EdgeSeen {
    pub key: (usize, TagFamily, u32, usize),
    pub set: u64,
    pub angle_deg: f64,
    pub phase_px: f64,
    pub off_a: f64,
    pub off_b: f64,
    pub mid_px: [f64; 2],
    pub length_px: f64,
    pub outward_dir_deg: f64,
}

fn edges_of(set: u64, cam: usize, d: &Detection, truth: &[Point2<f64>; 4]) -> Vec<EdgeSeen> {
    let centre = truth.iter().fold(Vector2::zeros(), |s, p| s + p.coords) / 4.0;
    (0..4)
        .map(|i| {
            let j = (i + 1) % 4;
            let (ta, tb) = (truth[i], truth[j]);
            let u = (tb - ta).normalize();
            let n = Vector2::new(-u.y, u.x);
            let deg = u.y.atan2(u.x).to_degrees().abs() % 90.0;
            let angle_deg = deg.min(90.0 - deg);
            // The coordinate across the edge: y for a near-horizontal edge, x for a vertical one.
            let mid = ta + 0.5 * (tb - ta);
            let across = if u.x.abs() > u.y.abs() { mid.y } else { mid.x };
            let phase_px = across - across.floor();
            // The direction whose normal (−sin, cos) points away from the tag's centre.
            let out = if n.dot(&(mid.coords - centre)) > 0.0 { u } else { -u };
            EdgeSeen {
                mid_px: [mid.x, mid.y],
                length_px: (tb - ta).norm(),
                outward_dir_deg: out.y.atan2(out.x).to_degrees().rem_euclid(360.0),
                key: (cam, d.family, d.id, i),
                set,
                angle_deg,
                phase_px,
                off_a: n.dot(&(d.corners[i] - ta)),
                off_b: n.dot(&(d.corners[j] - tb)),
            }
        })
        .collect()
}

/// Every tag's true corners (distorted pixels) in camera `cam` at `t_ns`, by (family, id).
fn truth_corners(rig: &SimRig, cam: usize, t_ns: i64) -> HashMap<(TagFamily, u32), [Point2<f64>; 4]> {
    let intr = rig.cameras()[cam].intrinsics;
    let pose = rig.camera_pose(cam, t_ns);
    let lens = tagdeflect_sim::lens::Lens::of(&intr);
    let project = |w: &Vector3<f64>| lens.pixel(&pose.transform(w));
    let mut out = HashMap::new();
    let mut put = |key, corners: Vec<Point2<f64>>| {
        if corners.len() == 4 && corners.iter().all(|p| intr.in_image(p, 10.0)) {
            out.insert(key, [corners[0], corners[1], corners[2], corners[3]]);
        }
    };
    for (id, c) in rig.tag_corners_world(t_ns) {
        put((TagFamily::Tag36h11, id), c.iter().filter_map(project).collect());
    }
    for b in rig.background_tags() {
        put((TagFamily::Tag25h9, b.id), b.corners_mm.iter().filter_map(|c| project(&Vector3::new(c[0], c[1], c[2]))).collect());
    }
    out
}

fn rig_detectors(rig: &SimRig) -> Arc<RigDetectors> {
    let roles = TagRoles {
        background_family: TagFamily::Tag25h9,
        background: rig.background_tags().iter().map(|b| b.id).collect(),
        specimen_family: TagFamily::Tag36h11,
        specimen: rig.specimen_roles().iter().map(|r| r.0).collect(),
    };
    let opts = DetectorOptions {
        nthreads: 1,
        subpixel: Some(RefineOptions::default()),
        ..DetectorOptions::for_families(&[TagFamily::Tag36h11, TagFamily::Tag25h9])
    };
    let library = Detector::with_workers(opts, 2).unwrap();
    let confirmer = TagConfirmer::new(ConfirmOptions::default(), roles.known());
    Arc::new(RigDetectors { library, confirmer, roles })
}

/// Every edge of every matched tag over the scene's frame sets.
pub(crate) fn measure(p: &SimParams) -> Vec<EdgeSeen> {
    let rig = SimRig::new(p).expect("sim rig");
    let shared = rig_detectors(&rig);
    let cams = rig.cameras();
    let mut dets: Vec<CameraDetector> =
        cams.iter().enumerate().map(|(k, c)| CameraDetector::new(c.intrinsics, true, 1.0, k as u32)).collect();
    let mut out = Vec::new();
    for k in 0..p.frame_sets as u64 {
        for (cam, frame) in render_frame_set(&rig, k).into_iter().enumerate() {
            let Some((t_ns, img)) = frame else { continue };
            let (found, _) = dets[cam].detect(t_ns, &img, &shared);
            let truth = truth_corners(&rig, cam, t_ns);
            for d in found.specimen.iter().chain(&found.background) {
                let Some(t) = truth.get(&(d.family, d.id)) else { continue };
                if (0..4).any(|i| (d.corners[i] - t[i]).norm() > 1.0) {
                    continue;
                }
                out.extend(edges_of(k, cam, d, t));
            }
        }
    }
    out
}

fn rms(v: impl Iterator<Item = f64>) -> (f64, usize) {
    let (s, n) = v.fold((0.0, 0usize), |(s, n), x| (s + x * x, n + 1));
    ((s / n.max(1) as f64).sqrt(), n)
}

/// The table of one scene: per angle bin, edges, offsets' mean and RMS, and each edge's
/// middle and end offsets' RMS about its own mean (what moves between frames).
fn report(name: &str, seen: &[EdgeSeen]) {
    let mut by_edge: HashMap<(usize, TagFamily, u32, usize), Vec<&EdgeSeen>> = HashMap::new();
    seen.iter().for_each(|e| by_edge.entry(e.key).or_default().push(e));
    let bins = [0.0, 0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 45.01];
    println!("EDGES {name}: {} edge fits, {} edges", seen.len(), by_edge.len());
    println!("| {name}: edge angle | edges | fits | mean middle offset | RMS middle offset | middle about the edge's mean | ends about the edge's mean |");
    println!("| --- | --- | --- | --- | --- | --- | --- |");
    for w in bins.windows(2) {
        let edges: Vec<&Vec<&EdgeSeen>> = by_edge.values().filter(|v| v.len() >= 3 && (w[0]..w[1]).contains(&v[0].angle_deg)).collect();
        if edges.is_empty() {
            continue;
        }
        let fits: Vec<&EdgeSeen> = edges.iter().flat_map(|v| v.iter().copied()).collect();
        let mid = |e: &EdgeSeen| 0.5 * (e.off_a + e.off_b);
        let mean = fits.iter().map(|e| mid(e)).sum::<f64>() / fits.len() as f64;
        let (all, n) = rms(fits.iter().map(|e| mid(e)));
        let about = |f: &dyn Fn(&EdgeSeen) -> f64| {
            rms(edges.iter().flat_map(|v| {
                let m = v.iter().map(|e| f(e)).sum::<f64>() / v.len() as f64;
                v.iter().map(move |e| f(e) - m).collect::<Vec<_>>()
            }))
            .0
        };
        let ends = (0.5 * (about(&|e: &EdgeSeen| e.off_a).powi(2) + about(&|e: &EdgeSeen| e.off_b).powi(2))).sqrt();
        println!(
            "| {:.1}–{:.0}° | {} | {n} | {mean:+.4} px | {all:.4} px | {:.4} px | {ends:.4} px |",
            w[0],
            w[1].min(45.0),
            edges.len(),
            about(&mid)
        );
    }
    let aligned: Vec<&EdgeSeen> = seen.iter().filter(|e| e.angle_deg < 2.0).collect();
    let cells: Vec<String> = (0..8)
        .map(|b| {
            let v: Vec<f64> = aligned.iter().filter(|e| (e.phase_px * 8.0) as usize == b).map(|e| 0.5 * (e.off_a + e.off_b)).collect();
            if v.is_empty() {
                "—".into()
            } else {
                format!("{:+.4}", v.iter().sum::<f64>() / v.len() as f64)
            }
        })
        .collect();
    let sets = seen.iter().map(|e| e.set).max().unwrap_or(0) + 1;
    let per_set: Vec<String> = (0..sets)
        .map(|k| {
            let v: Vec<f64> =
                seen.iter().filter(|e| e.set == k && e.key.1 == TagFamily::Tag36h11).map(|e| 0.5 * (e.off_a + e.off_b)).collect();
            format!("{:+.4}", v.iter().sum::<f64>() / v.len().max(1) as f64)
        })
        .collect();
    println!("SETS {name}: specimen edges' mean middle offset (px) per frame set: {}", per_set.join(" "));
    println!("PHASE {name}: edges within 2°, mean middle offset (px) per 1/8 px of phase: {}", cells.join(" "));
}

#[test]
#[ignore = "a measurement of minutes: run with --ignored --nocapture"]
fn edge_offsets_against_angle_and_phase_per_formation() {
    let only: Vec<String> = std::env::var("TAGDEFLECT_FORMATIONS")
        .map(|v| v.split(',').map(|s| s.trim().to_lowercase()).filter(|s| !s.is_empty()).collect())
        .unwrap_or_default();
    let base = SimParams { noise_sigma: 0.0, ..crate::formations::sharp_scene() };
    let scenes = [
        ("sharp", base.clone()),
        ("Gaussian 0.7 px after the pixel", SimParams { post_blur_px: 0.7, ..base.clone() }),
        ("3×3 sharpening, amount 1", SimParams { sharpen: 1.0, ..base.clone() }),
        ("Bayer RGGB, bilinear demosaic", SimParams { bayer: true, ..base.clone() }),
    ];
    let mut ran = 0;
    for (name, p) in scenes.iter().filter(|(name, _)| only.is_empty() || only.iter().any(|o| name.to_lowercase().contains(o.as_str()))) {
        let seen = measure(p);
        assert!(seen.len() > 100, "{name}: only {} edge fits matched", seen.len());
        report(name, &seen);
        ran += 1;
    }
    assert!(ran > 0, "no scene chosen");
}
