//! Series as the standards need them: C1609 means, SD and CoV; folder names that `test.json`
//! cannot steer; EN 14651 with exclusions, characteristic values and the fib class.

use std::fs;

use crate::report_lab::*;

#[test]
fn a_series_of_three_specimens_with_mean_sd_and_cov() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = config_with_beam(dir.path(), C1609_BEAM);
    let mut folders = Vec::new();
    for (k, name) in ["B1", "B2", "B3"].iter().enumerate() {
        let mut s = clean(false, 10 + k as u64);
        s.dt_s = 1.0;
        s.utm_hz = 5.0;
        // Specimens differ: the law scaled by 0.9, 1.0, 1.1 (a first peak of 36, 40, 44 kN).
        s.law = [|x| 0.9 * softening(x), softening, |x| 1.1 * softening(x)][k];
        let d = dir.path().join(name);
        s.write(&d);
        fs::write(d.join("test.json"), serde_json::json!({"id": name, "specimen": name, "operator": "A. Tester"}).to_string()).unwrap();
        folders.push(d);
    }
    let out = dir.path().join("series");
    let mut a = vec!["report", "--series"];
    a.extend(folders.iter().map(|f| f.to_str().unwrap()));
    a.extend(["--config", cfg.to_str().unwrap(), "--standard", "astm-c1609", "--out", out.to_str().unwrap(), "--no-pdf"]);
    let o = tagdeflect(&a);
    assert!(o.status.success(), "{}", stderr(&o));
    let j = read_json(&out.join("series.json"));
    let sp = j["specimens"].as_array().unwrap();
    assert_eq!(sp.len(), 3);
    let p1: Vec<f64> = sp.iter().map(|s| s["P1"]["value"].as_f64().unwrap()).collect();
    let names: Vec<&str> = sp.iter().map(|s| s["specimen"].as_str().unwrap()).collect();
    assert_eq!(names, ["B1", "B2", "B3"], "the ids from each folder's test.json");
    let mean = p1.iter().sum::<f64>() / 3.0;
    let sd = (p1.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / 2.0).sqrt();
    let st = &j["statistics"]["P1"];
    // The statistics of the unrounded values; the specimens' values are rounded to their σ.
    let s1 = sp[0]["P1"]["sigma"].as_f64().unwrap();
    assert!((st["mean"].as_f64().unwrap() - mean).abs() <= s1 && (st["sd"].as_f64().unwrap() - sd).abs() <= s1, "{st}");
    let cov = st["cov_pct"].as_f64().unwrap();
    assert!((cov - 100.0 * st["sd"].as_f64().unwrap() / st["mean"].as_f64().unwrap()).abs() < 1e-9, "{cov}");
    assert!((mean - 40.0).abs() < 0.3 && (sd - 4.0).abs() < 0.3, "P1 {p1:?}");
    // C1609's results: the means of f1, f600, f150 and T150 over the three, each with its n
    // (the law scaled by 0.9, 1.0, 1.1: each mean is B2's value, the SD a tenth of it).
    for key in ["f1", "f600", "f150", "T150"] {
        let v: Vec<f64> = sp.iter().map(|s| s[key]["value"].as_f64().unwrap_or_else(|| panic!("{key}: {s}"))).collect();
        let sigma = sp.iter().map(|s| s[key]["sigma"].as_f64().unwrap()).fold(0.0, f64::max);
        let mean = v.iter().sum::<f64>() / 3.0;
        let st = &j["statistics"][key];
        assert_eq!(st["n"], 3, "{key}: {st}");
        let m = st["mean"].as_f64().unwrap_or_else(|| panic!("{key}: no mean: {}", j["statistics"]));
        assert!((m - mean).abs() <= sigma, "{key}: mean {m}, of the specimens' values {v:?} {mean}");
        assert!((m - v[1]).abs() <= 0.01 * v[1] && (st["sd"].as_f64().unwrap() - 0.1 * v[1]).abs() <= 0.01 * v[1], "{key}: {st} {v:?}");
    }
    for n in ["B1", "B2", "B3"] {
        assert!(out.join(n).join("report.html").is_file());
    }
    let html = fs::read_to_string(out.join("series.html")).unwrap();
    assert!(html.contains("<svg") && html.contains("CoV"));
}

#[test]
fn a_series_names_its_folders_safely_whatever_test_json_says() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = config_with_beam(dir.path(), C1609_BEAM);
    let abs = dir.path().join("abs");
    let mut folders = Vec::new();
    for (k, name) in ["../../x", abs.to_str().unwrap(), ".."].iter().enumerate() {
        let mut s = clean(false, 20 + k as u64);
        s.dt_s = 1.0;
        s.utm_hz = 5.0;
        let d = dir.path().join("in").join(format!("t{k}"));
        s.write(&d);
        fs::write(d.join("test.json"), serde_json::json!({"id": format!("t{k}"), "specimen": name}).to_string()).unwrap();
        folders.push(d);
    }
    let out = dir.path().join("a").join("b").join("series");
    let mut a = vec!["report", "--series"];
    a.extend(folders.iter().map(|f| f.to_str().unwrap()));
    a.extend(["--config", cfg.to_str().unwrap(), "--standard", "astm-c1609", "--out", out.to_str().unwrap(), "--no-pdf"]);
    let o = tagdeflect(&a);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stderr(&o).contains("not a safe folder name"), "{}", stderr(&o));
    assert!(!dir.path().join("a").join("x").exists() && !abs.exists(), "nothing written outside --out");
    let mut made: Vec<String> = fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap())
        .filter(|e| e.path().is_dir())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .collect();
    made.sort();
    assert_eq!(made.len(), 3, "{made:?}");
    for m in &made {
        assert!(!m.starts_with('.') && !m.contains('/'), "{m}");
        assert!(out.join(m).join("report.html").is_file(), "{m}");
    }
    assert!(made.contains(&"___.._x".to_string()), "{made:?}");
    // The series still names each specimen as test.json does.
    let names: Vec<String> = read_json(&out.join("series.json"))["specimens"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["specimen"].as_str().unwrap().to_string())
        .collect();
    assert_eq!(names[0], "../../x");
}

