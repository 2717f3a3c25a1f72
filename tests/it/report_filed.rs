//! What a lab files: traceability (inputs hashed, `report verify`), the PDF, identification
//! from config, command line and `test.json`, rounding, the crack entry and the method in force.

use std::fs;
use std::path::{Path, PathBuf};
use std::process::Command;

use crate::common;
use crate::report_lab::*;

#[test]
fn report_json_lists_its_inputs_and_verify_says_what_changed() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = config_with_beam(dir.path(), C1609_BEAM);
    let feed = clean(false, 3).write(&dir.path().join("t"));
    let out = dir.path().join("r");
    let o = report(&feed, &cfg, "astm-c1609", &out, &[]);
    assert!(o.status.success(), "{}", stderr(&o));
    let j = read_json(&out.join("report.json"));
    let files = j["inputs"]["files"].as_array().unwrap();
    let roles: Vec<&str> = files.iter().map(|f| f["role"].as_str().unwrap()).collect();
    assert_eq!(roles, ["feed", "utm", "config"]);
    // The hash is the file's SHA-256 (checked with Python's hashlib).
    let o = Command::new(common::python())
        .arg("-c")
        .arg("import hashlib,sys; print(hashlib.sha256(open(sys.argv[1],'rb').read()).hexdigest())")
        .arg(&feed)
        .output()
        .unwrap();
    assert_eq!(String::from_utf8_lossy(&o.stdout).trim(), files[0]["sha256"].as_str().unwrap());
    assert_eq!(j["inputs"]["software"]["version"], env!("CARGO_PKG_VERSION"));
    let o = tagdeflect(&["report", "verify", out.to_str().unwrap()]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(String::from_utf8_lossy(&o.stdout).contains("every file as recorded"));
    // One changed byte of the UTM stream.
    let utm = dir.path().join("t/utm.jsonl");
    let text = fs::read_to_string(&utm).unwrap();
    fs::write(&utm, text.replacen("\"load_kN\":", "\"load_kN\": ", 1)).unwrap();
    let o = tagdeflect(&["report", "verify", out.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(1), "a change is a finding, not bad input");
    let so = String::from_utf8_lossy(&o.stdout);
    assert!(so.contains("CHANGED  utm") && so.contains("same     feed"), "{so}");
    assert!(stderr(&o).contains("1 change(s)"), "{}", stderr(&o));
}

#[test]
fn the_report_prints_to_pdf_with_page_numbers() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = config_with_beam(dir.path(), C1609_BEAM);
    let feed = clean(false, 4).write(&dir.path().join("t"));
    let out = dir.path().join("r");
    let o = report(&feed, &cfg, "astm-c1609", &out, &["--specimen", "B7", "--edition", "C1609/C1609M-19a", "--pdf-please"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let pdf = out.join("report.pdf");
    assert!(pdf.is_file(), "report.pdf printed by headless Chromium");
    if let Ok(keep) = std::env::var("TAGDEFLECT_KEEP_PDF") {
        fs::copy(&pdf, keep).unwrap();
    }
    assert!(fs::read(&pdf).unwrap().starts_with(b"%PDF"));
    // Its first page as an image: text and the plot's ink are there.
    let png = dir.path().join("page");
    let o = Command::new("pdftoppm")
        .args(["-png", "-r", "60", "-f", "1", "-l", "1"])
        .arg(&pdf)
        .arg(&png)
        .output()
        .expect("pdftoppm (poppler-utils, scripts/setup.sh)");
    assert!(o.status.success(), "{}", stderr(&o));
    let first = fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().path()).find(|p| p.to_string_lossy().contains("page")).unwrap();
    let img = image::open(&first).unwrap().to_rgb8();
    let ink = img.pixels().filter(|p| p[0] < 100 && p[1] < 100 && p[2] < 100).count();
    assert!(ink > 1000, "text on the first page: {ink} px");
    let o = Command::new("pdfinfo").arg(&pdf).output().unwrap();
    let pages: usize = String::from_utf8_lossy(&o.stdout).lines().find_map(|l| l.strip_prefix("Pages:")).unwrap().trim().parse().unwrap();
    assert!(pages >= 2, "{pages} pages");
    let o = Command::new("pdftotext").arg(&pdf).arg("-").output().unwrap();
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(text.contains(&format!("Page 1 of {pages}")) && text.contains("B7"), "header and footer: {}", &text[..text.len().min(600)]);
}

/// Operator, dates, edition, machine, fracture and laboratory from each place they can be
/// given — `[report.lab]`, the command line, `test.json` beside the feed — in `report.json`
/// and in the page's identification table (escaped).
#[test]
fn what_a_lab_files_is_in_report_json_and_report_html() {
    let dir = tempfile::tempdir().unwrap();
    let feed = clean(false, 41).write(&dir.path().join("t"));
    fs::write(
        dir.path().join("t/test.json"),
        serde_json::json!({"id": "T-0042", "specimen": "B12-north", "operator": "J. Json"}).to_string(),
    )
    .unwrap();
    let cfg = config_with_beam(dir.path(), C1609_BEAM);
    let text = fs::read_to_string(&cfg).unwrap();
    fs::write(
        &cfg,
        format!(
            "{text}\n[report]\nstandard = \"astm-c1609\"\nout = \"reports\"\n[report.lab]\nlaboratory = \"Lab & Co <Materials>\"\n\
             machine = \"Instron 5985, S/N 5985K1234, 250 kN cell\"\ncast_date = \"2025-11-03\"\nedition = \"C1609/C1609M-12\"\n"
        ),
    )
    .unwrap();
    // The command line over the config and test.json.
    let out = dir.path().join("r");
    let o = report(
        &feed,
        &cfg,
        "astm-c1609",
        &out,
        &[
            "--operator",
            "A. Tester",
            "--test-date",
            "2026-01-02",
            "--edition",
            "C1609/C1609M-19a",
            "--fracture",
            "within the middle third, 12 mm left of midspan",
        ],
    );
    assert!(o.status.success(), "{}", stderr(&o));
    let j = read_json(&out.join("report.json"));
    let s = &j["specimen"];
    println!("REPORT lab fields: {s} edition {}", j["standard_edition"]);
    assert_eq!(s["id"], "B12-north", "test.json's specimen");
    assert_eq!(s["operator"], "A. Tester", "the command line over test.json");
    assert_eq!(s["cast_date"], "2025-11-03");
    assert_eq!(s["test_date"], "2026-01-02");
    assert_eq!(s["age_days"], 60);
    assert_eq!(j["standard_edition"], "C1609/C1609M-19a", "the command line over [report.lab]");
    assert_eq!(s["machine"], "Instron 5985, S/N 5985K1234, 250 kN cell");
    assert_eq!(s["fracture"], "within the middle third, 12 mm left of midspan");
    assert_eq!(s["laboratory"], "Lab & Co <Materials>");
    let html = fs::read_to_string(out.join("report.html")).unwrap();
    for cell in [
        "<th>Specimen</th><td>B12-north</td>",
        "<th>Operator</th><td>A. Tester</td>",
        "<th>Cast</th><td>2025-11-03</td>",
        "<th>Tested</th><td>2026-01-02</td>",
        "<th>Age</th><td>60 days</td>",
        "<th>Machine</th><td>Instron 5985, S/N 5985K1234, 250 kN cell</td>",
        "<th>Standard</th><td>ASTM C1609 (C1609/C1609M-19a)</td>",
        "<th>Fracture</th><td>within the middle third, 12 mm left of midspan</td>",
        "<th>Laboratory</th><td>Lab &amp; Co &lt;Materials&gt;</td>",
    ] {
        assert!(html.contains(cell), "{cell} in report.html");
    }
    assert!(html.contains("edition C1609/C1609M-19a"), "the edition in the header");
    assert!(!html.contains("Lab & Co <Materials>"), "escaped");

    // Without the command line: test.json's operator, the test date of the feed's first line
    // (2026-01-01), the config's edition; --laboratory over the config's.
    let out = dir.path().join("r2");
    let o = report(&feed, &cfg, "astm-c1609", &out, &["--laboratory", "Materials Lab, Room 2"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let j = read_json(&out.join("report.json"));
    let s = &j["specimen"];
    assert_eq!(s["operator"], "J. Json", "test.json's operator");
    assert_eq!(s["test_date"], "2026-01-01", "the date of the feed's first line");
    assert_eq!(s["age_days"], 59);
    assert_eq!(j["standard_edition"], "C1609/C1609M-12");
    assert_eq!(s["laboratory"], "Materials Lab, Room 2");
    let html = fs::read_to_string(out.join("report.html")).unwrap();
    for cell in
        ["<th>Operator</th><td>J. Json</td>", "<th>Tested</th><td>2026-01-01</td>", "<th>Laboratory</th><td>Materials Lab, Room 2</td>"]
    {
        assert!(html.contains(cell), "{cell} in report.html");
    }
}

/// Every value of a clean report in `report.json` and in the page: σ with exactly two
/// significant digits, the value to the same decimal, and the page showing the same digits.
#[test]
fn report_values_are_rounded_to_two_significant_digits_of_sigma() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = config_with_beam(dir.path(), C1609_BEAM);
    let feed = clean(false, 42).write(&dir.path().join("t"));
    let out = dir.path().join("r");
    let o = report(&feed, &cfg, "astm-c1609", &out, &[]);
    assert!(o.status.success(), "{}", stderr(&o));
    let j = read_json(&out.join("report.json"));
    let html = fs::read_to_string(out.join("report.html")).unwrap();
    let mut checked = Vec::new();
    for (key, q) in j.as_object().unwrap() {
        let (Some(v), Some(s), Some(unit)) = (q["value"].as_f64(), q["sigma"].as_f64(), q["unit"].as_str()) else { continue };
        assert!(s > 0.0, "{key}: σ {s}");
        // The power of ten of σ's second significant digit.
        let e = s.log10().floor() as i32 - 1;
        let d = (-e).max(0) as usize;
        let digits = s / 10f64.powi(e);
        assert!((digits - digits.round()).abs() < 1e-6 && (10.0..=99.0).contains(&digits.round()), "{key}: σ {s} has not two digits");
        // The JSON's numbers are those decimals exactly (nothing after them).
        let (vs, ss) = (format!("{v:.d$}"), format!("{s:.d$}"));
        assert_eq!((vs.parse::<f64>().unwrap(), ss.parse::<f64>().unwrap()), (v, s), "{key}: {v} ± {s} to {d} decimals");
        assert_eq!(ss.trim_start_matches(['0', '.']).replace('.', "").len(), 2, "{key}: σ printed {ss}");
        let row = format!("<td class=\"num\">{vs}</td><td class=\"num\">{ss}</td><td>{unit}</td><td class=\"key\">{key}</td>");
        assert!(html.contains(&row), "{key}: the page shows {row}");
        checked.push(format!("{key} {vs} ± {ss} {unit}"));
    }
    println!("REPORT rounded: {checked:?}");
    for key in ["P1", "delta1", "f1", "Pp", "P600", "P150", "f150", "T150", "RT150"] {
        assert!(checked.iter().any(|c| c.starts_with(&format!("{key} "))), "{key} checked: {checked:?}");
    }
}

/// A calibration file the config names (`[[camera]] calibration`, an OpenCV file and a
/// camera of a Kalibr camchain) is an input of the report: role, path and SHA-256 in
/// `report.json` and the page, and `report verify` sees it change.
#[test]
fn calibration_files_the_config_names_are_hashed_inputs() {
    let dir = tempfile::tempdir().unwrap();
    let feed = clean(false, 43).write(&dir.path().join("t"));
    let sha256 = |p: &Path| {
        let o = Command::new(common::python())
            .arg("-c")
            .arg("import hashlib,sys; print(hashlib.sha256(open(sys.argv[1],'rb').read()).hexdigest())")
            .arg(p)
            .output()
            .unwrap();
        String::from_utf8_lossy(&o.stdout).trim().to_string()
    };
    for (name, file, source, value) in [
        ("opencv", "cam-front.yml", common::root().join("config/centre-calibration.yml"), "cam-front.yml"),
        ("kalibr", "camchain.yaml", common::root().join("tests/fixtures/calibration/kalibr_camchain.yaml"), "camchain.yaml#cam0"),
    ] {
        let d = dir.path().join(name);
        fs::create_dir_all(&d).unwrap();
        let cal = d.join(file);
        fs::copy(&source, &cal).unwrap();
        // The camera's intrinsics from the file instead of inline.
        let cfg = config_with_beam(&d, C1609_BEAM);
        let text: String = fs::read_to_string(&cfg)
            .unwrap()
            .lines()
            .filter(|l| !["fx =", "fy =", "cx =", "cy =", "dist ="].iter().any(|k| l.starts_with(k)))
            .map(|l| format!("{l}\n"))
            .collect();
        // The camera at the calibration's own image size (a calibration of another size is refused).
        let text = if name == "kalibr" { text.replacen("width = 1920\nheight = 1080", "width = 752\nheight = 480", 1) } else { text };
        fs::write(&cfg, text.replacen("[[camera]]\n", &format!("[[camera]]\ncalibration = \"{value}\"\n"), 1)).unwrap();
        let out = d.join("r");
        let o = report(&feed, &cfg, "astm-c1609", &out, &[]);
        assert!(o.status.success(), "{name}: {}", stderr(&o));
        let j = read_json(&out.join("report.json"));
        let files = j["inputs"]["files"].as_array().unwrap();
        println!("REPORT inputs ({name}): {}", j["inputs"]);
        let roles: Vec<&str> = files.iter().map(|f| f["role"].as_str().unwrap()).collect();
        assert_eq!(roles, ["feed", "utm", "config", "calibration"], "{name}");
        let c = &files[3];
        assert_eq!(Path::new(c["path"].as_str().unwrap()), cal, "{name}: the file itself");
        let hash = sha256(&cal);
        assert_eq!(hash.len(), 64);
        assert_eq!(c["sha256"], hash.as_str(), "{name}: its SHA-256");
        let html = fs::read_to_string(out.join("report.html")).unwrap();
        assert!(
            html.contains(&format!("<tr><td>calibration</td><td><code>{}</code></td><td class=\"key\">{hash}</td></tr>", cal.display())),
            "{name}: the page's inputs"
        );
        let o = tagdeflect(&["report", "verify", out.to_str().unwrap()]);
        assert!(o.status.success(), "{name}: {}", stderr(&o));
        assert!(String::from_utf8_lossy(&o.stdout).contains("every file as recorded"), "{name}");
        // The calibration changed after the report.
        fs::write(&cal, fs::read_to_string(&cal).unwrap() + "\n# edited\n").unwrap();
        let o = tagdeflect(&["report", "verify", out.to_str().unwrap()]);
        assert_eq!(o.status.code(), Some(1), "{name}");
        let so = String::from_utf8_lossy(&o.stdout);
        assert!(so.contains(&format!("CHANGED  calibration {}", cal.display())) && so.contains("same     config"), "{name}: {so}");
    }
}

/// A test folder's `test.json` as the daemon writes it, with `extra` keys (crack, method).
fn test_folder(dir: &Path, cmod: bool, standard: &str, extra: serde_json::Value) -> PathBuf {
    clean(cmod, 7).write(dir);
    let mut rec = serde_json::json!({"id": "t", "specimen": "S1", "operator": "A. Tester", "standard": standard,
        "started_t_ns": T0, "events": [{"kind": "start", "t_ns": T0}], "lines": 1, "utm_samples": 1, "sha256": {}});
    rec.as_object_mut().unwrap().extend(extra.as_object().unwrap().clone());
    fs::write(dir.join("test.json"), rec.to_string()).unwrap();
    dir.to_path_buf()
}

/// The operator's crack entry is part of the validity of a C1609/C1856 test (outside the
/// middle third: invalid with that reason; no entry: a QC warning, still valid), not of an EN
/// 14651 test; and the report states the method in force — reviewed, not reviewed, or the
/// built-in rules with the source of each — instead of a blanket disclaimer.
#[test]
fn the_crack_entry_and_the_method_in_force_reach_the_report() {
    let dir = tempfile::tempdir().unwrap();
    let method = |review: bool| {
        let mut m = serde_json::json!({"name": "C1609-19", "version": 2, "standard": "astm-c1609", "sha256": "ab".repeat(32)});
        if review {
            m["review"] = serde_json::json!({"by": "J. Reviewer", "at": "2026-12-06T10:00:00Z", "meaning": "checked against the lab's copy of C1609-19"});
        }
        m
    };
    // The crack entries as the daemon writes them (it decides inside/outside from the span when
    // the entry is made, and stamps it).
    let cases = [
        (
            "inside",
            false,
            "astm-c1609",
            serde_json::json!({"crack": {"position_mm": 20.0, "inside_middle_third": true, "t_ns": 1}, "method": method(true)}),
        ),
        (
            "outside",
            false,
            "astm-c1609",
            serde_json::json!({"crack": {"position_mm": -110.0, "inside_middle_third": false, "t_ns": 1}, "method": method(false)}),
        ),
        ("none", false, "astm-c1609", serde_json::json!({})),
        ("en", true, "en-14651", serde_json::json!({"crack": {"position_mm": 120.0, "inside_middle_third": false, "t_ns": 1}})),
    ];
    for (name, cmod, standard, extra) in cases {
        let folder = test_folder(&dir.path().join(name), cmod, standard, extra);
        let cfg = config_with_beam(dir.path(), if cmod { EN_BEAM } else { C1609_BEAM });
        let out = dir.path().join(format!("{name}-r"));
        let o = tagdeflect(&[
            "report",
            folder.to_str().unwrap(),
            "--config",
            cfg.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--no-pdf",
        ]);
        assert!(o.status.success(), "{name}: {}", stderr(&o));
        let j = read_json(&out.join("report.json"));
        let html = fs::read_to_string(out.join("report.html")).unwrap();
        let reasons = invalid_reasons(&j);
        let crack_warning = qc_warnings(&j).iter().any(|w| w.contains("crack position not entered"));
        let statement = j["method_statement"].as_str().unwrap().to_string();
        println!("REPORT crack {name}: valid {} reasons {reasons:?}; {statement}", j["valid"]);
        assert!(html.contains(&statement.replace('\'', "&#39;")) || html.contains(&statement), "{name}: the statement in the HTML");
        assert!(!html.contains("not checked against") && !html.contains("authors of this software"), "{name}: no blanket sentence");
        assert!(html.contains("Rules and their sources"), "{name}");
        match name {
            "inside" => {
                assert_eq!(j["valid"], true, "{reasons:?}");
                assert_eq!(
                    statement,
                    "Method C1609-19 v2, reviewed by J. Reviewer on 2026-12-06 (checked against the lab's copy of C1609-19)."
                );
                assert_eq!(j["method"]["name"], "C1609-19");
                assert!(j["specimen"]["fracture"].as_str().unwrap().starts_with("inside the middle third"), "{}", j["specimen"]);
            }
            "outside" => {
                assert_eq!(j["valid"], false);
                assert!(reasons.iter().any(|r| r.contains("fracture outside the middle third") && r.contains("-110 mm")), "{reasons:?}");
                assert_eq!(statement, "Method C1609-19 v2, not reviewed by the lab.");
            }
            "none" => {
                assert_eq!(j["valid"], true, "{reasons:?}");
                assert!(crack_warning, "{:?}", qc_warnings(&j));
                assert!(statement.starts_with("No test method was named: the built-in rules of"), "{statement}");
                assert!(html.contains("ASTM C1609-19 §9 Calculation, Eq. 1"), "each rule's source listed");
            }
            _ => {
                assert_eq!(j["valid"], true, "EN 14651 ignores the crack entry: {reasons:?}");
                assert!(!crack_warning);
                assert!(html.contains("EN 14651:2005+A1:2007 §9.2, Eq. 2"));
            }
        }
    }
}

/// The specimen's row of the lab's table, as test.json carries it (`specimen_info`: readings,
/// cast date and age, mix, fibre and dosage, client, project), reaches report.json's
/// `specimen.info` whole and the page's Specimen section; test.json's measured means are the
/// dimensions used; a method naming `report_fields` has the page show only those details,
/// report.json still the whole row.
#[test]
fn the_specimen_s_row_reaches_report_json_and_the_page() {
    let dir = tempfile::tempdir().unwrap();
    let info = serde_json::json!({"id": "S1", "readings": {"width_mm": [150.2, 150.6], "depth_mm": [149.8, 150.0]},
        "cast_date": "2026-11-01", "age_days": 35, "mix": "C40/50 <pump>", "fibre": "hooked steel 60/35", "dosage_kg_m3": 40.0,
        "client": "ACME", "project": "Bridge 7"});
    let extra = serde_json::json!({"specimen_info": info, "measured": {"width_mm": 150.4, "depth_mm": 149.9}});
    let folder = test_folder(&dir.path().join("t"), false, "astm-c1609", extra);
    let cfg = config_with_beam(dir.path(), C1609_BEAM);
    let out = dir.path().join("r");
    let o =
        tagdeflect(&["report", folder.to_str().unwrap(), "--config", cfg.to_str().unwrap(), "--out", out.to_str().unwrap(), "--no-pdf"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let j = read_json(&out.join("report.json"));
    assert_eq!(j["specimen"]["info"], info, "the row whole in report.json");
    assert_eq!((j["specimen"]["width_mm"].as_f64(), j["specimen"]["depth_mm"].as_f64()), (Some(150.4), Some(149.9)));
    assert_eq!(j["specimen"]["dimension_sources"]["width_mm"], "test.json");
    let html = fs::read_to_string(out.join("report.html")).unwrap();
    for shown in [
        "<b>Mix:</b> C40/50 &lt;pump&gt;",
        "<b>Fibre:</b> hooked steel 60/35",
        "<b>Dosage:</b> 40 kg/m³",
        "<b>Client:</b> ACME",
        "<b>Project:</b> Bridge 7",
        "<b>width_mm:</b> 150.2, 150.6 (their mean measured)",
    ] {
        assert!(html.contains(shown), "{shown} on the page");
    }
    assert!(html.contains("<th>Cast</th><td>2026-11-01</td>"), "the cast date in the identification");

    // A method naming the details its report shows (`report_fields`): the page shows those and
    // the standard's identification, report.json keeps the whole row.
    let text = tagdeflect_core::method::SHIPPED[0].1.replace("C1609-19", "C1609-ROW");
    let text = format!("report_fields = [\"client\", \"project\"]\n{text}");
    fs::create_dir_all(dir.path().join("methods")).unwrap();
    fs::write(dir.path().join("methods/C1609-ROW.toml"), &text).unwrap();
    let sha = tagdeflect_core::method::library::sha256_hex(text.as_bytes());
    let version = tagdeflect_core::method::Method::parse(&text).unwrap().version;
    let method = serde_json::json!({"name": "C1609-ROW", "version": version, "standard": "astm-c1609", "sha256": sha});
    let extra = serde_json::json!({"specimen_info": info, "measured": {"width_mm": 150.4, "depth_mm": 149.9}, "method": method});
    let folder = test_folder(&dir.path().join("m"), false, "astm-c1609", extra);
    let out = dir.path().join("rm");
    let o =
        tagdeflect(&["report", folder.to_str().unwrap(), "--config", cfg.to_str().unwrap(), "--out", out.to_str().unwrap(), "--no-pdf"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let j = read_json(&out.join("report.json"));
    assert_eq!(j["method"]["name"], "C1609-ROW", "the method applied: {}", j["qc"]);
    assert_eq!(j["specimen"]["info"], info, "the row whole in report.json whatever the method shows");
    let html = fs::read_to_string(out.join("report.html")).unwrap();
    assert!(html.contains("<b>Client:</b> ACME; <b>Project:</b> Bridge 7</p>"), "the method's details on the page");
    for hidden in ["<b>Mix:</b>", "<b>Fibre:</b>", "<b>Dosage:</b>", "<b>width_mm:</b>"] {
        assert!(!html.contains(hidden), "{hidden} not on the page of a method that does not name it");
    }
    assert!(html.contains("<th>Cast</th><td>2026-11-01</td>"), "the standard's identification whatever the method");
}
