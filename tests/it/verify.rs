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
        dir: Some(rec.to_path_buf()),
        live: false,
        config: None,
        duration_s: None,
        type_positions: false,
        hold_s: 10.0,
        reference,
        steps: None,
        reference_from_stroke: false,
        stroke_tolerance_um: 2.0,
        stroke_min_hold_s: 1.0,
        stroke_sign: 1.0,
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

/// A two-part target (the midspan block on a stage, the supports' blocks still): the net
/// deflection and the `net` gauge follow the stage's steps, verified against the UTM's stroke
/// (the crosshead carries the stage) as against the reference file; each step's error is what
/// the truth says.
#[test]
fn the_net_deflection_and_a_gauge_are_verified_against_the_stroke_on_a_staged_target() {
    let dir = tempfile::tempdir().unwrap();
    let p = SimParams {
        cameras: 2,
        width: 800,
        height: 600,
        frame_sets: 70,
        verify_steps: "0,0.5,1,2,1,0.5,0".into(),
        verify_stage_half_width_mm: 100.0,
        seed: 47,
        ..SimParams::default()
    };
    let rec_dir = simulate(dir.path(), "staged-run", &p);
    let rec = Recording::open(&rec_dir).unwrap();
    assert!(rec.config.gauges.iter().any(|g| g.name == "net"), "a staged run's config has the net gauge");
    let run = |out: &str, stroke: bool, gauge: Option<&str>| {
        let mut a = args(&rec_dir, dir.path().join(out), None, None);
        a.reference_from_stroke = stroke;
        // Each step is held 1 s (10 frame sets at 10 fps): the stroke's samples within one
        // span a little less, so the shortest hold is set below it.
        a.stroke_min_hold_s = 0.5;
        a.gauge = gauge.map(String::from);
        read_verification(&verify::run(&a).unwrap())
    };
    let (cert_file, by_file) = run("cert-file", false, None);
    let (cert_stroke, by_stroke) = run("cert-stroke", true, None);
    let (_, by_gauge) = run("cert-gauge", true, Some("net"));
    assert!(cert_stroke["reference"].as_str().unwrap().ends_with("utm.jsonl"), "{}", cert_stroke["reference"]);
    assert!(cert_file["reference"].as_str().unwrap().ends_with(REFERENCE_FILE));
    assert_eq!(by_stroke.quantity, Quantity::NetDeflection);
    assert_eq!(by_gauge.quantity, Quantity::Gauge("net".into()));
    for v in [&by_file, &by_stroke, &by_gauge] {
        let nominal: Vec<f64> = v.steps.iter().map(|s| s.nominal_mm).collect();
        assert_eq!(nominal.len(), 7, "{:?}", v.steps);
        for (got, want) in nominal.iter().zip([0.0, 0.5, 1.0, 2.0, 1.0, 0.5, 0.0]) {
            assert!((got - want).abs() < 1e-9, "{nominal:?}");
        }
    }
    // The truth's net deflection per step gives the same errors (within the lines the two
    // windows share), and the stroke's holds the same figures as the file's to a micrometre.
    let truth = net_truth_errors(&rec, &dir.path().join("cert-stroke/feed.jsonl"), &cert_stroke);
    for ((s, f), t) in by_stroke.steps.iter().zip(&by_file.steps).zip(&truth) {
        assert!((s.error_mm - f.error_mm).abs() < 1e-3, "step {}: stroke {} vs file {}", s.step, s.error_mm, f.error_mm);
        assert!((s.error_mm - t).abs() < 1e-6, "step {}: verify {} mm, truth {t} mm", s.step, s.error_mm);
    }
    for (g, s) in by_gauge.steps.iter().zip(&by_stroke.steps) {
        assert!((g.error_mm - s.error_mm).abs() < 2e-3, "step {}: gauge {} vs net {}", g.step, g.error_mm, s.error_mm);
    }
    println!(
        "VERIFY staged net deflection vs stroke: class {:?}, U {:.2} µm; gauge net: class {:?}, U {:.2} µm",
        by_stroke.iso9513.class,
        by_stroke.uncertainty.expanded_mm * 1e3,
        by_gauge.iso9513.class,
        by_gauge.uncertainty.expanded_mm * 1e3
    );
    // The class is the table's for the errors found (each the truth's, above).
    for v in [&by_stroke, &by_gauge] {
        assert_eq!(iso9513::classify(&v.steps, v.iso9513.resolution_mm).class, v.iso9513.class);
    }
    // No stroke recorded: exit 2 naming the UTM file.
    let bin = env!("CARGO_BIN_EXE_tagdeflect");
    let flat = dir.path().join("flat");
    copy_dir(&rec_dir, &flat);
    let utm = std::fs::read_to_string(flat.join("utm.jsonl")).unwrap();
    let no_stroke: String =
        utm.lines().map(|l| format!("{{\"t_ns\": {}, \"load_kN\": 0}}\n", l.split(['"', ':', ',']).nth(3).unwrap().trim())).collect();
    std::fs::write(flat.join("utm.jsonl"), no_stroke).unwrap();
    let o = std::process::Command::new(bin)
        .args(["verify", flat.to_str().unwrap(), "--reference-from-stroke", "--no-pdf", "--out"])
        .arg(dir.path().join("cert-none"))
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(2), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(
        String::from_utf8_lossy(&o.stderr).contains("utm.jsonl: no UTM sample with a stroke"),
        "{}",
        String::from_utf8_lossy(&o.stderr)
    );
}

