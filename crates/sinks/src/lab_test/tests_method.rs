//! The unit tests of a start with a method and a specimen of the table, the refusals, the
//! preload, the crack entry and the stop's report error.

use tagdeflect_core::feed::FeedLine;
use tagdeflect_core::utm_sample::UtmSample;

use super::{LabTests, ReportHook, TestError, TestRecord, ZERO_SETS};

const TABLE: &str = "id,width_mm,width_mm,depth_mm,span_mm,cast_date,mix\n\
                     S1,150.2,150.4,149.9,450,2026-11-01,C40\n\
                     S2,150,,150,450,,\n\
                     S3,150,,150,,,\n";

fn utm(load_kn: f64) -> UtmSample {
    UtmSample { t_ns: tagdeflect_core::clock::now_epoch_ns(), load_kn, stroke_mm: None }
}

fn start(tests: &LabTests, body: serde_json::Value) -> Result<serde_json::Value, TestError> {
    tests.start_request(body, None)
}

#[test]
fn a_start_takes_its_method_and_the_next_specimen_and_is_refused_when_its_report_could_not_be_made() {
    let dir = tempfile::tempdir().unwrap();
    let hook: ReportHook = Box::new(|_, _| Err("the feed holds too few lines".into()));
    let tests = LabTests::new(dir.path(), String::new(), Vec::new(), Some(hook)).unwrap();
    tests.import_specimens(super::parse_specimens(TABLE.as_bytes(), true).unwrap()).unwrap();
    assert_eq!(tests.specimens().unwrap()["next"], "S1");
    // No geometry anywhere: refused, naming what is missing and where it was looked for.
    let no_span = start(&tests, serde_json::json!({"method": "C1609-19", "specimen": "S3"}));
    let Err(TestError::Bad(why)) = no_span else { panic!("{no_span:?}") };
    assert!(why.contains("method C1609-19 needs span_mm") && why.contains("[specimen.beam]"), "{why}");
    let Err(TestError::Bad(why)) = start(&tests, serde_json::json!({"standard": "en-14651", "specimen": "X1"})) else { panic!() };
    assert!(why.contains("standard en-14651 needs width_mm, depth_mm, span_mm, notch_mm"), "{why}");
    let Err(TestError::Bad(why)) = start(&tests, serde_json::json!({"method": "C1609-19", "standard": "en-14651", "specimen": "S1"}))
    else {
        panic!()
    };
    assert!(why.contains("astm-c1609"), "{why}");
    assert!(matches!(start(&tests, serde_json::json!({"method": "C0000", "specimen": "S1"})), Err(TestError::Bad(_))));
    assert!(matches!(start(&tests, serde_json::json!({"specimen": "S1", "colour": "red"})), Err(TestError::Bad(_))));
    // Under load: refused (409), naming the load and the method's limit.
    tests.on_utm(&utm(3.25));
    let Err(TestError::Conflict(why)) = start(&tests, serde_json::json!({"method": "C1609-19", "specimen": "next"})) else { panic!() };
    assert!(why.contains("3.250 kN") && why.contains("max_start_load_kn = 2 kN"), "{why}");
    // Unloaded: the next specimen, its readings' means, the method recorded.
    tests.on_utm(&utm(0.4));
    let st = start(&tests, serde_json::json!({"method": "C1609-19", "specimen": "next", "operator": "A. Tester"})).unwrap();
    assert_eq!(st["specimen"], "S1");
    assert!((st["measured"]["width_mm"].as_f64().unwrap() - 150.3).abs() < 1e-9, "{st}");
    assert_eq!(st["measured"]["span_mm"], 450.0);
    for k in 0..ZERO_SETS as i64 + 1 {
        let mut l = FeedLine {
            seq: k as u64,
            t_ns: super::tests::t(k),
            load_kn: Some(0.5 + 0.01 * k as f64),
            net_deflection_mm: Some(0.0),
            ..FeedLine::default()
        };
        tests.apply(&mut l);
        tests.on_line(&l);
    }
    assert!(matches!(
        tests.crack(serde_json::from_str(r#"{"position_mm": 20, "inside_middle_third": false}"#).unwrap()),
        Err(TestError::Bad(_))
    ));
    tests.crack(serde_json::from_str(r#"{"position_mm": -90.5}"#).unwrap()).unwrap();
    let stopped = tests.stop().unwrap();
    assert_eq!(stopped.report_error.as_deref(), Some("the report could not be made: the feed holds too few lines"));
    assert_eq!(tests.status()["last"]["report_error"], "the report could not be made: the feed holds too few lines");
    let record: TestRecord = serde_json::from_str(&std::fs::read_to_string(stopped.folder.join("test.json")).unwrap()).unwrap();
    let m = record.method.as_ref().unwrap();
    assert_eq!((m.name.as_str(), m.version, m.standard.as_str()), ("C1609-19", 2, "astm-c1609"));
    assert_eq!(m.sha256, tagdeflect_core::method::library::sha256_hex(tagdeflect_core::method::SHIPPED[0].1.as_bytes()));
    assert!(m.review.is_none(), "not reviewed");
    assert_eq!(record.meta.standard.as_deref(), Some("astm-c1609"));
    let info = record.specimen_info.as_ref().unwrap();
    assert_eq!((info.id.as_str(), info.mix.as_deref()), ("S1", Some("C40")));
    assert!(info.age_days.is_some_and(|d| d >= 35), "{info:?}");
    assert_eq!(record.preload.as_ref().map(|p| p.load_kn), Some(0.5 + 0.01 * (ZERO_SETS - 1) as f64));
    let crack = record.crack.as_ref().unwrap();
    assert!(!crack.inside_middle_third && crack.position_mm == -90.5);
    let kinds: Vec<&str> = record.events.iter().map(|e| e.kind.as_str()).collect();
    assert_eq!(kinds, ["start", "preload", "crack", "stop"]);
    // The table: S1 tested by that test; the next is S2.
    let table = tests.specimens().unwrap();
    assert_eq!(table["next"], "S2");
    assert_eq!(table["specimens"][0]["test"], record.id.as_str());
    assert_eq!(table["specimens"][1]["tested"], false);
}

#[test]
fn a_table_is_checked_row_by_row_and_a_test_without_a_method_works_as_before() {
    let dir = tempfile::tempdir().unwrap();
    let tests = LabTests::new(dir.path(), String::new(), Vec::new(), None).unwrap();
    let Err(TestError::Bad(why)) = start(&tests, serde_json::json!({"specimen": "next"})) else { panic!() };
    assert!(why.contains("no untested specimen"), "{why}");
    let bad = br#"[{"id": "A1", "readings": {"width_mm": [150]}}, {"id": "A2", "readings": {"depth_mm": [150, 15000]}}]"#;
    let Err(TestError::Bad(why)) = super::parse_specimens(bad, false) else { panic!() };
    assert!(why.contains("row 2, column depth_mm"), "{why}");
    let Err(TestError::Bad(why)) = super::parse_specimens(br#"{"specimens": [{"id": "A1", "colour": "red"}]}"#, false) else { panic!() };
    assert!(why.contains("row 1, column colour"), "{why}");
    // Without a method, a standard and the config's beam: as before, and no preload event.
    let mut beam = std::collections::BTreeMap::new();
    for (k, v) in [("width_mm", 150.0), ("depth_mm", 150.0), ("span_mm", 450.0)] {
        beam.insert(k.to_string(), v);
    }
    tests.set_beam(beam);
    start(&tests, serde_json::json!({"specimen": "B1", "standard": "astm-c1609"})).unwrap();
    for k in 0..ZERO_SETS as i64 {
        let mut l = FeedLine { seq: k as u64, t_ns: super::tests::t(k), load_kn: Some(0.1), ..FeedLine::default() };
        tests.apply(&mut l);
    }
    tests.crack(serde_json::from_str(r#"{"position_mm": 20}"#).unwrap()).unwrap();
    let stopped = tests.stop().unwrap();
    assert_eq!(stopped.report_error, None, "no report hook: nothing failed");
    let record: TestRecord = serde_json::from_str(&std::fs::read_to_string(stopped.folder.join("test.json")).unwrap()).unwrap();
    assert!(record.method.is_none() && record.specimen_info.is_none());
    assert_eq!(record.preload.as_ref().map(|p| p.load_kn), Some(0.1));
    assert!(record.crack.as_ref().unwrap().inside_middle_third, "20 mm from mid-span of a 450 mm span");
    assert_eq!(record.events.iter().map(|e| e.kind.as_str()).collect::<Vec<_>>(), ["start", "crack", "stop"]);
}
