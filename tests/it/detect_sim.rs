//! Detector corners against the synthetic rig's truth (`tagdeflect_sim`): the pixel
//! convention (mean offset of the library's converted corners vs projected truth) and the
//! gain of sub-pixel refinement, per scenario. Figures are printed.

use nalgebra::{Point2, Vector2, Vector3};
use tagdeflect_core::tags::TagFamily;
use tagdeflect_detect::{Detection, Detector, DetectorOptions};
use tagdeflect_sim::{render_frame_set, SimParams, SimRig};

#[derive(Default)]
struct Acc {
    n: usize,
    sum: Vector2<f64>,
    sq: f64,
    /// Sum of the error component along the tag-centre → corner direction.
    radial: f64,
}

impl Acc {
    fn add(&mut self, e: Vector2<f64>, outward: Vector2<f64>) {
        self.n += 1;
        self.sum += e;
        self.sq += e.norm_squared();
        self.radial += e.dot(&outward);
    }
    fn mean_radial(&self) -> f64 {
        self.radial / self.n.max(1) as f64
    }
    fn mean(&self) -> Vector2<f64> {
        self.sum / self.n.max(1) as f64
    }
    fn rms(&self) -> f64 {
        (self.sq / self.n.max(1) as f64).sqrt()
    }
}

struct Figures {
    raw: Acc,
    refined: Acc,
    missed: usize,
    tags: usize,
}

fn run(params: &SimParams, sets: &[u64]) -> Figures {
    let rig = SimRig::new(params).expect("sim rig");
    let cams = rig.cameras();
    let fams = [TagFamily::Tag36h11, TagFamily::Tag25h9];
    let mut raw_det = Detector::new(DetectorOptions { subpixel: None, ..DetectorOptions::for_families(&fams) }).unwrap();
    let mut ref_det = Detector::new(DetectorOptions::for_families(&fams)).unwrap();
    let background = rig.background_tags();
    let mut f = Figures { raw: Acc::default(), refined: Acc::default(), missed: 0, tags: 0 };
    for &k in sets {
        for (cam, frame) in render_frame_set(&rig, k).into_iter().enumerate() {
            let Some((t_ns, img)) = frame else { continue };
            let intr = cams[cam].intrinsics;
            let pose = rig.camera_pose(cam, t_ns);
            ref_det.set_intrinsics(Some(intr));
            // Truth: every tag whose four corners project well inside the image.
            let mut truth: Vec<(TagFamily, u32, [Point2<f64>; 4])> = Vec::new();
            // The simulator's own lens model (independent of the product's).
            let lens = tagdeflect_sim::lens::Lens::of(&intr);
            let project = |w: &Vector3<f64>| lens.pixel(&pose.transform(w));
            for (id, corners) in rig.tag_corners_world(t_ns) {
                let px: Vec<Point2<f64>> = corners.iter().filter_map(project).collect();
                if px.len() == 4 && px.iter().all(|p| intr.in_image(p, 10.0)) {
                    truth.push((TagFamily::Tag36h11, id, [px[0], px[1], px[2], px[3]]));
                }
            }
            for b in &background {
                let px: Vec<Point2<f64>> = b.corners_mm.iter().filter_map(|c| project(&Vector3::new(c[0], c[1], c[2]))).collect();
                if px.len() == 4 && px.iter().all(|p| intr.in_image(p, 10.0)) {
                    truth.push((TagFamily::Tag25h9, b.id, [px[0], px[1], px[2], px[3]]));
                }
            }
            let raw = raw_det.detect(&img);
            let refined = ref_det.detect(&img);
            let find = |v: &[Detection], fam, id| v.iter().find(|d| d.family == fam && d.id == id).cloned();
            for (fam, id, t) in &truth {
                let (Some(r), Some(q)) = (find(&raw, *fam, *id), find(&refined, *fam, *id)) else {
                    f.missed += 1;
                    continue;
                };
                // A tag hidden or cut by the beam's edge would show as a gross error; skip those.
                if (0..4).any(|i| (r.corners[i] - t[i]).norm() > 2.0) {
                    f.missed += 1;
                    continue;
                }
                f.tags += 1;
                let centre = (t[0].coords + t[1].coords + t[2].coords + t[3].coords) / 4.0;
                for (i, ti) in t.iter().enumerate() {
                    let outward = (ti.coords - centre).normalize();
                    f.raw.add(r.corners[i] - ti, outward);
                    f.refined.add(q.corners[i] - ti, outward);
                }
            }
        }
    }
    let s = ref_det.refine_stats();
    println!(
        "  refine stats: {} tags, {} corners refined, {} kept ({} failed fits, {} too far)",
        s.tags, s.corners_refined, s.corners_kept, s.failed_fit, s.too_far
    );
    f
}

#[test]
fn simulated_rig_corners_convention_and_refinement_gain() {
    let cases = [
        ("default rig (3 cams 1280x960, noise 2, blur 0.6, k1 -0.05)", SimParams { frame_sets: 12, ..SimParams::default() }),
        ("noise-free (noise 0, blur 0.6, k1 -0.05)", SimParams { frame_sets: 12, noise_sigma: 0.0, ..SimParams::default() }),
        (
            "hard (noise 5, blur 1.2, k1 -0.25 on camera 0)",
            SimParams { frame_sets: 12, noise_sigma: 5.0, blur_sigma: 1.2, strong_distortion_camera: Some(0), ..SimParams::default() },
        ),
    ];
    for (name, params) in cases {
        let f = run(&params, &[0, 11]);
        let (mr, mq) = (f.raw.mean(), f.refined.mean());
        println!(
            "{name}: {} tags ({} not matched); library corners: mean offset ({:+.4}, {:+.4}) px, RMS {:.4} px; refined: mean ({:+.4}, {:+.4}) px, RMS {:.4} px ({:.2}x better)",
            f.tags,
            f.missed,
            mr.x,
            mr.y,
            f.raw.rms(),
            mq.x,
            mq.y,
            f.refined.rms(),
            f.raw.rms() / f.refined.rms()
        );
        println!("  mean outward error: library {:+.4} px, refined {:+.4} px", f.raw.mean_radial(), f.refined.mean_radial());
        assert!(f.tags >= 20, "{name}: only {} tags matched", f.tags);
        // Pixel convention: no systematic offset against the projected truth.
        assert!(mr.norm() < 0.05, "{name}: library corners offset by {mr:?}");
        assert!(mq.norm() < 0.05, "{name}: refined corners offset by {mq:?}");
        assert!(f.refined.rms() < 0.8 * f.raw.rms(), "{name}: refinement gives {:.4} vs {:.4}", f.refined.rms(), f.raw.rms());
    }
}