/// An EN 14651 series as the standard needs it: a specimen the lab excludes (`--exclude`) and
/// one that is not a valid test are listed with their reasons and left out; n used; fR1…fR4
/// means with their characteristic values f_Rk = f_Rm − k_n·s (EN 1990 Table D1, k_3 = 3.37)
/// and the fib Model Code 2010 class; `series.csv`; reported as EN 14651. A series mixing
/// standards is refused, naming the folders of each, unless --standard picks one.
#[test]
fn an_en_14651_series_with_exclusions_characteristic_values_and_its_class() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = config_with_beam(dir.path(), EN_BEAM);
    let mut folders = Vec::new();
    for (k, name) in ["E1", "E2", "E3", "E4", "E5"].iter().enumerate() {
        let d = dir.path().join(name);
        let mut s = clean(true, 30 + k as u64);
        s.dt_s = 1.0;
        s.utm_hz = 5.0;
        s.law = [|x| 0.9 * notched(x), notched, |x| 1.1 * notched(x), notched, notched][k];
        if k == 4 {
            s.x_end = 2.0;
        }
        s.write(&d);
        fs::write(d.join("test.json"), serde_json::json!({"id": name, "specimen": name, "standard": "en-14651"}).to_string()).unwrap();
        folders.push(d);
    }
    let out = dir.path().join("series");
    let mut a = vec!["report", "--series"];
    a.extend(folders.iter().map(|f| f.to_str().unwrap()));
    a.extend(["--config", cfg.to_str().unwrap(), "--out", out.to_str().unwrap(), "--no-pdf", "--exclude", "E4=cast with a void"]);
    let o = tagdeflect(&a);
    assert!(o.status.success(), "{}", stderr(&o));
    let j = read_json(&out.join("series.json"));
    println!(
        "SERIES EN: excluded {} statistics fR1 {} characteristic {} class {}",
        j["excluded"], j["statistics"]["fR1"], j["characteristic"], j["fib_class"]
    );
    assert_eq!(j["standard"], "en-14651");
    assert_eq!((j["n_total"].as_u64(), j["n_used"].as_u64()), (Some(5), Some(3)));
    let excluded = j["excluded"].as_array().unwrap();
    assert_eq!(excluded[0]["specimen"], "E4");
    assert_eq!(excluded[0]["reason"], "excluded by the lab: cast with a void");
    assert_eq!(excluded[1]["specimen"], "E5");
    assert!(excluded[1]["reason"].as_str().unwrap().starts_with("not a valid test: "), "{}", excluded[1]);
    let ck = |k: &str| j["characteristic"][k]["value"].as_f64().unwrap();
    for key in ["fR1", "fR3"] {
        let st = &j["statistics"][key];
        let (mean, sd) = (st["mean"].as_f64().unwrap(), st["sd"].as_f64().unwrap());
        assert_eq!(st["n"], 3);
        assert!((ck(&format!("{key}k")) - (mean - 3.37 * sd)).abs() < 1e-12, "{key}: {} vs {mean} − 3.37·{sd}", ck(&format!("{key}k")));
        assert_eq!(j["characteristic"][format!("{key}k")]["k_n"], 3.37);
    }
    let class = tagdeflect_report::series_stats::fib_class(ck("fR1k"), ck("fR3k"));
    assert_eq!(j["fib_class"]["class"].as_str(), class.as_deref());
    assert!(j["fib_class"]["source"].as_str().unwrap().contains("fib Model Code 2010 §5.6.3"));
    assert!(j["characteristic_source"].as_str().unwrap().contains("EN 1990"));
    let csv = fs::read_to_string(out.join("series.csv")).unwrap();
    assert!(csv.starts_with("specimen,used,excluded_reason,") && csv.contains("fR1 [MPa]"), "{csv}");
    assert!(csv.contains("\nE4,no,excluded by the lab: cast with a void,"), "{csv}");
    let html = fs::read_to_string(out.join("series.html")).unwrap();
    assert!(html.contains("Characteristic values") && html.contains("cast with a void"));

    // A C1609 specimen among them: refused, naming the folders of each standard.
    let c = dir.path().join("C1");
    clean(false, 50).write(&c);
    fs::write(c.join("test.json"), serde_json::json!({"id": "C1", "specimen": "C1", "standard": "astm-c1609"}).to_string()).unwrap();
    let out2 = dir.path().join("mixed");
    let mut a = vec!["report", "--series", folders[0].to_str().unwrap(), c.to_str().unwrap()];
    a.extend(["--config", cfg.to_str().unwrap(), "--out", out2.to_str().unwrap(), "--no-pdf"]);
    let o = tagdeflect(&a);
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    let e = stderr(&o);
    assert!(e.contains("mixes standards") && e.contains(&format!("astm-c1609: {}", c.display())), "{e}");
    assert!(e.contains(&format!("en-14651: {}", folders[0].display())), "{e}");
    assert!(!out2.join("series.json").exists(), "nothing written");
}
