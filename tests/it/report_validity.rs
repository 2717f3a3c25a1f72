//! A test's validity end to end (the UTM stream's gaps and outages, a test stopped early) and
//! QC without false alarms on every standard and load law.

use std::fs;
use std::path::Path;

use crate::report_lab::*;

/// Removes the lines `lines` (0-based) of a JSON Lines file.
fn drop_lines(p: &Path, lines: std::ops::Range<usize>) {
    let kept: Vec<String> =
        fs::read_to_string(p).unwrap().lines().enumerate().filter(|(k, _)| !lines.contains(k)).map(|(_, l)| l.to_string()).collect();
    put(p, &kept);
}

/// The clean C1609 test with 4 s of its UTM samples lost, then with the UTM down for 3 s
/// (feed lines `"utm": "down"` without a load, no UTM samples then): each a located sentence
/// in `invalid_reasons` and in the page's banner; the untouched test is valid.
#[test]
fn gaps_and_outages_of_the_utm_stream_make_a_test_invalid() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = config_with_beam(dir.path(), C1609_BEAM);
    // UTM sample j is taken at 0.05·j − 0.247 s (20 Hz); j = 20004 at 999.953 s.
    let feed = clean(false, 21).write(&dir.path().join("gap"));
    drop_lines(&dir.path().join("gap/utm.jsonl"), 20005..20084);
    let out = dir.path().join("r-gap");
    let o = report(&feed, &cfg, "astm-c1609", &out, &[]);
    assert!(o.status.success(), "{}", stderr(&o));
    let j = read_json(&out.join("report.json"));
    println!("REPORT UTM gap: valid {} {:?}", j["valid"], invalid_reasons(&j));
    assert_eq!(j["valid"], false);
    assert_eq!(
        invalid_reasons(&j),
        ["The UTM stream has 1 gap(s) longer than 2 s (the longest 4.0 s, from 1000.0 s to 1004.0 s into the feed): the load is not known there."]
    );
    let html = fs::read_to_string(out.join("report.html")).unwrap();
    assert!(html.contains("Not a valid test") && html.contains("The UTM stream has 1 gap(s) longer than 2 s"), "the banner");

    // The UTM down from 500 to 503 s: the feed's lines say so and carry no load.
    let feed = clean(false, 22).write(&dir.path().join("down"));
    let lines: Vec<String> = fs::read_to_string(&feed)
        .unwrap()
        .lines()
        .map(|l| {
            let mut v: serde_json::Value = serde_json::from_str(l).unwrap();
            let t = (v["t_ns"].as_i64().unwrap() - T0) as f64 * 1e-9;
            if (500.0..503.0).contains(&t) {
                v["utm"] = "down".into();
                v.as_object_mut().unwrap().remove("load_kN");
            }
            v.to_string()
        })
        .collect();
    put(&feed, &lines);
    drop_lines(&dir.path().join("down/utm.jsonl"), 10005..10064);
    let out = dir.path().join("r-down");
    let o = report(&feed, &cfg, "astm-c1609", &out, &[]);
    assert!(o.status.success(), "{}", stderr(&o));
    let j = read_json(&out.join("report.json"));
    println!("REPORT UTM down: valid {} {:?} qc {:?}", j["valid"], invalid_reasons(&j), qc_warnings(&j));
    assert_eq!(j["valid"], false);
    assert_eq!(
        invalid_reasons(&j),
        [
            "The UTM stream has 1 gap(s) longer than 2 s (the longest 3.0 s, from 500.0 s to 503.0 s into the feed): the load is not known there.",
            "The UTM was unreachable for 3.0 s during the test: the load is not known then."
        ]
    );
    assert_eq!(j["qc"]["utm_down_lines"], 6);
    assert!(qc_warnings(&j).iter().any(|w| w == "UTM down 1 time(s), 3.0 s in all"), "{:?}", qc_warnings(&j));

    // The same test untouched: valid.
    let feed = clean(false, 22).write(&dir.path().join("ok"));
    let out = dir.path().join("r-ok");
    let o = report(&feed, &cfg, "astm-c1609", &out, &[]);
    assert!(o.status.success(), "{}", stderr(&o));
    let j = read_json(&out.join("report.json"));
    assert_eq!(j["valid"], true, "{:?}", invalid_reasons(&j));
}

/// A C1609 test stopped at 2.5 mm (L/150 = 3 mm) and an EN 14651 test stopped at CMOD 3 mm:
/// invalid, the sentence says how far the test got and what the standard needs, and the
/// values past the end are undetermined.
#[test]
fn a_test_stopped_before_its_end_says_how_far_it_got() {
    let dir = tempfile::tempdir().unwrap();
    for (standard, beam, cmod, x_end, x_name, needs, missing) in [
        ("astm-c1609", C1609_BEAM, false, 2.5, "net deflection", "ASTM C1609 needs the test carried to L/150 = 3.00 mm.", "P150"),
        ("en-14651", EN_BEAM, true, 3.0, "CMOD (gauge cmod)", "EN 14651 needs the test carried to CMOD = 3.5 mm.", "fR4"),
    ] {
        let feed = Synth { x_end, ..clean(cmod, 23) }.write(&dir.path().join(standard));
        let cfg = config_with_beam(dir.path(), beam);
        let out = dir.path().join(format!("{standard}-r"));
        let o = report(&feed, &cfg, standard, &out, &[]);
        assert!(o.status.success(), "{}", stderr(&o));
        let j = read_json(&out.join("report.json"));
        let r = invalid_reasons(&j);
        println!("REPORT stopped early {standard}: {r:?}");
        assert_eq!(j["valid"], false);
        assert_eq!(r.len(), 1, "{standard}: {r:?}");
        let reached: f64 = r[0]
            .strip_prefix(&format!("The {x_name} reached only "))
            .and_then(|s| s.strip_suffix(&format!(" mm: {needs}")))
            .unwrap_or_else(|| panic!("{standard}: {}", r[0]))
            .parse()
            .unwrap();
        assert!((reached - x_end).abs() < 0.01, "{standard}: reached {reached}");
        assert!(j["undetermined"][missing].is_string(), "{standard}: {missing} undetermined: {}", j["undetermined"]);
    }
}

