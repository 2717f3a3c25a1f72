//! `tagdeflect verify` on a simulated verification run: the class and the uncertainty its
//! truth supports, a step error injected moving the class as ISO 9513's table says, and bad
//! input refused with exit 2.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use tagdeflect::commands::verify::{self, VerifyArgs};
use tagdeflect::config::Recording;
use tagdeflect_core::feed::FeedLine;
use tagdeflect_core::rig::TagRole;
use tagdeflect_sim::SimParams;
use tagdeflect_verify::{iso9513, reference, Quantity, StepPlan, Verification, REFERENCE_FILE};

use crate::common::simulate;

fn args(rec: &Path, out: PathBuf, reference: Option<PathBuf>, tag: Option<u32>) -> VerifyArgs {
    VerifyArgs {
        dir: rec.to_path_buf(),
        reference,
        steps: None,
        gauge: None,
        tag,
        all_tags: false,
        operator: Some("A. Tester".into()),
        equipment: Some("micrometer stage MS-25 #1187".into()),
        equipment_calibrated: Some("2026-03-02".into()),
        reference_u_um: 0.5,
        out: Some(out),
        no_pdf: false,
    }
}

/// SPEC's keys of `verification.json` are there with their types.
fn assert_spec_keys(cert: &serde_json::Value, reference: &Path) {
    let class = cert["class_iso9513"].as_str().unwrap();
    assert!(["0.2", "0.5", "1", "2", "none"].contains(&class), "{class}");
    for key in ["bias_um", "resolution_um", "u_k2_mm"] {
        assert!(cert[key].as_f64().unwrap() >= 0.0, "{key}: {}", cert[key]);
    }
    let steps = cert["steps"].as_array().unwrap();
    assert!(!steps.is_empty());
    for s in steps {
        let (r, m, e) = (s["reference_mm"].as_f64().unwrap(), s["measured_mm"].as_f64().unwrap(), s["error_um"].as_f64().unwrap());
        assert!(((m - r) * 1e3 - e).abs() < 1e-6, "{s}");
    }
    let largest = steps.iter().map(|s| s["error_um"].as_f64().unwrap().abs()).fold(0.0, f64::max);
    assert!((cert["bias_um"].as_f64().unwrap() - largest).abs() < 1e-9, "bias_um is the largest |error|");
    let inputs = cert["inputs"].as_object().unwrap();
    assert_eq!(inputs[&reference.display().to_string()].as_str().unwrap().len(), 64, "{inputs:?}");
    assert!(inputs.keys().any(|k| k.ends_with("frames.jsonl")));
    let date = cert["date"].as_str().unwrap();
    assert!(chrono::NaiveDate::parse_from_str(date, "%Y-%m-%d").is_ok(), "{date}");
}

/// The reference file with `shift_mm` added to the lines of hold `hold` (from 0).
fn shifted_reference(text: &str, hold: usize, shift_mm: f64) -> String {
    let points = reference::parse_reference(text).unwrap();
    let holds = reference::holds(&points);
    let h = holds[hold];
    points
        .iter()
        .map(|p| {
            let d = if p.t_ns >= h.first_ns && p.t_ns <= h.last_ns { p.displacement_mm + shift_mm } else { p.displacement_mm };
            format!("{{\"t_ns\": {}, \"displacement_mm\": {d}}}\n", p.t_ns)
        })
        .collect()
}

fn read_verification(out: &Path) -> (serde_json::Value, Verification) {
    let cert: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("verification.json")).unwrap()).unwrap();
    let v = serde_json::from_value(cert["verification"].clone()).unwrap();
    (cert, v)
}

