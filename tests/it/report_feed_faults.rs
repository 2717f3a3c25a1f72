//! The report's feed reader and export against faulty feeds: two runs in one file, a jump in
//! time, absurd values, a line with 300 000 tags, QC said once, export guarding its output.

use std::fs;

use crate::report_lab::*;

fn simple_feed(n: usize, dt_ns: i64) -> Vec<String> {
    (0..n)
        .map(|k| {
            let x = k as f64 * 0.01;
            serde_json::json!({"seq": k, "t_ns": T0 + k as i64 * dt_ns, "load_kN": softening(x), "net_deflection_mm": x,
                "tags": [{"id": 0, "pos_mm": [0.0, 0.0, 0.0], "disp_mm": [0.0, 0.0, 0.0], "sigma_mm": [0.004, 0.01, 0.002]},
                         {"id": 1, "pos_mm": [0.0, 0.0, -x], "disp_mm": [0.0, 0.0, -x], "sigma_mm": [0.004, 0.01, 0.002]},
                         {"id": 2, "pos_mm": [0.0, 0.0, 0.0], "disp_mm": [0.0, 0.0, 0.0], "sigma_mm": [0.004, 0.01, 0.002]}]})
            .to_string()
        })
        .collect()
}

#[test]
fn two_runs_in_one_feed_are_refused_or_reported_as_two() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = config_with_beam(dir.path(), C1609_BEAM);
    let feed = dir.path().join("feed.jsonl");
    let one = simple_feed(40, 100_000_000);
    // Two runs appended: seq 39 → 0, the deflection from 0 again.
    put(&feed, &[one.clone(), one.clone()].concat());
    let out = dir.path().join("r");
    let o = report(&feed, &cfg, "astm-c1609", &out, &[]);
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(stderr(&o).contains("feed.jsonl:41:") && stderr(&o).contains("seq 0 goes back from seq 39"), "{}", stderr(&o));
    assert!(!out.exists(), "nothing written");
    // With --allow-restarts: each run on its own.
    let o = report(&feed, &cfg, "astm-c1609", &out, &["--allow-restarts"]);
    assert!(o.status.success(), "{}", stderr(&o));
    for k in [1, 2] {
        let j = read_json(&out.join(format!("run-{k}/report.json")));
        assert_eq!(j["run"]["index"], k);
        assert_eq!(j["qc"]["lines"], 40);
        assert!((value(&j, "P1").0 - 40.0).abs() < 1.0);
    }
    assert_eq!(read_json(&out.join("series.json"))["specimens"].as_array().unwrap().len(), 2);
    // One repeated seq with a load of 999 kN.
    let mut rep = one.clone();
    let mut dup: serde_json::Value = serde_json::from_str(&one[20]).unwrap();
    dup["load_kN"] = 999.0.into();
    rep.insert(21, dup.to_string());
    put(&feed, &rep);
    let o = report(&feed, &cfg, "astm-c1609", &dir.path().join("r3"), &[]);
    assert_eq!(o.status.code(), Some(2));
    assert!(stderr(&o).contains("feed.jsonl:22:") && stderr(&o).contains("seq 20 repeats seq 20"), "{}", stderr(&o));
}

