//! The feed reader's tests.

use super::*;

fn parse(text: &str) -> Result<Vec<Feed>, ReportError> {
    Feed::parse(text, Path::new("f.jsonl"), &ReadOptions::default())
}

#[test]
fn reads_lines_other_writers_leave_short_and_skips_a_truncated_last_one() {
    let text = concat!(
        r#"{"seq":0,"t_ns":10,"tags":[{"id":4,"pos_mm":[0,0,0],"disp_mm":[0,0,-1]}],"gauges":{"cmod":{"value":0.0,"sigma":0.002,"unit":"mm"}}}"#,
        "\n",
        r#"{"seq":1,"t_ns":20,"load_kN":1.5,"gauges":{"cmod":{"value":0.1}},"cameras":[{"name":"left"}],"drift_px":3}"#,
        "\n",
        r#"{"seq":2,"t_ns":30,"tags":[{"id""#,
    );
    let feed = parse(text).unwrap().remove(0);
    assert_eq!(feed.columns.seq, vec![0, 1], "the cut line skipped");
    assert_eq!(feed.warnings, vec!["f.jsonl:3: truncated last line skipped".to_string()]);
    assert_eq!(feed.gauge_names(), vec!["cmod".to_string()]);
    assert_eq!(feed.gauge_unit("cmod").as_deref(), Some("mm"), "from the first line that names one");
    let cmod = feed.columns.gauge("cmod").unwrap();
    assert_eq!((cmod.value[1], cmod.sigma[0]), (0.1, 0.002));
    assert!(cmod.sigma[1].is_nan(), "σ not given");
    assert_eq!((feed.columns.load(0), feed.columns.load(1)), (None, Some(1.5)));
    assert_eq!(feed.summary.cameras["left"], crate::feed_summary::CameraTally::default(), "framed and posed by default");
    assert_eq!(feed.tag_ids(), vec![4]);
    let mut tags = Vec::new();
    feed.for_each_line(|k, l| tags.push((k, l.tags.iter().map(|t| t.disp_mm[2]).collect::<Vec<_>>()))).unwrap();
    assert_eq!(tags, vec![(0, vec![-1.0]), (1, vec![])], "read again");
    let e = parse("{\"seq\":0,\"t_ns\":\"soon\"}\n").unwrap_err();
    assert!(e.to_string().starts_with("f.jsonl:1: not a feed line"), "{e}");
}

#[test]
fn a_seq_going_back_or_repeating_is_an_error_or_a_new_run() {
    let l = |seq: u64, t: i64| format!("{{\"seq\":{seq},\"t_ns\":{t},\"load_kN\":1.0}}\n");
    let restart = [l(0, 10), l(1, 20), l(0, 30), l(1, 40), l(2, 50)].concat();
    let e = parse(&restart).unwrap_err().to_string();
    assert!(e.starts_with("f.jsonl:3: not a feed line: seq 0 goes back from seq 1 of line 2"), "{e}");
    let e = parse(&[l(0, 10), l(1, 20), l(1, 30)].concat()).unwrap_err().to_string();
    assert!(e.starts_with("f.jsonl:3:") && e.contains("seq 1 repeats seq 1"), "{e}");
    let e = parse(&[l(0, 10), l(1, 5)].concat()).unwrap_err().to_string();
    assert!(e.starts_with("f.jsonl:2:") && e.contains("t_ns 5 is not after"), "{e}");
    let runs = Feed::parse(&restart, Path::new("f.jsonl"), &ReadOptions { allow_restarts: true, ..Default::default() }).unwrap();
    assert_eq!(runs.len(), 2);
    assert_eq!((runs[0].len(), runs[1].len()), (2, 3));
    let mut seqs = Vec::new();
    runs[1].for_each_line(|_, l| seqs.push(l.seq)).unwrap();
    assert_eq!(seqs, vec![0, 1, 2], "the second run read again from its own first line");
    assert_eq!(runs[1].run, Some((2, 2)));
    assert_eq!(runs[1].line_numbers, vec![3, 4, 5]);
}