/// The simulator's hardening law (`simulate --load-law hardening`, `tagdeflect_sim::law`):
/// elastic to the first crack (30 kN at 0.3 mm), a 10 % drop, then a rise towards 1.5 times
/// the cracking load (scale 0.5 mm).
fn sim_hardening(x: f64) -> f64 {
    if x <= 0.3 {
        100.0 * x
    } else {
        30.0 * (1.5 + (0.9 - 1.5) * (-(x - 0.3) / 0.5).exp())
    }
}

/// An elastic beam that never cracks (`simulate --load-law elastic`): 15 kN/mm.
fn elastic(x: f64) -> f64 {
    15.0 * x
}

/// Against CMOD: elastic to 16 kN at 0.03 mm, a drop to 14 kN, then a rise to 20 kN at 4 mm.
fn notched_hardening(x: f64) -> f64 {
    if x <= 0.03 {
        16.0 / 0.03 * x
    } else {
        14.0 + 6.0 * (x - 0.03) / 3.97
    }
}

/// A UHPC prism (ASTM C1856): 75 × 75 mm on a 225 mm span (L/150 = 1.5 mm, L/900 = 0.25 mm).
const C1856_BEAM: &str = "width_mm = 75.0\ndepth_mm = 75.0\nspan_mm = 225.0";

/// The clean tests of `a_clean_test_of_each_kind_is_valid_without_qc_warnings` for ASTM
/// C1856 and for each load law: no QC warning on any; valid, except the never-cracked elastic
/// beam, which is invalid for the one reason that it has no first peak.
/// A clean case: name, standard, beam, the test, extra arguments, and the one reason it is
/// invalid for (none: valid).
type CleanCase = (&'static str, &'static str, &'static str, Synth, &'static [&'static str], Option<&'static str>);

#[test]
fn a_clean_test_of_every_standard_and_load_law_has_no_qc_warning() {
    const NO_PEAK: &str = "No first peak: the load never fell after a maximum, so the first crack (the first point where the slope is \
                           zero) was not reached or not recorded.";
    let dir = tempfile::tempdir().unwrap();
    // The C1856 prism at 0.06 mm/min (inside both of C1609's windows for a beam ≤ 125 mm deep).
    let uhpc = |law: fn(f64) -> f64, seed| Synth { law, rate: 0.06, x_end: 1.6, ..clean(false, seed) };
    let cases: [CleanCase; 8] = [
        ("c1856-softening", "astm-c1856", C1856_BEAM, uhpc(softening, 31), &[], None),
        ("c1856-hardening", "astm-c1856", C1856_BEAM, uhpc(sim_hardening, 32), &[], None),
        ("c1856-elastic", "astm-c1856", C1856_BEAM, uhpc(elastic, 33), &[], Some(NO_PEAK)),
        ("c1609-hardening", "astm-c1609", C1609_BEAM, Synth { law: sim_hardening, ..clean(false, 34) }, &[], None),
        (
            "c1609-hardening-stated",
            "astm-c1609",
            C1609_BEAM,
            Synth { law: hardening, x_end: 3.3, ..clean(false, 35) },
            &["--response", "hardening"],
            None,
        ),
        ("c1609-elastic", "astm-c1609", C1609_BEAM, Synth { law: elastic, ..clean(false, 36) }, &[], Some(NO_PEAK)),
        ("en-hardening", "en-14651", EN_BEAM, Synth { law: notched_hardening, ..clean(true, 37) }, &[], None),
        ("en-softening-other-seed", "en-14651", EN_BEAM, clean(true, 38), &[], None),
    ];
    for (name, standard, beam, synth, extra, invalid) in cases {
        let feed = synth.write(&dir.path().join(name));
        let cfg_dir = dir.path().join(format!("{name}-cfg"));
        fs::create_dir_all(&cfg_dir).unwrap();
        let cfg = config_with_beam(&cfg_dir, beam);
        let out = dir.path().join(format!("{name}-r"));
        let o = report(&feed, &cfg, standard, &out, extra);
        assert!(o.status.success(), "{name}: {}", stderr(&o));
        let j = read_json(&out.join("report.json"));
        println!(
            "REPORT clean {name}: valid {} reasons {:?} qc {:?} rates {}",
            j["valid"],
            invalid_reasons(&j),
            qc_warnings(&j),
            j["rates"]
        );
        assert_eq!(qc_warnings(&j), Vec::<String>::new(), "{name}: QC false alarms");
        match invalid {
            None => assert_eq!((j["valid"].as_bool(), invalid_reasons(&j)), (Some(true), vec![]), "{name}"),
            Some(why) => assert_eq!((j["valid"].as_bool(), invalid_reasons(&j)), (Some(false), vec![why.to_string()]), "{name}"),
        }
        let html = fs::read_to_string(out.join("report.html")).unwrap();
        assert!(html.contains("No warnings."), "{name}: the page's QC says so");
    }
}