#[test]
fn a_jump_in_time_with_contiguous_seq_is_a_gap() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = config_with_beam(dir.path(), C1609_BEAM);
    let feed = dir.path().join("feed.jsonl");
    let mut lines = simple_feed(60, 100_000_000);
    for (k, l) in lines.iter_mut().enumerate().skip(30) {
        let mut v: serde_json::Value = serde_json::from_str(l).unwrap();
        v["t_ns"] = (T0 + k as i64 * 100_000_000 + 20_000_000_000).into();
        *l = v.to_string();
    }
    put(&feed, &lines);
    let out = dir.path().join("r");
    let o = report(&feed, &cfg, "astm-c1609", &out, &[]);
    assert!(o.status.success(), "{}", stderr(&o));
    let j = read_json(&out.join("report.json"));
    assert_eq!(j["qc"]["frame_sets_without_line"], 0, "seq is contiguous");
    assert_eq!(j["qc"]["time_gaps"].as_array().unwrap().len(), 1, "{}", j["qc"]);
    assert!((j["qc"]["time_gaps"][0]["duration_s"].as_f64().unwrap() - 20.1).abs() < 1e-6);
    assert!(
        j["qc"]["warnings"].as_array().unwrap().iter().any(|w| w.as_str().unwrap().contains("gap(s) in time")),
        "{}",
        j["qc"]["warnings"]
    );
    assert!(j["invalid_reasons"].as_array().unwrap().iter().any(|w| w.as_str().unwrap().contains("20.1 s")), "{}", j["invalid_reasons"]);
}

#[test]
fn absurd_values_are_an_error_naming_file_and_line() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = config_with_beam(dir.path(), C1609_BEAM);
    let feed = dir.path().join("feed.jsonl");
    for (field, v, want) in [
        ("load_kN", serde_json::json!(1e308), "load_kN = 1e308"),
        ("load_kN", serde_json::json!(-1e308), "load_kN = -1e308"),
        ("load_kN", serde_json::json!(3e38), "load_kN = 3e38"),
        ("t_ns", serde_json::json!(i64::MAX), "t_ns 9223372036854775807"),
        ("seq", serde_json::json!(u64::MAX), "seq 18446744073709551615"),
    ] {
        let mut lines = simple_feed(20, 100_000_000);
        let mut l: serde_json::Value = serde_json::from_str(&lines[4]).unwrap();
        l[field] = v;
        lines[4] = l.to_string();
        put(&feed, &lines);
        let o = report(&feed, &cfg, "astm-c1609", &dir.path().join("r"), &[]);
        assert_eq!(o.status.code(), Some(2), "{field}: {}", stderr(&o));
        assert!(stderr(&o).contains("feed.jsonl:5:") && stderr(&o).contains(want), "{field}: {}", stderr(&o));
        assert_eq!(stderr(&o).trim().lines().count(), 1, "one line: {}", stderr(&o));
    }
    // The range is configurable.
    let mut lines = simple_feed(20, 100_000_000);
    let mut l: serde_json::Value = serde_json::from_str(&lines[4]).unwrap();
    l["load_kN"] = 200.0.into();
    lines[4] = l.to_string();
    put(&feed, &lines);
    let o = report(&feed, &cfg, "astm-c1609", &dir.path().join("r"), &["--max-load-kn", "100"]);
    assert_eq!(o.status.code(), Some(2));
    assert!(stderr(&o).contains("load_kN = 200 is outside ±100 kN"), "{}", stderr(&o));
}

