//! `tagdeflect verify` on a simulated verification run: the class and the uncertainty its
//! truth supports, a step error injected moving the class as ISO 9513's table says, and bad
//! input refused with exit 2.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use tagdeflect::commands::verify::{self, VerifyArgs};
use tagdeflect::config::Recording;
use tagdeflect_core::feed::FeedLine;
use tagdeflect_sim::SimParams;
use tagdeflect_verify::{iso9513, StepPlan, Verification, VERIFY_STEPS_FILE};

use crate::common::simulate;

fn args(rec: &Path, out: PathBuf, steps: Option<PathBuf>) -> VerifyArgs {
    VerifyArgs {
        dir: rec.to_path_buf(),
        steps,
        operator: Some("A. Tester".into()),
        equipment: Some("micrometer stage MS-25 #1187".into()),
        equipment_calibrated: Some("2026-03-02".into()),
        reference_u_um: 0.5,
        out: Some(out),
        no_pdf: false,
    }
}

fn read_verification(out: &Path) -> (serde_json::Value, Verification) {
    let cert: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("verification.json")).unwrap()).unwrap();
    let v = serde_json::from_value(cert["verification"].clone()).unwrap();
    (cert, v)
}

/// Per step, the feed's displacement minus the truth's over the hold's settled lines (the
/// same tags, downward), each line's error: what the truth says the rig's errors are.
fn truth_errors(rec: &Recording, lines: &[FeedLine], plan: &StepPlan) -> Vec<Vec<f64>> {
    let rest: HashMap<u32, f64> = rec.truth[0].tags.iter().map(|t| (t.id, t.center_mm[2])).collect();
    let windows = plan.windows(lines[0].t_ns, lines.last().unwrap().t_ns).unwrap();
    windows
        .iter()
        .map(|&(_, a, b)| {
            let hold: Vec<&FeedLine> = lines.iter().filter(|l| l.t_ns >= a && l.t_ns < b).collect();
            let skip = (hold.len() as f64 * plan.settle_fraction).floor() as usize;
            hold[skip..]
                .iter()
                .map(|l| {
                    let truth = rec.truth.iter().min_by_key(|t| (t.t_ns - l.t_ns).abs()).unwrap();
                    let n = l.tags.len() as f64;
                    let feed: f64 = l.tags.iter().map(|t| -t.disp_mm[2]).sum::<f64>() / n;
                    let true_down: f64 =
                        l.tags.iter().map(|t| rest[&t.id] - truth.tags.iter().find(|x| x.id == t.id).unwrap().center_mm[2]).sum::<f64>()
                            / n;
                    feed - true_down
                })
                .collect()
        })
        .collect()
}