/// Per step of `cert`'s plan, the mean over the lines its windows take (after the settle
/// fraction) of the feed's net deflection minus the truth's: the midspan tags' mean true drop
/// minus the support tags' (the truth holds tag centres only).
fn net_truth_errors(rec: &Recording, feed: &Path, cert: &serde_json::Value) -> Vec<f64> {
    let plan: StepPlan = serde_json::from_value(cert["plan"].clone()).unwrap();
    let lines: Vec<FeedLine> = std::fs::read_to_string(feed).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    let ids = |role: TagRole| -> Vec<u32> { rec.config.specimen.tags.iter().filter(|t| t.role == Some(role)).map(|t| t.id).collect() };
    let (mid, sup) = (ids(TagRole::Midspan), ids(TagRole::Support));
    let rest: HashMap<u32, f64> = rec.truth[0].tags.iter().map(|t| (t.id, t.center_mm[2])).collect();
    let mean_drop = |t: &tagdeflect_io::recording::TruthLine, of: &[u32]| {
        of.iter().map(|id| rest[id] - t.tags.iter().find(|x| x.id == *id).unwrap().center_mm[2]).sum::<f64>() / of.len() as f64
    };
    let windows = plan.windows(lines[0].t_ns, lines.last().unwrap().t_ns).unwrap();
    windows
        .iter()
        .map(|&(_, start, end)| {
            let inside: Vec<&FeedLine> =
                lines.iter().filter(|l| l.t_ns >= start && l.t_ns < end && l.net_deflection_mm.is_some()).collect();
            let kept = &inside[(inside.len() as f64 * plan.settle_fraction).floor() as usize..];
            let e: Vec<f64> = kept
                .iter()
                .map(|l| {
                    let t = rec.truth.iter().min_by_key(|t| (t.t_ns - l.t_ns).abs()).unwrap();
                    l.net_deflection_mm.unwrap() - (mean_drop(t, &mid) - mean_drop(t, &sup))
                })
                .collect();
            e.iter().sum::<f64>() / e.len() as f64
        })
        .collect()
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        if e.file_type().unwrap().is_dir() {
            copy_dir(&e.path(), &to.join(e.file_name()));
        } else {
            std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
        }
    }
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

/// `verify --live`: the simulated rig (a staged target stepped 0, 0.5, 1 mm, the simulated UTM
/// over Modbus carrying it) recorded for a stated time into the certificate's folder and
/// verified against the stroke the UTM reported — the whole procedure as on a lab's rig.
#[test]
fn verify_live_records_the_rig_and_verifies_it_against_the_utm_stroke() {
    let dir = tempfile::tempdir().unwrap();
    let params = SimParams {
        cameras: 2,
        width: 640,
        height: 480,
        fps: 5.0,
        frame_sets: 45,
        verify_steps: "0,0.5,1".into(),
        verify_stage_half_width_mm: 100.0,
        subsamples: 2,
        ..SimParams::default()
    };
    let rig = tagdeflect_sim::SimRig::new(&params).unwrap();
    let mut config = tagdeflect::config::Config::from_sim(&rig);
    config.utm = Some(tagdeflect_sim::live_rig::demo_utm());
    let cfg = dir.path().join("rig.toml");
    std::fs::write(&cfg, config.to_toml_string()).unwrap();
    let out = dir.path().join("cert");
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_tagdeflect"))
        .args(["verify", "--live", "--config", cfg.to_str().unwrap(), "--duration-s", "11", "--reference-from-stroke", "--no-pdf"])
        .args(["--stroke-min-hold-s", "1.5", "--operator", "A. Tester", "--out", out.to_str().unwrap()])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(0), "{stderr}");
    assert!(out.join("recording/frames.jsonl").is_file() && out.join("recording/utm.jsonl").is_file());
    let (cert, v) = read_verification(&out);
    assert!(cert["reference"].as_str().unwrap().ends_with("recording/utm.jsonl"), "{}", cert["reference"]);
    let nominal: Vec<f64> = v.steps.iter().map(|s| s.nominal_mm).collect();
    assert_eq!(nominal.len(), 3, "{:?}\n{stderr}", v.steps);
    for (got, want) in nominal.iter().zip([0.0, 0.5, 1.0]) {
        assert!((got - want).abs() < 1e-6, "{nominal:?}");
    }
    // Each step's error is the rig's: a few micrometres on this scene, never a missed step
    // (a busy machine renders fewer frame sets live: a step needs one).
    for s in &v.steps {
        assert!(s.lines >= 1, "step {} has {} lines", s.step, s.lines);
        assert!(s.error_mm.abs() < 0.02, "step {}: error {} mm", s.step, s.error_mm);
    }
    println!("VERIFY live: class {:?}, U {:.2} µm, bias {} µm", v.iso9513.class, v.uncertainty.expanded_mm * 1e3, cert["bias_um"]);
    // --live without --duration-s, and a DIR with --live, are refused before anything runs.
    let bad = std::process::Command::new(env!("CARGO_BIN_EXE_tagdeflect"))
        .args(["verify", "--live", "--config", cfg.to_str().unwrap(), "--reference-from-stroke"])
        .output()
        .unwrap();
    assert_eq!(bad.status.code(), Some(2), "{}", String::from_utf8_lossy(&bad.stderr));
}
