//! A test folder's report whatever the route (issue "the test a lab signs"): the report made
//! at the test's stop by the daemon equals `report DIR`'s to the last digit; test.json's
//! measured dimensions, specimen, operator, notes and marks win over the config; a test.json
//! with a value out of range is one error naming the file and key.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::time::{Duration, Instant};

use tagdeflect_sim::SimParams;

use crate::http::{get, post, small_rig, tagdeflect_test, Daemon};

fn tagdeflect(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_tagdeflect")).args(args).output().expect("run tagdeflect")
}

pub(crate) fn read_json(p: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))).unwrap()
}

/// A test of a softening beam run through the control API of `demo` (start with measured
/// dimensions, notes and a standard; a mark; stop): its folder, and the beam of the config.
fn a_test_folder(dir: &Path, specimen: &str) -> (PathBuf, tagdeflect_report::BeamConfig) {
    a_test_folder_of(dir, specimen, None)
}

/// [`a_test_folder`] started with the method `method` (a file of `<tests>/methods/`) instead
/// of the standard, when given.
fn a_test_folder_of(dir: &Path, specimen: &str, method: Option<&str>) -> (PathBuf, tagdeflect_report::BeamConfig) {
    let params = SimParams { load_law: tagdeflect_sim::LoadLaw::Softening, frame_sets: 600, ..small_rig() };
    let cfg = crate::common::beam_rig_config(&params);
    let beam = crate::common::sim_beam(&params);
    let cfg_path = dir.join("rig.toml");
    std::fs::write(&cfg_path, cfg.to_toml_string()).unwrap();
    let tests_dir = dir.join("tests");
    let mut d =
        Daemon::start(&["demo", "--config", cfg_path.to_str().unwrap(), "--http", "127.0.0.1:0", "--tests", tests_dir.to_str().unwrap()]);
    let addr = d.addr();
    let token_file = tests_dir.join(".token");
    // The page may be served before the control API: wait for the API itself, idle.
    let served = Instant::now() + Duration::from_secs(60);
    while !token_file.is_file() || serde_json::from_slice::<serde_json::Value>(&get(addr, "/api/test").2).unwrap()["state"] != "idle" {
        assert!(Instant::now() < served, "no control API within 60 s");
        std::thread::sleep(Duration::from_millis(100));
    }
    let token = std::fs::read_to_string(&token_file).unwrap().trim().to_string();
    let mut body = serde_json::json!({
        "specimen": specimen, "operator": "A. Tester", "standard": "astm-c1609", "notes": "cast in mould 3",
        "measured": {"width_mm": beam.width_mm + 0.4, "depth_mm": beam.depth_mm - 0.3},
    });
    if let Some(m) = method {
        body.as_object_mut().unwrap().remove("standard");
        body["method"] = m.into();
    }
    let auth = format!("Bearer {token}");
    let (code, answer) =
        post(addr, "/api/test/start", &[("Content-Type", "application/json"), ("Authorization", &auth)], body.to_string().as_bytes());
    assert_eq!(code, 200, "{answer}");
    let id = serde_json::from_str::<serde_json::Value>(&answer).unwrap()["id"].as_str().unwrap().to_string();
    let of_test = |d: &Daemon| d.lines().iter().filter(|(_, l)| l.test.as_ref().is_some_and(|t| t.id == id)).count();
    let deadline = Instant::now() + Duration::from_secs(120);
    for want in [10, 20] {
        while of_test(&d) < want {
            assert!(Instant::now() < deadline, "the test's lines did not come");
            std::thread::sleep(Duration::from_millis(100));
        }
        if want == 10 {
            tagdeflect_test(addr, &token_file, &["mark", "first crack seen"]);
        }
    }
    let stopped = tagdeflect_test(addr, &token_file, &["stop"]);
    assert_eq!(d.stop(), Some(0));
    (PathBuf::from(stopped["folder"].as_str().unwrap()), beam)
}

/// report.json without what differs by where and when the report was written: the hashes of
/// its own output files (the PDF carries its printing time) and where its inputs are named
/// from (the report folder's parent); every value, note and input hash compared.
pub(crate) fn comparable(mut j: serde_json::Value) -> serde_json::Value {
    j.as_object_mut().unwrap().remove("outputs");
    for f in j["inputs"]["files"].as_array_mut().unwrap() {
        f.as_object_mut().unwrap().remove("name");
    }
    j
}