#[test]
fn a_simulated_verification_run_gets_the_class_and_uncertainty_its_truth_supports() {
    let dir = tempfile::tempdir().unwrap();
    let p = SimParams {
        cameras: 2,
        width: 800,
        height: 600,
        frame_sets: 70,
        verify_steps: "0,0.5,1,2,1,0.5,0".into(),
        seed: 43,
        ..SimParams::default()
    };
    let rec_dir = simulate(dir.path(), "verify-run", &p);
    let plan = StepPlan::from_json(&std::fs::read_to_string(rec_dir.join(VERIFY_STEPS_FILE)).unwrap()).unwrap();
    assert_eq!(plan.steps.len(), 7);
    let out = verify::run(&args(&rec_dir, dir.path().join("cert"), None)).unwrap();
    let (cert, v) = read_verification(&out);
    assert_eq!(cert["operator"], "A. Tester");
    assert_eq!(cert["equipment"]["calibrated"], "2026-03-02");
    assert_eq!(cert["rig"]["cameras"].as_array().unwrap().len(), 2);
    assert!(cert["rig"]["config"]["sha256"].as_str().unwrap().len() == 64);
    assert!(out.join("verification.html").is_file() && out.join("recording/frames.jsonl").is_file());
    println!(
        "VERIFY class {:?}, U {:.2} µm, resolution {:.3} µm",
        v.iso9513.class,
        v.uncertainty.expanded_mm * 1e3,
        v.iso9513.resolution_mm * 1e3
    );
    for s in &v.steps {
        println!(
            "VERIFY step {} at {} mm: error {:+.3} µm (SD {:.3} µm, {} lines)",
            s.step,
            s.position_mm,
            s.error_mm * 1e3,
            s.sd_mm.unwrap_or(0.0) * 1e3,
            s.lines
        );
    }
    for r in &v.verdict.reasons {
        println!("VERIFY {r}");
    }

    // The truth's own errors per step give the same step errors (the windows hold what the
    // simulator did) and, by the table, the same class.
    let rec = Recording::open(&rec_dir).unwrap();
    let lines: Vec<FeedLine> =
        std::fs::read_to_string(out.join("feed.jsonl")).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    let errors = truth_errors(&rec, &lines, &plan);
    let mut truth_steps = v.steps.clone();
    for (s, e) in truth_steps.iter_mut().zip(&errors) {
        let mean = e.iter().sum::<f64>() / e.len() as f64;
        assert!((mean - s.error_mm).abs() < 1e-6, "step {}: truth says {mean} mm, verify {} mm", s.step, s.error_mm);
        s.error_mm = mean;
    }
    assert_eq!(iso9513::classify(&truth_steps, v.iso9513.resolution_mm).class, v.iso9513.class);
    assert!(v.iso9513.class.is_some(), "the simulated rig reaches a class: {:?}", v.iso9513);
    assert!(v.vdi2626.zs_net_deflection_mm.unwrap() < 0.005, "a rigid bar shows no net deflection: {:?}", v.vdi2626);
    // U (k = 2) covers a single reading's truth error about 95 % of the time.
    let all: Vec<f64> = errors.concat();
    let within = all.iter().filter(|e| e.abs() <= v.uncertainty.expanded_mm).count() as f64 / all.len() as f64;
    println!("VERIFY {:.0} % of {} readings within U of the truth", within * 100.0, all.len());
    assert!(within >= 0.9, "{within}");

    // A reference that is off at one step: the class moves as the table says. 14 µm at
    // 1 mm is beyond class 1's 10 µm and within class 2's 20 µm; 25 µm beyond class 2.
    for (shift_mm, class) in [(0.014, Some("2")), (0.025, None)] {
        let mut shifted = plan.clone();
        shifted.steps[2].position_mm += shift_mm;
        let steps_file = dir.path().join(format!("shifted-{shift_mm}.json"));
        std::fs::write(&steps_file, serde_json::to_string(&shifted).unwrap()).unwrap();
        let out2 = verify::run(&args(&rec_dir, dir.path().join(format!("cert-{shift_mm}")), Some(steps_file))).unwrap();
        let (_, v2) = read_verification(&out2);
        let mut expected = v.steps.clone();
        expected[2].error_mm -= shift_mm;
        expected[2].nominal_mm += shift_mm;
        assert!((v2.steps[2].error_mm - expected[2].error_mm).abs() < 1e-9);
        assert_eq!(v2.iso9513.class, iso9513::classify(&expected, v.iso9513.resolution_mm).class);
        println!(
            "VERIFY with {} µm injected at step 3: class {:?}, U {:.2} µm",
            shift_mm * 1e3,
            v2.iso9513.class,
            v2.uncertainty.expanded_mm * 1e3
        );
        assert_eq!(v2.iso9513.class.as_deref(), class);
        assert!(v2.uncertainty.expanded_mm > v.uncertainty.expanded_mm);
    }

    // Bad input: no step plan, or a folder that holds something — exit 2, nothing written.
    let bin = env!("CARGO_BIN_EXE_tagdeflect");
    let missing =
        std::process::Command::new(bin).args(["verify", rec_dir.to_str().unwrap(), "--steps", "/nonexistent/steps.json"]).output().unwrap();
    assert_eq!(missing.status.code(), Some(2), "{}", String::from_utf8_lossy(&missing.stderr));
    assert!(String::from_utf8_lossy(&missing.stderr).contains("/nonexistent/steps.json"));
    let taken =
        std::process::Command::new(bin).args(["verify", rec_dir.to_str().unwrap(), "--out", out.to_str().unwrap()]).output().unwrap();
    assert_eq!(taken.status.code(), Some(2));
    assert!(out.join("verification.json").is_file());
}