#[test]
fn a_line_with_300000_tags_is_read_and_exported_in_linear_time() {
    let dir = tempfile::tempdir().unwrap();
    let feed = dir.path().join("feed.jsonl");
    let mut lines = simple_feed(5, 100_000_000);
    let mut big: serde_json::Value = serde_json::from_str(&lines[2]).unwrap();
    let tags: Vec<serde_json::Value> =
        (0..300_000u32).map(|id| serde_json::json!({"id": id, "pos_mm": [0, 0, 0], "disp_mm": [0, 0, 0], "views": 1})).collect();
    big["tags"] = tags.into();
    lines[2] = big.to_string();
    put(&feed, &lines);
    // Quadratic before (every tag id looked up in every line by a scan): 9·10¹⁰ steps.
    let csv = dir.path().join("feed.csv");
    let o = tagdeflect(&["export", feed.to_str().unwrap(), "--csv", csv.to_str().unwrap()]);
    assert!(o.status.success(), "{}", stderr(&o));
    let text = fs::read_to_string(&csv).unwrap();
    let header = text.lines().next().unwrap();
    assert_eq!(header.split(',').count(), 5 + 3 * 300_000);
    let cfg = config_with_beam(dir.path(), C1609_BEAM);
    let out = dir.path().join("r");
    let o = report(&feed, &cfg, "astm-c1609", &out, &[]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(read_json(&out.join("report.json"))["qc"]["tags"].as_array().unwrap().len(), 300_000);
}

#[test]
fn qc_says_things_once_and_in_units_of_sigma_and_export_guards_its_output() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = config_with_beam(dir.path(), C1609_BEAM);
    // A feed that starts at 0.5 mm: the warning once; drift of 0.0001° (far below the σ): none.
    let feed = dir.path().join("feed.jsonl");
    let lines: Vec<String> = simple_feed(200, 100_000_000)
        .into_iter()
        .skip(50)
        .map(|l| {
            let mut v: serde_json::Value = serde_json::from_str(&l).unwrap();
            v["cameras"] = serde_json::json!([{"name": "front", "drift_deg": 0.0001, "drift_mm": 0.00003}]);
            v.to_string()
        })
        .collect();
    put(&feed, &lines);
    let out = dir.path().join("r");
    let o = report(&feed, &cfg, "astm-c1609", &out, &[]);
    assert!(o.status.success(), "{}", stderr(&o));
    let j = read_json(&out.join("report.json"));
    let w: Vec<&str> = j["qc"]["warnings"].as_array().unwrap().iter().map(|w| w.as_str().unwrap()).collect();
    assert_eq!(w.iter().filter(|w| w.contains("curve starts at")).count(), 1, "{w:?}");
    assert!(!w.iter().any(|w| w.contains("drift")), "{w:?}");
    // A drift that matters (0.05° ≈ 0.9 mm at 1 m) is one warning.
    let drifting: Vec<String> = lines
        .iter()
        .map(|l| {
            let mut v: serde_json::Value = serde_json::from_str(l).unwrap();
            v["cameras"] = serde_json::json!([{"name": "front", "drift_deg": 0.05}]);
            v.to_string()
        })
        .collect();
    put(&feed, &drifting);
    let o = report(&feed, &cfg, "astm-c1609", &out, &[]);
    assert!(o.status.success());
    let j = read_json(&out.join("report.json"));
    assert_eq!(j["qc"]["warnings"].as_array().unwrap().iter().filter(|w| w.as_str().unwrap().contains("drift_deg")).count(), 1);

    // CSV without float noise or negative zero.
    let mut v: serde_json::Value = serde_json::from_str(&lines[0]).unwrap();
    v["load_kN"] = 16.860300000000002.into();
    v["stroke_mm"] = (-0.0).into();
    put(&feed, &[v.to_string()]);
    let csv = dir.path().join("one.csv");
    let o = tagdeflect(&["export", feed.to_str().unwrap(), "--csv", csv.to_str().unwrap()]);
    assert!(o.status.success(), "{}", stderr(&o));
    let row = fs::read_to_string(&csv).unwrap().lines().nth(1).unwrap().to_string();
    assert!(row.contains(",16.8603,0,"), "{row}");
    // export refuses a missing folder (naming it) and an output that is its input.
    let before = fs::read_to_string(&feed).unwrap();
    let missing = dir.path().join("no/such/dir/out.csv");
    let o = tagdeflect(&["export", feed.to_str().unwrap(), "--csv", missing.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(2));
    assert!(stderr(&o).contains("no/such/dir") && stderr(&o).contains("does not exist"), "{}", stderr(&o));
    assert!(!dir.path().join("no").exists(), "no folder created");
    let o = tagdeflect(&["export", feed.to_str().unwrap(), "--csv", feed.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(2));
    assert!(stderr(&o).contains("overwrite the feed"), "{}", stderr(&o));
    assert_eq!(fs::read_to_string(&feed).unwrap(), before, "the feed is untouched");
}