/// A lab test's feed across a restart of its daemon: seq 75–79, then
/// the resumed daemon's seq 0–9 after a 12 s hole, its first line with the `resume` event.
fn resumed_test_feed(with_event: bool) -> String {
    const T0: i64 = 1_764_000_000_000_000_000;
    let test = r#""test":{"id":"20261202T013000Z-B12","specimen":"B12"}"#;
    let mut text = String::new();
    let mut line = |seq: u64, t_ns: i64, events: &str| {
        let x = (t_ns - T0) as f64 * 1e-9 * 0.01;
        text.push_str(&format!(
            "{{\"seq\":{seq},\"t_ns\":{t_ns},\"load_kN\":{:.3},\"net_deflection_mm\":{x:.6},{test}{events}}}\n",
            10.0 + 300.0 * x
        ));
    };
    for k in 0..5 {
        line(75 + k, T0 + k as i64 * 200_000_000, "");
    }
    let t1 = T0 + 800_000_000 + 12_000_000_000;
    for k in 0..10 {
        let ev = if k == 0 && with_event {
            format!(r#","events":[{{"kind":"{RESUME_EVENT}","t_ns":{}}}]"#, t1 - 50_000_000)
        } else {
            String::new()
        };
        line(k, t1 + k as i64 * 200_000_000, &ev);
    }
    text
}

/// With the `resume` event the seq restart is one test read across it, the hole named in
/// the feed's warnings and counted as a gap by QC and validity; without it the same feed
/// is refused, naming the line; a resume whose time goes back is refused too.
#[test]
fn a_resumed_test_is_one_test_across_its_seq_restart_and_its_hole_is_a_gap() {
    let text = resumed_test_feed(true);
    for allow_restarts in [false, true] {
        let runs = Feed::parse(&text, Path::new("f.jsonl"), &ReadOptions { allow_restarts, ..Default::default() }).unwrap();
        assert_eq!(runs.len(), 1, "one test, not two runs (allow_restarts {allow_restarts})");
        let feed = &runs[0];
        assert_eq!(feed.run, None);
        assert_eq!(feed.columns.seq, [75, 76, 77, 78, 79, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9]);
        assert_eq!(feed.line_numbers, (1..=15).collect::<Vec<_>>());
        assert_eq!(feed.columns.resumes, vec![5]);
        assert_eq!(feed.warnings.len(), 1, "{:?}", feed.warnings);
        let w = &feed.warnings[0];
        assert!(w.starts_with("f.jsonl:6: the daemon restarted during the test") && w.contains("no lines for 12.0 s after line 5"), "{w}");
        assert!(w.contains("seq 0 after seq 79"), "{w}");
    }

    // The report reads it as one test: the hole is one gap in time for QC (with the
    // reader's warning) and for validity.
    let feed = Feed::parse(&text, Path::new("f.jsonl"), &ReadOptions::default()).unwrap().remove(0);
    let specimen: tagdeflect_core::rig::SpecimenConfig = serde_json::from_value(serde_json::json!({
        "family": "tag36h11", "size_mm": 30.0, "tag": [],
        "beam": {"width_mm": 150.0, "depth_mm": 150.0, "span_mm": 450.0},
    }))
    .unwrap();
    let rig = crate::TestRig { world: Default::default(), specimen, gauges: Vec::new() };
    let opts = crate::ReportConfig::new(crate::Standard::AstmC1609, "out".into());
    let rep = crate::build(&feed, None, &rig, Path::new("rig.toml"), &opts).unwrap();
    assert_eq!(rep.qc.time_gaps.len(), 1, "{:?}", rep.qc.time_gaps);
    assert!((rep.qc.time_gaps[0].duration_s - 12.0).abs() < 1e-6, "{:?}", rep.qc.time_gaps);
    assert!(rep.qc.warnings.iter().any(|w| w.contains("the daemon restarted during the test")), "{:?}", rep.qc.warnings);
    assert!(rep.qc.warnings.iter().any(|w| w.starts_with("1 gap(s) in time")), "{:?}", rep.qc.warnings);
    assert!(!rep.validity.valid && rep.validity.reasons.iter().any(|r| r.contains("gap(s)")), "{:?}", rep.validity.reasons);

    // The same feed without the event: two runs appended, refused naming the line.
    let e = parse(&resumed_test_feed(false)).unwrap_err().to_string();
    assert!(e.starts_with("f.jsonl:6: not a feed line: seq 0 goes back from seq 79 of line 5"), "{e}");
    assert!(e.contains("`resume` event"), "{e}");
    // A resume whose time goes back, or a resume after a line of another test, is refused.
    let back = text.replacen(
        &format!("\"t_ns\":{}", 1_764_000_000_000_000_000i64 + 800_000_000 + 12_000_000_000),
        "\"t_ns\":1764000000000000000",
        1,
    );
    let e = parse(&back).unwrap_err().to_string();
    assert!(e.starts_with("f.jsonl:6: not a feed line: t_ns 1764000000000000000 is not after"), "{e}");
    let mut other: Vec<String> = text.lines().map(String::from).collect();
    for l in &mut other[5..] {
        *l = l.replace("-B12\"", "-B13\"");
    }
    let e = parse(&(other.join("\n") + "\n")).unwrap_err().to_string();
    assert!(e.starts_with("f.jsonl:6: not a feed line: seq 0 goes back from seq 79 of line 5"), "{e}");
}

#[test]
fn absurd_values_are_errors_naming_the_field() {
    let cases = [
        (r#"{"seq":0,"t_ns":10,"load_kN":1e308}"#, "load_kN = 1e308"),
        (r#"{"seq":0,"t_ns":10,"load_kN":-3e38}"#, "load_kN = -3"),
        (r#"{"seq":0,"t_ns":-9223372036854775808}"#, "t_ns -9223372036854775808"),
        (r#"{"seq":0,"t_ns":9223372036854775807}"#, "t_ns 9223372036854775807"),
        (r#"{"seq":18446744073709551615,"t_ns":10}"#, "seq 18446744073709551615"),
        (r#"{"seq":0,"t_ns":10,"net_deflection_mm":1e20}"#, "net_deflection_mm"),
        (r#"{"seq":0,"t_ns":10,"gauges":{"cmod":{"value":1e300,"unit":"mm"}}}"#, "gauge cmod"),
        (r#"{"seq":0,"t_ns":10,"tags":[{"id":3,"pos_mm":[0,0,1e99],"disp_mm":[0,0,0]}]}"#, "tag 3 pos_mm"),
    ];
    for (line, want) in cases {
        let e = parse(&format!("{line}\n")).unwrap_err().to_string();
        assert!(e.starts_with("f.jsonl:1: not a feed line") && e.contains(want), "{line}: {e}");
    }
}

/// Read line by line as parsed whole (a `\r\n`, a cut last line); a non-UTF-8 line named.
#[test]
fn a_feed_read_line_by_line_is_the_feed_parsed_whole() {
    let dir = tempfile::tempdir().unwrap();
    let text = [resumed_test_feed(true).replacen('\n', "\r\n", 2), "\n{\"seq\":99,\"t_ns\":9".into()].concat();
    let path = dir.path().join("f.jsonl");
    std::fs::write(&path, &text).unwrap();
    let (streamed, whole) =
        (Feed::read_runs(&path, &ReadOptions::default()).unwrap(), Feed::parse(&text, &path, &ReadOptions::default()).unwrap());
    assert_eq!((streamed.len(), streamed[0].len()), (1, 15));
    assert_eq!(
        (&streamed[0].columns, &streamed[0].line_numbers, &streamed[0].warnings, &streamed[0].summary),
        (&whole[0].columns, &whole[0].line_numbers, &whole[0].warnings, &whole[0].summary)
    );
    let again = |f: &Feed| {
        let mut v = Vec::new();
        f.for_each_line(|k, l| v.push((k, l.seq, l.t_ns))).unwrap();
        v
    };
    assert_eq!(again(&streamed[0]), again(&whole[0]));
    assert_eq!(again(&streamed[0]).len(), 15);
    assert!(streamed[0].warnings.iter().any(|w| w.contains(":17: truncated last line skipped")), "{:?}", streamed[0].warnings);
    std::fs::write(&path, [&b"{\"seq\":0,\"t_ns\":1}\n\xff\n"[..], text.as_bytes()].concat()).unwrap();
    let e = Feed::read_runs(&path, &ReadOptions::default()).unwrap_err().to_string();
    assert!(e.contains("f.jsonl:2: not a feed line: not UTF-8"), "{e}");
}