/// Per step, tag `id`'s feed displacement minus the truth's over the hold's settled lines
/// (downward), each line's error: what the truth says the rig's errors are.
fn truth_errors(rec: &Recording, lines: &[FeedLine], plan: &StepPlan, id: u32) -> Vec<Vec<f64>> {
    let rest: HashMap<u32, f64> = rec.truth[0].tags.iter().map(|t| (t.id, t.center_mm[2])).collect();
    let windows = plan.windows(lines[0].t_ns, lines.last().unwrap().t_ns).unwrap();
    windows
        .iter()
        .map(|&(_, a, b)| {
            let hold: Vec<&FeedLine> = lines.iter().filter(|l| l.t_ns >= a && l.t_ns < b).collect();
            let skip = (hold.len() as f64 * plan.settle_fraction).floor() as usize;
            hold[skip..]
                .iter()
                .filter_map(|l| {
                    let truth = rec.truth.iter().min_by_key(|t| (t.t_ns - l.t_ns).abs()).unwrap();
                    let feed = -l.tags.iter().find(|t| t.id == id)?.disp_mm[2];
                    Some(feed - (rest[&id] - truth.tags.iter().find(|x| x.id == id).unwrap().center_mm[2]))
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
    let reference_file = rec_dir.join(REFERENCE_FILE);
    let reference_text = std::fs::read_to_string(&reference_file).unwrap();
    assert_eq!(reference::holds(&reference::parse_reference(&reference_text).unwrap()).len(), 7);
    let rec = Recording::open(&rec_dir).unwrap();
    // The simulated bar moves all tags as one: its net deflection stays ~0, so a tag is
    // verified — the first midspan tag, the one a deflection is about.
    let id = rec.config.specimen.tags.iter().find(|t| t.role == Some(TagRole::Midspan)).unwrap().id;
    let out = verify::run(&args(&rec_dir, dir.path().join("cert"), Some(reference_file.clone()), Some(id))).unwrap();
    let (cert, v) = read_verification(&out);
    assert_spec_keys(&cert, &reference_file);
    assert_eq!(cert["steps"].as_array().unwrap().len(), 7);
    assert_eq!(v.quantity, Quantity::Tag(id));
    assert_eq!(cert["class_iso9513"], v.iso9513.class.as_deref().unwrap_or("none"));
    assert!((cert["u_k2_mm"].as_f64().unwrap() - v.uncertainty.expanded_mm).abs() < 1e-12);
    assert_eq!(cert["operator"], "A. Tester");
    assert_eq!(cert["equipment"]["calibrated"], "2026-03-02");
    assert_eq!(cert["rig"]["cameras"].as_array().unwrap().len(), 2);
    assert!(cert["rig"]["config"]["sha256"].as_str().unwrap().len() == 64);
    assert!(out.join("verification.html").is_file() && out.join("recording/frames.jsonl").is_file());
    println!(
        "VERIFY tag {id}: class {:?}, U {:.2} µm, resolution {:.3} µm",
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

    // The truth's own errors per step give the same step errors (the holds' windows hold
    // what the simulator did) and, by the table, the same class.
    let plan: StepPlan = serde_json::from_value(cert["plan"].clone()).unwrap();
    let lines: Vec<FeedLine> =
        std::fs::read_to_string(out.join("feed.jsonl")).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    let errors = truth_errors(&rec, &lines, &plan, id);
    let mut truth_steps = v.steps.clone();
    for (s, e) in truth_steps.iter_mut().zip(&errors) {
        assert_eq!(e.len(), s.lines, "step {}", s.step);
        let mean = e.iter().sum::<f64>() / e.len() as f64;
        assert!((mean - s.error_mm).abs() < 1e-6, "step {}: truth says {mean} mm, verify {} mm", s.step, s.error_mm);
        s.error_mm = mean;
    }
    assert_eq!(iso9513::classify(&truth_steps, v.iso9513.resolution_mm).class, v.iso9513.class);
    for (tag, st) in &v.static_figures.tags {
        println!("VERIFY tag {tag} at rest: SD {:.3} µm", st.sd_mm.unwrap_or(0.0) * 1e3);
    }
    assert!(v.vdi2626.zs_net_deflection_mm.unwrap() < 0.005, "a rigid bar shows no net deflection: {:?}", v.vdi2626);
    // U (k = 2) covers a single reading's truth error about 95 % of the time.
    let all: Vec<f64> = errors.concat();
    let within = all.iter().filter(|e| e.abs() <= v.uncertainty.expanded_mm).count() as f64 / all.len() as f64;
    println!("VERIFY {:.0} % of {} readings within U of the truth", within * 100.0, all.len());
    assert!(within >= 0.9, "{within}");

    // A reference that is off at one hold moves the tag's error by as much and its class
    // as the table says.
    let file = dir.path().join("shifted-tag.jsonl");
    std::fs::write(&file, shifted_reference(&reference_text, 2, 0.025)).unwrap();
    let (cert2, v2) = read_verification(&verify::run(&args(&rec_dir, dir.path().join("cert-tag"), Some(file.clone()), Some(id))).unwrap());
    assert_spec_keys(&cert2, &file);
    let mut expected = v.steps.clone();
    (expected[2].error_mm, expected[2].nominal_mm) = (expected[2].error_mm - 0.025, expected[2].nominal_mm + 0.025);
    assert!((v2.steps[2].error_mm - expected[2].error_mm).abs() < 1e-9);
    assert!((cert2["steps"][2]["error_um"].as_f64().unwrap() - expected[2].error_mm * 1e3).abs() < 1e-6);
    assert_eq!(v2.iso9513.class, iso9513::classify(&expected, v.iso9513.resolution_mm).class);
    assert!(v2.uncertainty.expanded_mm > v.uncertainty.expanded_mm);

    // The mean of the tags (extension --all-tags) reaches a class on this rig; 14 µm injected
    // at 1 mm is beyond class 1's 10 µm and within class 2's 20 µm; 25 µm beyond class 2.
    let all_tags = |out: &str, reference: PathBuf| {
        let mut a = args(&rec_dir, dir.path().join(out), Some(reference), None);
        a.all_tags = true;
        read_verification(&verify::run(&a).unwrap())
    };
    let (_, base) = all_tags("cert-all", reference_file.clone());
    println!("VERIFY mean of the tags: class {:?}, U {:.2} µm", base.iso9513.class, base.uncertainty.expanded_mm * 1e3);
    assert!(base.iso9513.class.is_some(), "the mean of the simulated rig's tags reaches a class: {:?}", base.iso9513);
    for (shift_mm, class) in [(0.014, Some("2")), (0.025, None)] {
        let file = dir.path().join(format!("shifted-{shift_mm}.jsonl"));
        std::fs::write(&file, shifted_reference(&reference_text, 2, shift_mm)).unwrap();
        let (cert2, v2) = all_tags(&format!("cert-{shift_mm}"), file);
        let mut expected = base.steps.clone();
        (expected[2].error_mm, expected[2].nominal_mm) = (expected[2].error_mm - shift_mm, expected[2].nominal_mm + shift_mm);
        assert!((v2.steps[2].error_mm - expected[2].error_mm).abs() < 1e-9);
        assert_eq!(v2.iso9513.class, iso9513::classify(&expected, base.iso9513.resolution_mm).class);
        println!(
            "VERIFY with {} µm injected at step 3: class {:?}, U {:.2} µm",
            shift_mm * 1e3,
            v2.iso9513.class,
            v2.uncertainty.expanded_mm * 1e3
        );
        assert_eq!(v2.iso9513.class.as_deref(), class);
        assert_eq!(cert2["class_iso9513"], class.unwrap_or("none"));
        assert!(v2.uncertainty.expanded_mm > base.uncertainty.expanded_mm);
    }

    // The default quantity, the net deflection, against a reference of zero over the whole
    // run while the bar moves: VDI/VDE 2626's ZS check as a verification of one hold.
    let zeros: String = reference::parse_reference(&reference_text)
        .unwrap()
        .iter()
        .map(|p| format!("{{\"t_ns\": {}, \"displacement_mm\": 0}}\n", p.t_ns))
        .collect();
    let zero_file = dir.path().join("zero.jsonl");
    std::fs::write(&zero_file, zeros).unwrap();
    let out3 = verify::run(&args(&rec_dir, dir.path().join("cert-zs"), Some(zero_file.clone()), None)).unwrap();
    let (cert3, v3) = read_verification(&out3);
    assert_spec_keys(&cert3, &zero_file);
    assert_eq!(v3.quantity, Quantity::NetDeflection);
    assert_eq!(v3.steps.len(), 1);
    let settled = &lines[(lines.len() as f64 * 0.3).floor() as usize..];
    let net: Vec<f64> = settled.iter().filter_map(|l| l.net_deflection_mm).collect();
    let net_mean = net.iter().sum::<f64>() / net.len() as f64;
    assert!((cert3["steps"][0]["measured_mm"].as_f64().unwrap() - net_mean).abs() < 1e-9);
    assert!(cert3["bias_um"].as_f64().unwrap() < 5.0, "the rigid bar's net deflection stays near zero: {cert3}");
    println!("VERIFY net deflection held at 0 (ZS): class {}, bias {:.2} µm", cert3["class_iso9513"], cert3["bias_um"]);

    // Without --reference the recording's own reference.jsonl is used.
    let out4 = verify::run(&args(&rec_dir, dir.path().join("cert-default"), None, Some(id))).unwrap();
    let (cert4, _) = read_verification(&out4);
    assert_eq!(cert4["steps"], cert["steps"]);

    // Bad input: a missing or malformed reference, or a folder that holds something — exit
    // 2 naming it, nothing written.
    let bin = env!("CARGO_BIN_EXE_tagdeflect");
    let rec_arg = rec_dir.to_str().unwrap();
    let missing = std::process::Command::new(bin).args(["verify", rec_arg, "--reference", "/nonexistent/ref.jsonl"]).output().unwrap();
    assert_eq!(missing.status.code(), Some(2), "{}", String::from_utf8_lossy(&missing.stderr));
    assert!(String::from_utf8_lossy(&missing.stderr).contains("/nonexistent/ref.jsonl"));
    let bad_file = dir.path().join("bad.jsonl");
    std::fs::write(&bad_file, "{\"t_ns\": 1, \"displacement_mm\": 0}\n{\"t_ns\": 2, \"displacement_mm\": \"one\"}\n").unwrap();
    let bad_out = dir.path().join("cert-bad");
    let bad = std::process::Command::new(bin)
        .args(["verify", rec_arg, "--reference", bad_file.to_str().unwrap(), "--out", bad_out.to_str().unwrap()])
        .output()
        .unwrap();
    assert_eq!(bad.status.code(), Some(2), "{}", String::from_utf8_lossy(&bad.stderr));
    assert!(
        String::from_utf8_lossy(&bad.stderr).contains(&format!("{}:2:", bad_file.display())),
        "{}",
        String::from_utf8_lossy(&bad.stderr)
    );
    assert!(!bad_out.exists());
    let taken = std::process::Command::new(bin).args(["verify", rec_arg, "--out", out.to_str().unwrap()]).output().unwrap();
    assert_eq!(taken.status.code(), Some(2));
    assert!(out.join("verification.json").is_file());
    verification_in_force_is_checked(&rec_dir, &out.join("verification.json"), dir.path());
}

/// `check --config` names the verification in force (class, date, id), and says it is stale
/// once the config's geometry changed since the certificate; a certificate that cannot be read
/// is bad input (exit 2) naming it.
fn verification_in_force_is_checked(rec_dir: &Path, certificate: &Path, dir: &Path) {
    let bin = env!("CARGO_BIN_EXE_tagdeflect");
    let mut cfg: toml::Table = std::fs::read_to_string(rec_dir.join("tagdeflect.toml")).unwrap().parse().unwrap();
    let mut section = toml::Table::new();
    section.insert("certificate".into(), certificate.display().to_string().into());
    section.insert("valid_days".into(), 30.into());
    cfg.insert("verification".into(), section.into());
    // The live simulated rig runs a test's load, not the recorded verification's steps.
    cfg["sim"].as_table_mut().unwrap().remove("verify_steps");
    let check = |cfg: &toml::Table, name: &str| {
        let path = dir.join(name);
        std::fs::write(&path, toml::to_string(cfg).unwrap()).unwrap();
        let o = std::process::Command::new(bin).args(["check", "--config", path.to_str().unwrap()]).output().unwrap();
        (o.status.code(), String::from_utf8_lossy(&o.stdout).into_owned() + &String::from_utf8_lossy(&o.stderr))
    };
    let (code, out) = check(&cfg, "in-force.toml");
    assert_eq!(code, Some(0), "{out}");
    let cert: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(certificate).unwrap()).unwrap();
    let line = out.lines().find(|l| l.contains("verification ")).unwrap_or_else(|| panic!("no verification line: {out}"));
    assert!(line.contains("in force") && line.contains(&format!("class {}", cert["class_iso9513"].as_str().unwrap())), "{line}");
    // A specimen tag added to the config: the geometry the certificate was made on is gone.
    let specimen = cfg["specimen"].as_table_mut().unwrap();
    let mut extra = toml::Table::new();
    extra.insert("id".into(), 586.into());
    specimen["tag"].as_array_mut().unwrap().push(extra.into());
    let (code, out) = check(&cfg, "changed.toml");
    assert_eq!(code, Some(0), "a stale verification is a warning: {out}");
    assert!(out.contains("STALE") && out.contains("geometry changed"), "{out}");
    // An unreadable certificate: exit 2, named.
    cfg["verification"].as_table_mut().unwrap().insert("certificate".into(), dir.join("none.json").display().to_string().into());
    let (code, out) = check(&cfg, "missing.toml");
    assert_eq!(code, Some(2), "{out}");
    assert!(out.contains("none.json"), "{out}");
}