pub(crate) fn report_dir(folder: &Path, out: &Path) -> serde_json::Value {
    let o = tagdeflect(&["report", folder.to_str().unwrap(), "--out", out.to_str().unwrap(), "--no-pdf"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    read_json(&out.join("report.json"))
}

pub(crate) fn values(j: &serde_json::Value) -> Vec<(String, serde_json::Value)> {
    ["P1", "delta1", "f1", "Pp", "deltap", "fp", "P600", "P150", "f600", "f150", "T150", "RT150"]
        .iter()
        .filter_map(|k| j.get(*k).map(|v| (k.to_string(), v.clone())))
        .collect()
}

#[test]
fn the_report_at_stop_equals_report_dir_and_test_json_wins_over_the_config() {
    let dir = tempfile::tempdir().unwrap();
    let (folder, beam) = a_test_folder(dir.path(), "B7");
    let at_stop = read_json(&folder.join("report/report.json"));
    let again = report_dir(&folder, &dir.path().join("again"));
    assert!(!values(&at_stop).is_empty(), "{at_stop}");
    assert!(at_stop["outputs"].as_object().is_some_and(|o| o.contains_key("report.html")), "{}", at_stop["outputs"]);
    // No control output in this run: no control.json, no "Control output" section.
    assert!(!folder.join("control.json").exists() && at_stop.get("control").is_none(), "{}", at_stop["control"]);
    let html = std::fs::read_to_string(folder.join("report/report.html")).unwrap();
    assert!(!html.contains("Control output"), "a test without control outputs has no such section");
    assert_eq!(comparable(at_stop.clone()), comparable(again), "the report made at the stop and `report DIR` differ");
    // What the record gives the report.
    let s = &at_stop["specimen"];
    assert_eq!(s["id"], "B7");
    assert_eq!(at_stop["operator"], "A. Tester");
    assert_eq!(s["width_mm"].as_f64().unwrap(), beam.width_mm + 0.4);
    assert_eq!(s["depth_mm"].as_f64().unwrap(), beam.depth_mm - 0.3);
    assert_eq!(s["span_mm"].as_f64().unwrap(), beam.span_mm);
    assert_eq!(s["dimension_sources"], serde_json::json!({"width_mm": "test.json", "depth_mm": "test.json", "span_mm": "config"}));
    let kinds: Vec<&str> = at_stop["events"].as_array().unwrap().iter().map(|e| e["kind"].as_str().unwrap()).collect();
    assert_eq!(kinds, ["start", "mark", "stop"]);
    assert_eq!(at_stop["events"][1]["note"], "first crack seen");
    assert_eq!(at_stop["test_notes"], "cast in mould 3");
    assert!(at_stop["method_statement"].as_str().unwrap().starts_with("No test method was named"), "{}", at_stop["method_statement"]);
    let html = std::fs::read_to_string(folder.join("report/report.html")).unwrap();
    assert!(
        html.contains("Test record") && html.contains("first crack seen") && html.contains("cast in mould 3"),
        "the record in the HTML"
    );
    assert!(html.contains("<td>A. Tester</td>") && html.contains("<td>B7</td>"), "specimen and operator in the HTML");
    let curve_svg = std::fs::read_to_string(folder.join("report/load_deflection.svg")).unwrap_or_default();
    assert!(curve_svg.contains("first crack seen"), "the mark drawn on the load–deflection curve");

    // A mistyped width in the config changes nothing when test.json has the width.
    let copy = dir.path().join("copy");
    assert!(Command::new("cp").args(["-r", folder.to_str().unwrap(), copy.to_str().unwrap()]).status().unwrap().success());
    let toml_path = copy.join("tagdeflect.toml");
    let mut t: toml::Table = std::fs::read_to_string(&toml_path).unwrap().parse().unwrap();
    t["specimen"]["beam"].as_table_mut().unwrap().insert("width_mm".into(), toml::Value::Float(15.0));
    std::fs::write(&toml_path, toml::to_string(&t).unwrap()).unwrap();
    let mistyped = report_dir(&copy, &dir.path().join("mistyped"));
    assert_eq!(values(&mistyped), values(&at_stop), "the config's width does not reach the values");
    assert_eq!(mistyped["specimen"]["width_mm"], at_stop["specimen"]["width_mm"]);
    // The third route, `report --series`, of the folder and its copy: the same numbers for both.
    let series_out = dir.path().join("series");
    let (f, c, o) = (folder.to_str().unwrap(), copy.to_str().unwrap(), series_out.to_str().unwrap());
    let o = tagdeflect(&["report", "--series", f, c, "--out", o, "--no-pdf"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let specimens = read_json(&series_out.join("series.json"))["specimens"].clone();
    for k in 0..2 {
        for (key, v) in values(&at_stop) {
            let got = &specimens[k][&key];
            assert!(got["value"] == v["value"] && got["sigma"] == v["sigma"], "{key}: the series gives {got}, the report at stop {v}");
        }
    }

    // A width out of any beam's range in test.json: one error naming the file and the key.
    let rec_path = copy.join("test.json");
    let mut rec = read_json(&rec_path);
    rec["measured"]["width_mm"] = serde_json::json!(0.001);
    std::fs::write(&rec_path, rec.to_string()).unwrap();
    let o = tagdeflect(&["report", copy.to_str().unwrap(), "--out", dir.path().join("bad").to_str().unwrap(), "--no-pdf"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("test.json") && err.contains("measured.width_mm"), "{err}");
    assert!(!dir.path().join("bad").join("report.json").exists(), "nothing written");

    // test.json is read as the daemon writes it: a key of the wrong type (the width as text,
    // a count as text) is one error naming the file and the key, exit 2.
    for (key, bad) in [("measured", serde_json::json!({"width_mm": "150.2"})), ("lines", serde_json::json!("many"))] {
        let mut rec = read_json(&rec_path);
        rec["measured"]["width_mm"] = at_stop["specimen"]["width_mm"].clone();
        rec[key] = bad;
        std::fs::write(&rec_path, rec.to_string()).unwrap();
        let o = tagdeflect(&["report", copy.to_str().unwrap(), "--out", dir.path().join("bad").to_str().unwrap(), "--no-pdf"]);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{err}");
        let named = if key == "lines" { "lines: invalid type" } else { "measured.width_mm: invalid type" };
        assert!(err.contains(&format!("{}: {named}", rec_path.display())), "{err}");
        assert!(!dir.path().join("bad").join("report.json").exists(), "nothing written");
    }
}

/// The keys of the results table of a report's page, in its order.
fn page_results(html: &str) -> Vec<String> {
    let table = html.split("<h2>Results</h2>").nth(1).and_then(|t| t.split("</table>").next()).expect("a results table");
    table.split("<td class=\"key\">").skip(1).map(|c| c.split('<').next().unwrap().to_string()).collect()
}

/// A method's `results` are the report's: a lab's method naming four of C1609's results, in
/// its own order, gives a report at stop with only those (report.json, the page) that equals
/// `report DIR`'s, and a series of only those; a method naming a result its standard does not
/// give is refused when it is read, naming the file, the line and the key, exit 2.
#[test]
fn a_method_s_results_are_the_report_s_and_an_unknown_one_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let methods = dir.path().join("tests").join("methods");
    std::fs::create_dir_all(&methods).unwrap();
    let shipped = tagdeflect_core::method::SHIPPED[0].1;
    let all = r#"results = ["P1", "delta1", "f1", "Pp", "deltap", "fp", "P600", "P150", "f600", "f150", "T150", "RT150"]"#;
    assert!(shipped.contains(all), "the shipped C1609 method names every result of today's reports");
    // No preload and a high start limit: the test starts at once, whatever the load.
    let lab = shipped
        .replace("C1609-19", "C1609-LAB")
        .replace("preload_kn = 0.5\n", "")
        .replace("max_start_load_kn = 2.0", "max_start_load_kn = 500.0");
    let bad = lab.replace("C1609-LAB", "C1609-BAD").replace(all, r#"results = ["P1", "f1", "f300", "T150"]"#);
    let lab = lab.replace(all, r#"results = ["f150", "f1", "T150", "P1"]"#);
    std::fs::write(methods.join("C1609-LAB.toml"), &lab).unwrap();
    std::fs::write(methods.join("C1609-BAD.toml"), &bad).unwrap();
    let t = dir.path().join("tests");
    let o = tagdeflect(&["method", "show", "C1609-BAD", "--tests", t.to_str().unwrap()]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    let line = bad.lines().position(|l| l.starts_with("results =")).unwrap() + 1;
    assert!(err.contains(&format!("C1609-BAD.toml:{line}: `results[2]`")) && err.contains("\"f300\""), "{err}");

    let (folder, _) = a_test_folder_of(dir.path(), "M1", Some("C1609-LAB"));
    let want = ["f150", "f1", "T150", "P1"];
    let at_stop = read_json(&folder.join("report/report.json"));
    assert_eq!(at_stop["method"]["name"], "C1609-LAB", "{}", at_stop["method"]);
    let mut given: Vec<&str> =
        at_stop.as_object().unwrap().keys().map(String::as_str).filter(|k| all.contains(&format!("\"{k}\""))).collect();
    given.extend(at_stop["undetermined"].as_object().map_or(Vec::new(), |u| u.keys().map(String::as_str).collect()));
    given.sort_unstable();
    let mut sorted = want.to_vec();
    sorted.sort_unstable();
    assert_eq!(given, sorted, "report.json gives the method's results, no other: {at_stop}");
    let mut defined: Vec<&str> = at_stop["definitions"].as_object().unwrap().keys().map(String::as_str).collect();
    defined.sort_unstable();
    assert_eq!(defined, sorted, "and defines only those");
    let html = std::fs::read_to_string(folder.join("report/report.html")).unwrap();
    assert_eq!(page_results(&html), want, "the page's results: the method's, in its order");
    let again = report_dir(&folder, &dir.path().join("again"));
    assert_eq!(comparable(at_stop.clone()), comparable(again), "the report made at the stop and `report DIR` differ");

    // A series of the folder and its copy (beside it, so the method is found): only those.
    let copy = folder.with_file_name("M1-copy");
    assert!(Command::new("cp").args(["-r", folder.to_str().unwrap(), copy.to_str().unwrap()]).status().unwrap().success());
    let out = dir.path().join("series");
    let o =
        tagdeflect(&["report", "--series", folder.to_str().unwrap(), copy.to_str().unwrap(), "--out", out.to_str().unwrap(), "--no-pdf"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let series = read_json(&out.join("series.json"));
    let mut stats: Vec<&str> = series["statistics"].as_object().unwrap().keys().map(String::as_str).collect();
    stats.sort_unstable();
    assert_eq!(stats, sorted, "{series}");
    let csv = std::fs::read_to_string(out.join("series.csv")).unwrap();
    let header = csv.lines().next().unwrap();
    let columns: Vec<&str> = want.iter().copied().filter(|k| header.contains(&format!(",{k} ["))).collect();
    assert_eq!(columns, want, "{header}");
    for k in ["delta1", "Pp", "f600", "RT150"] {
        assert!(!header.contains(&format!(",{k} [")), "{k} not in the series' CSV: {header}");
    }
    assert_eq!(page_results(&std::fs::read_to_string(copy.join("report/report.html")).unwrap()), want);
}

pub(crate) fn verify(dir: &Path) -> (Option<i32>, String) {
    let o = tagdeflect(&["report", "verify", dir.to_str().unwrap()]);
    (o.status.code(), format!("{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr)))
}

/// `report verify DIR` checks the folder it is given: a copy elsewhere verifies clean (its
/// inputs found by name, the outputs, test.json's hashes, the audit chain); an edited
/// report.json, a deleted PDF and a changed test.json are each caught and named, exit 1.
#[test]
fn report_verify_checks_the_copied_folder_it_is_given() {
    let dir = tempfile::tempdir().unwrap();
    let (folder, _) = a_test_folder(dir.path(), "V1");
    let id = folder.file_name().unwrap().to_str().unwrap().to_string();
    let tests_copy = dir.path().join("elsewhere").join("tests");
    std::fs::create_dir_all(tests_copy.parent().unwrap()).unwrap();
    assert!(Command::new("cp")
        .args(["-r", folder.parent().unwrap().to_str().unwrap(), tests_copy.to_str().unwrap()])
        .status()
        .unwrap()
        .success());
    let copy = tests_copy.join(&id);
    let (code, out) = verify(&copy);
    println!("VERIFY clean copy:\n{out}");
    assert_eq!(code, Some(0), "{out}");
    assert!(out.contains(&copy.join("feed.jsonl").display().to_string()), "the copy's own files checked: {out}");
    assert!(!out.contains(&folder.join("feed.jsonl").display().to_string()), "not the original's: {out}");
    assert!(out.contains("output") && out.contains("report.html"), "{out}");
    let (code, out) = verify(&copy.join("report"));
    assert_eq!(code, Some(0), "the report folder verifies as its test folder: {out}");

    tampering_caught(&copy);

    // A changed feed: named as the report's input and through test.json's hashes.
    let feed = copy.join("feed.jsonl");
    let feed_text = std::fs::read_to_string(&feed).unwrap();
    std::fs::write(&feed, feed_text.replacen("\"seq\"", "\"seq\" ", 1)).unwrap();
    let (code, out) = verify(&copy);
    assert_eq!(code, Some(1), "{out}");
    assert!(out.contains(&format!("CHANGED  feed {}", feed.display())) && out.contains("test.json"), "{out}");
    std::fs::write(&feed, feed_text).unwrap();
    let tj = copy.join("test.json");
    let mut rec = read_json(&tj);
    rec["sha256"]["utm.jsonl"] = serde_json::json!("0".repeat(64));
    std::fs::write(&tj, rec.to_string()).unwrap();
    std::fs::write(copy.join("added.txt"), "slipped in\n").unwrap();
    let (code, out) = verify(&copy);
    assert_eq!(code, Some(1), "{out}");
    assert!(out.contains(&format!("CHANGED  test.json {}", copy.join("utm.jsonl").display())), "{out}");
    assert!(out.contains(&format!("EXTRA    test.json {}", copy.join("added.txt").display())), "{out}");

    // The tests folder's audit chain, edited by hand (the stop made by someone else): `report
    // verify` names the log and its broken line; whole again, the chain is whole.
    let log = tests_copy.join("audit.jsonl");
    let text = std::fs::read_to_string(&log).unwrap();
    assert!(out.contains(&format!("same     audit {} (", log.display())) && out.contains("chain whole)"), "the chain checked: {out}");
    let n = text.lines().position(|l| l.contains("\"action\":\"stop\"")).expect("the stop in the audit log");
    let edited: Vec<String> = text
        .lines()
        .enumerate()
        .map(|(i, l)| if i == n { l.replacen("\"user\":\"", "\"user\":\"eve", 1) } else { l.to_string() })
        .collect();
    std::fs::write(&log, edited.join("\n") + "\n").unwrap();
    let (code, out) = verify(&copy);
    assert_eq!(code, Some(1), "{out}");
    let named = format!("CHANGED  audit {}", log.display());
    let at = format!("{}:{}: sha256", log.display(), n + 1);
    assert!(out.contains(&named) && out.contains(&at), "the edited chain named with its line: {out}");
}

/// `report verify` on a test folder `copy` catches, each named (exit 1) and undone after: an
/// edited report.json, a deleted PDF (or, without Chromium, the HTML), a changed operator in
/// test.json. The folder verifies clean before and after.
pub(crate) fn tampering_caught(copy: &Path) {
    assert_eq!(verify(copy).0, Some(0), "{}", verify(copy).1);
    // An edited report.json.
    let rj = copy.join("report/report.json");
    let text = std::fs::read_to_string(&rj).unwrap();
    std::fs::write(&rj, text.replacen("\"valid\"", "\"valid\" ", 1)).unwrap();
    let (code, out) = verify(copy);
    assert_eq!(code, Some(1), "{out}");
    assert!(out.contains("CHANGED  test.json") && out.contains("report/report.json changed"), "{out}");
    std::fs::write(&rj, text).unwrap();
    assert_eq!(verify(copy).0, Some(0));

    // A deleted PDF (or, without Chromium, the HTML).
    let gone = ["report.pdf", "report.html"].iter().map(|n| copy.join("report").join(n)).find(|p| p.is_file()).unwrap();
    let bytes = std::fs::read(&gone).unwrap();
    std::fs::remove_file(&gone).unwrap();
    let (code, out) = verify(copy);
    assert_eq!(code, Some(1), "{out}");
    assert!(out.contains(&format!("MISSING  output {}", gone.display())), "{out}");
    std::fs::write(&gone, bytes).unwrap();
    assert_eq!(verify(copy).0, Some(0));

    let tj = copy.join("test.json");
    let original = std::fs::read_to_string(&tj).unwrap();
    let mut rec = read_json(&tj);
    let operator = rec["operator"].as_str().unwrap().to_string();
    rec["operator"] = serde_json::json!("Someone Else");
    std::fs::write(&tj, rec.to_string()).unwrap();
    let (code, out) = verify(copy);
    assert_eq!(code, Some(1), "{out}");
    assert!(out.contains(&format!("`operator` is \"Someone Else\", the report took \"{operator}\"")), "{out}");
    std::fs::write(&tj, original).unwrap();
    assert_eq!(verify(copy).0, Some(0));
}
