//! Results a lab can sign: loads from the UTM's own samples (the first peak between frame
//! sets), validity per standard, honest σ (Monte Carlo coverage); and the helpers the other
//! `report_*` files share (a synthetic test's feed and UTM stream, `report` run on it). The
//! feed reader's faults are in `report_feed_faults`, validity end to end and QC without false
//! alarms in `report_validity`, series in `report_series`, what a lab files (traceability,
//! PDF, identification, the crack entry and the method) in `report_filed`.

use std::fs;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Normal};
use tagdeflect_report::{c1609, en14651, BeamConfig, Curve, Entry};

use crate::common;

pub(crate) const T0: i64 = 1_767_225_600_000_000_000;

pub(crate) fn tagdeflect(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_tagdeflect")).args(args).env("TAGDEFLECT_LOG", "warn").output().expect("run tagdeflect")
}

pub(crate) fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

pub(crate) fn read_json(p: &Path) -> serde_json::Value {
    serde_json::from_str(&fs::read_to_string(p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))).unwrap()
}

/// The one-camera config (support tags 0, 2, midspan 1) with `[specimen.beam]` appended.
pub(crate) fn config_with_beam(dir: &Path, beam: &str) -> PathBuf {
    let base = common::one_camera_without_beam();
    let p = dir.join("rig.toml");
    fs::write(&p, format!("{base}\n[specimen.beam]\n{beam}\n")).unwrap();
    p
}

pub(crate) const C1609_BEAM: &str = "width_mm = 150.0\ndepth_mm = 150.0\nspan_mm = 450.0";
pub(crate) const EN_BEAM: &str = "width_mm = 150.0\ndepth_mm = 150.0\nspan_mm = 500.0\nnotch_mm = 25.0";

/// A synthetic test: `x(t)` ramps after `rest_s` at `rate` mm/min (EN: `rate2` after CMOD
/// 0.1 mm), load = `law(x)`; the feed every `dt_s`, the UTM every `1/utm_hz` s (phase 3 ms).
pub(crate) struct Synth {
    pub(crate) law: fn(f64) -> f64,
    pub(crate) rest_s: f64,
    pub(crate) rate: f64,
    pub(crate) rate2: Option<f64>,
    pub(crate) x_end: f64,
    pub(crate) dt_s: f64,
    pub(crate) utm_hz: f64,
    /// σ of x per line (0: exact), and of the load per UTM sample.
    pub(crate) x_sigma: f64,
    pub(crate) load_noise: f64,
    pub(crate) cmod: bool,
    pub(crate) seed: u64,
}

impl Synth {
    pub(crate) fn x_at(&self, t: f64) -> f64 {
        let s = (t - self.rest_s).max(0.0) / 60.0;
        match self.rate2 {
            Some(r2) if s * self.rate > 0.1 => 0.1 + (s - 0.1 / self.rate) * r2,
            _ => s * self.rate,
        }
    }

    pub(crate) fn duration_s(&self) -> f64 {
        let ramp = match self.rate2 {
            Some(r2) => 60.0 * (0.1 / self.rate + (self.x_end - 0.1) / r2),
            None => 60.0 * self.x_end / self.rate,
        };
        self.rest_s + ramp
    }

    /// Writes `feed.jsonl` and `utm.jsonl` into `dir`; returns the feed's path.
    pub(crate) fn write(&self, dir: &Path) -> PathBuf {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(self.seed);
        let nx = Normal::new(0.0, self.x_sigma.max(1e-300)).unwrap();
        let np = Normal::new(0.0, self.load_noise.max(1e-300)).unwrap();
        let dur = self.duration_s();
        let mut feed = String::new();
        let n = (dur / self.dt_s).floor() as usize + 1;
        for k in 0..n {
            let t = k as f64 * self.dt_s;
            let x = self.x_at(t);
            let e = if self.x_sigma > 0.0 { nx.sample(&mut rng) } else { 0.0 };
            let defl = if self.cmod { 0.85 * x } else { x + e };
            let tag = |id: u32, dz: f64| serde_json::json!({"id": id, "pos_mm": [0.0, 0.0, dz], "disp_mm": [0.0, 0.0, dz], "views": 1, "sigma_mm": [0.004, 0.01, 0.002]});
            let mut line = serde_json::json!({
                "seq": k, "t_ns": T0 + (t * 1e9).round() as i64, "load_kN": (self.law)(x), "stroke_mm": defl * 1.1,
                "tags": [tag(0, 0.0), tag(1, -defl), tag(2, 0.0)],
                "net_deflection_mm": defl, "utm": "ok", "dropped_sets": 0,
                "cameras": [{"name": "front", "frame": true, "background_tags": 5, "specimen_tags": 3, "posed": true, "drift_deg": 0.0001, "drift_mm": 0.00002}],
            });
            if self.cmod {
                line["gauges"] = serde_json::json!({"cmod": {"value": x + e, "sigma": self.x_sigma.max(0.002), "unit": "mm"}});
            }
            feed.push_str(&line.to_string());
            feed.push('\n');
        }
        let mut utm = String::new();
        let m = ((dur + 0.5) * self.utm_hz) as usize;
        for j in 0..m {
            let t = j as f64 / self.utm_hz + 0.003 - 0.25;
            let p = (self.law)(self.x_at(t)) + if self.load_noise > 0.0 { np.sample(&mut rng) } else { 0.0 };
            utm.push_str(&format!("{{\"t_ns\":{},\"load_kN\":{p},\"stroke_mm\":{}}}\n", T0 + (t * 1e9).round() as i64, self.x_at(t) * 1.1));
        }
        fs::create_dir_all(dir).unwrap();
        fs::write(dir.join("utm.jsonl"), utm).unwrap();
        let f = dir.join("feed.jsonl");
        fs::write(&f, feed).unwrap();
        f
    }
}

/// Elastic to 40 kN at 0.05 mm, a drop to 30 kN, softening to 20 kN at 0.5 mm, 10 kN at 5 mm.
pub(crate) fn softening(x: f64) -> f64 {
    if x <= 0.05 {
        800.0 * x
    } else if x <= 0.5 {
        30.0 - 10.0 * (x - 0.05) / 0.45
    } else {
        20.0 - 10.0 * (x - 0.5) / 4.5
    }
}

/// Against CMOD: elastic to 16 kN at 0.03 mm, a drop to 12 kN, then down to 8 kN at 4 mm.
pub(crate) fn notched(x: f64) -> f64 {
    if x <= 0.03 {
        16.0 / 0.03 * x
    } else {
        12.0 - 4.0 * (x - 0.03) / 3.97
    }
}

pub(crate) fn report(feed: &Path, cfg: &Path, standard: &str, out: &Path, extra: &[&str]) -> Output {
    let mut a =
        vec!["report", feed.to_str().unwrap(), "--config", cfg.to_str().unwrap(), "--standard", standard, "--out", out.to_str().unwrap()];
    a.extend_from_slice(extra);
    if !extra.contains(&"--pdf-please") {
        a.push("--no-pdf");
    }
    a.retain(|x| *x != "--pdf-please");
    tagdeflect(&a)
}

pub(crate) fn value(j: &serde_json::Value, key: &str) -> (f64, f64) {
    let q = &j[key];
    (q["value"].as_f64().unwrap_or_else(|| panic!("{key}: {q} ({})", j["undetermined"])), q["sigma"].as_f64().unwrap())
}

#[test]
pub(crate) fn the_first_peak_between_frame_sets_is_the_utm_s_peak() {
    let dir = tempfile::tempdir().unwrap();
    // 0.6 mm/min: 0.8 kN of rise per 10 Hz frame set, 0.08 kN per 100 Hz UTM sample; the
    // crack (40 kN) at 7.047 s, between the frame sets at 7.0 and 7.1 s.
    let s = Synth {
        law: softening,
        rest_s: 2.047,
        rate: 0.6,
        rate2: None,
        x_end: 0.5,
        dt_s: 0.1,
        utm_hz: 100.0,
        x_sigma: 0.0,
        load_noise: 0.0,
        cmod: false,
        seed: 1,
    };
    let feed = s.write(&dir.path().join("t1"));
    let cfg = config_with_beam(dir.path(), C1609_BEAM);
    let out = dir.path().join("r");
    let o = report(&feed, &cfg, "astm-c1609", &out, &[]);
    assert!(o.status.success(), "{}", stderr(&o));
    let j = read_json(&out.join("report.json"));
    assert_eq!(j["curve"]["load_from_utm"], true, "utm.jsonl beside the feed is used by default");
    let (p1, s1) = value(&j, "P1");
    println!("REPORT first peak from the UTM: P1 = {p1} ± {s1} kN (truth 40)");
    assert!((p1 - 40.0).abs() <= 0.005 * 40.0, "P1 {p1} within 0.5 % of 40 kN");
    assert!((p1 - 40.0).abs() <= 2.0 * s1 + 1e-9, "P1 {p1} ± {s1}: the truth within 2σ");
    assert!(s1 < 0.1, "σ {s1}: the sampling of a 100 Hz UTM");
    // The feed's own loads (frame rate): low by up to a frame's rise, and its σ says so.
    let alone = dir.path().join("alone");
    fs::create_dir_all(&alone).unwrap();
    fs::copy(&feed, alone.join("feed.jsonl")).unwrap();
    let out2 = dir.path().join("r2");
    let o = report(&alone.join("feed.jsonl"), &cfg, "astm-c1609", &out2, &[]);
    assert!(o.status.success(), "{}", stderr(&o));
    let j2 = read_json(&out2.join("report.json"));
    assert_eq!(j2["curve"]["load_from_utm"], false);
    let (q1, t1) = value(&j2, "P1");
    println!("REPORT first peak at the frame rate: P1 = {q1} ± {t1} kN (truth 40)");
    assert!(q1 < 39.8 && (q1 - 40.0).abs() <= 2.0 * t1, "frame-rate P1 {q1} ± {t1}");
    assert!(j2["notes"].as_array().unwrap().iter().any(|n| n.as_str().unwrap().contains("sampled at the frame rate")), "{}", j2["notes"]);

    // EN 14651: F_L the same way (CMOD 0.6 mm/min, crack at 16 kN between frame sets).
    let s = Synth { law: notched, rest_s: 1.043, x_end: 0.3, cmod: true, ..s };
    let feed = s.write(&dir.path().join("t2"));
    let cfg = config_with_beam(dir.path(), EN_BEAM);
    let out = dir.path().join("en");
    let o = report(&feed, &cfg, "en-14651", &out, &[]);
    assert!(o.status.success(), "{}", stderr(&o));
    let j = read_json(&out.join("report.json"));
    let (fl, sl) = value(&j, "FL");
    println!("REPORT F_L from the UTM: {fl} ± {sl} kN (truth 16)");
    assert!((fl - 16.0).abs() <= 0.005 * 16.0 && (fl - 16.0).abs() <= 2.0 * sl + 1e-9, "F_L {fl} ± {sl}");
}

/// The C1609 test at its rate (0.08 mm/min to 3.2 mm) and the EN 14651 test at its rates.
pub(crate) fn clean(cmod: bool, seed: u64) -> Synth {
    Synth {
        law: if cmod { notched } else { softening },
        rest_s: 5.0,
        rate: if cmod { 0.05 } else { 0.08 },
        rate2: cmod.then_some(0.2),
        x_end: if cmod { 3.6 } else { 3.2 },
        dt_s: 0.5,
        utm_hz: 20.0,
        x_sigma: 0.0025,
        load_noise: 0.02,
        cmod,
        seed,
    }
}

/// One line of `text` (JSON lines) with its `load_kN` set to `kn`.
pub(crate) fn with_load_at(text: &str, line: usize, kn: f64) -> String {
    let mut out = String::new();
    for (i, l) in text.lines().enumerate() {
        let mut v: serde_json::Value = serde_json::from_str(l).unwrap();
        if i == line {
            v["load_kN"] = serde_json::json!(kn);
        }
        out.push_str(&v.to_string());
        out.push('\n');
    }
    out
}

#[test]
pub(crate) fn one_glitched_load_sample_is_flagged_and_never_the_peak() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = config_with_beam(dir.path(), C1609_BEAM);
    let feed = clean(false, 5).write(&dir.path().join("t"));
    let utm = dir.path().join("t").join("utm.jsonl");
    let clean_utm = fs::read_to_string(&utm).unwrap();
    let clean_feed = fs::read_to_string(&feed).unwrap();
    // 999 kN in one UTM sample well after the first peak (about 5 s + 37.5 s in).
    fs::write(&utm, with_load_at(&clean_utm, 20 * 50, 999.0)).unwrap();
    // and, for the feed's own loads, in one feed line (the report without utm.jsonl).
    let alone = dir.path().join("alone");
    fs::create_dir_all(&alone).unwrap();
    fs::write(alone.join("feed.jsonl"), with_load_at(&clean_feed, 2 * 60, 999.0)).unwrap();
    for (what, f) in [("UTM sample", feed.clone()), ("feed line", alone.join("feed.jsonl"))] {
        let out = dir.path().join(format!("r-{}", what.replace(' ', "-")));
        let o = report(&f, &cfg, "astm-c1609", &out, &[]);
        assert!(o.status.success(), "{what}: {}", stderr(&o));
        let j = read_json(&out.join("report.json"));
        let (p1, _) = value(&j, "P1");
        let (pp, _) = value(&j, "Pp");
        let (f1, _) = value(&j, "f1");
        println!("REPORT a 999 kN {what}: P1 {p1} Pp {pp} kN f1 {f1} MPa, valid {}", j["valid"]);
        assert!((p1 - 40.0).abs() < 1.0 && (pp - 40.0).abs() < 1.0, "{what}: P1 {p1} Pp {pp} (truth 40 kN)");
        assert!((f1 - 40e3 * 450.0 / 150.0f64.powi(3)).abs() < 0.2, "{what}: f1 {f1}");
        assert_eq!(j["valid"], true, "{what}: {}", j["invalid_reasons"]);
        let w = j["qc"]["warnings"].to_string();
        assert!(w.contains("glitched load of 999 kN") && w.contains(what), "{what}: {w}");
    }
}

#[test]
pub(crate) fn a_clean_test_of_each_kind_is_valid_without_qc_warnings() {
    let dir = tempfile::tempdir().unwrap();
    for (standard, cmod, beam) in [("astm-c1609", false, C1609_BEAM), ("en-14651", true, EN_BEAM)] {
        let feed = clean(cmod, 5).write(&dir.path().join(standard));
        let cfg = config_with_beam(dir.path(), beam);
        let out = dir.path().join(format!("{standard}-r"));
        let o = report(&feed, &cfg, standard, &out, &["--specimen", "B12", "--operator", "A. Tester", "--cast-date", "2025-11-03"]);
        assert!(o.status.success(), "{}", stderr(&o));
        let j = read_json(&out.join("report.json"));
        println!("REPORT clean {standard}: valid {} rates {}", j["valid"], j["rates"]);
        assert_eq!(j["valid"], true, "{standard}: {}", j["invalid_reasons"]);
        assert_eq!(j["invalid_reasons"].as_array().unwrap().len(), 0);
        assert_eq!(j["qc"]["warnings"].as_array().unwrap().len(), 0, "{standard}: {}", j["qc"]["warnings"]);
        assert_eq!(j["specimen"]["id"], "B12");
        assert_eq!(j["specimen"]["age_days"], 59, "2025-11-03 to 2026-01-01");
        let html = fs::read_to_string(out.join("report.html")).unwrap();
        assert!(html.contains("Valid test of") && html.contains("No warnings.") && html.contains("B12"));
    }
}

/// Deflection-hardening (UHPC-like): elastic to 30 kN at 0.05 mm, rising after the first crack
/// to its peak 45 kN at 3.1 mm (beyond L/150 = 3 mm), then falling.
pub(crate) fn hardening(x: f64) -> f64 {
    if x <= 0.05 {
        600.0 * x
    } else if x <= 3.1 {
        30.0 + 15.0 * (x - 0.05) / 3.05
    } else {
        45.0 - 20.0 * (x - 3.1)
    }
}

/// A deflection-hardening beam whose first zero slope lies beyond L/150: invalid as a
/// softening specimen (the reason names the option), valid once the lab states the hardening
/// response (`--response hardening`, or `[report] response`), P1 = Pp at the peak.
#[test]
pub(crate) fn a_stated_hardening_response_accepts_a_first_peak_beyond_l_150() {
    let dir = tempfile::tempdir().unwrap();
    let feed = Synth { law: hardening, x_end: 3.3, ..clean(false, 9) }.write(&dir.path().join("h"));
    let cfg = config_with_beam(dir.path(), C1609_BEAM);
    let out = dir.path().join("soft");
    let o = report(&feed, &cfg, "astm-c1609", &out, &[]);
    assert!(o.status.success(), "{}", stderr(&o));
    let j = read_json(&out.join("report.json"));
    assert_eq!(j["response"], "softening");
    assert_eq!(j["valid"], false);
    let reasons = j["invalid_reasons"].to_string();
    assert!(reasons.contains("beyond L/150") && reasons.contains("response = \\\"hardening\\\""), "{reasons}");
    for (how, extra) in [("flag", vec!["--response", "hardening"]), ("config", vec![])] {
        let cfg = if how == "config" {
            fs::create_dir_all(dir.path().join("cfg")).unwrap();
            let c = config_with_beam(&dir.path().join("cfg"), C1609_BEAM);
            let text = fs::read_to_string(&c).unwrap();
            fs::write(&c, format!("{text}\n[report]\nstandard = \"astm-c1609\"\nout = \"reports\"\nresponse = \"hardening\"\n")).unwrap();
            c
        } else {
            cfg.clone()
        };
        let out = dir.path().join(format!("hard-{how}"));
        let o = report(&feed, &cfg, "astm-c1609", &out, &extra);
        assert!(o.status.success(), "{how}: {}", stderr(&o));
        let j = read_json(&out.join("report.json"));
        println!(
            "REPORT hardening ({how}): valid {} P1 {} at {} mm, unchecked {}",
            j["valid"], j["P1"], j["delta1"], j["validity_unchecked"]
        );
        assert_eq!(j["response"], "hardening", "{how}");
        assert_eq!(j["valid"], true, "{how}: {}", j["invalid_reasons"]);
        assert!(j["validity_unchecked"].to_string().contains("hardening response was stated"), "{how}: {}", j["validity_unchecked"]);
        let ((p1, _), (pp, _), (d1, _)) = (value(&j, "P1"), value(&j, "Pp"), value(&j, "delta1"));
        assert!((p1 - 45.0).abs() < 0.2 && p1 == pp && (d1 - 3.1).abs() < 0.02, "{how}: P1 {p1} Pp {pp} δ1 {d1}");
        let html = fs::read_to_string(out.join("report.html")).unwrap();
        assert!(html.contains("deflection-hardening response stated"), "{how}: the HTML names the stated response");
    }
    // A value the option does not know is a located config error.
    fs::create_dir_all(dir.path().join("bad")).unwrap();
    let c = config_with_beam(&dir.path().join("bad"), C1609_BEAM);
    let text = fs::read_to_string(&c).unwrap();
    fs::write(&c, format!("{text}\n[report]\nstandard = \"astm-c1609\"\nout = \"reports\"\nresponse = \"hardned\"\n")).unwrap();
    let o = report(&feed, &c, "astm-c1609", &dir.path().join("bad-out"), &[]);
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(stderr(&o).contains("response"), "{}", stderr(&o));
}

#[test]
pub(crate) fn the_demo_feed_is_not_a_valid_test() {
    let dir = tempfile::tempdir().unwrap();
    // The demo's own feed: an elastic beam loaded in cycles, never cracked.
    let o = tagdeflect(&["demo", "--duration-s", "14", "--no-http"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let feed = dir.path().join("feed.jsonl");
    fs::write(&feed, &o.stdout).unwrap();
    let mut cfg = tagdeflect::config::Config::demo();
    cfg.specimen.beam = Some(BeamConfig { width_mm: 150.0, depth_mm: 150.0, span_mm: 450.0, ..Default::default() });
    let path = dir.path().join("demo.toml");
    fs::write(&path, cfg.to_toml_string()).unwrap();
    let out = dir.path().join("r");
    let o = report(&feed, &path, "astm-c1609", &out, &[]);
    assert!(o.status.success(), "a report is written, marked invalid: {}", stderr(&o));
    let j = read_json(&out.join("report.json"));
    let reasons: Vec<String> = j["invalid_reasons"].as_array().unwrap().iter().map(|r| r.as_str().unwrap().to_string()).collect();
    println!("REPORT demo feed: valid {} — {reasons:#?}", j["valid"]);
    assert_eq!(j["valid"], false);
    assert!(reasons.iter().any(|r| r.contains("first peak") || r.contains("No first peak")), "{reasons:?}");
    assert!(reasons.iter().any(|r| r.contains("mm/min")), "the rate is far from the standard's: {reasons:?}");
    let html = fs::read_to_string(out.join("report.html")).unwrap();
    let banner = html.find("Not a valid test").expect("the banner");
    assert!(banner < html.find("<h2>Results").unwrap(), "the verdict comes before the values");
}

// ----------------------------------------------------------------------------------------
// Monte Carlo: ~95 % of the truths within 2σ.

/// One simulated test through the library: truth law, feed at 10 Hz with the x noise its σ
/// says, UTM at 100 Hz with load noise and resolution, a clock offset known to its σ
/// (`common::simulated_utm_curve`), the beam's true dimensions within the config's tolerances. Returns the report's entries and
/// the truth's (a noise-free, densely sampled curve with the true dimensions).
pub(crate) fn mc_trial(rng: &mut rand_chacha::ChaCha8Rng, cmod: bool) -> (Vec<Entry>, Vec<Entry>) {
    let law: fn(f64) -> f64 = if cmod { notched } else { softening };
    let (rate, x_end) = if cmod { (1.2, 3.7) } else { (0.9, 3.2) }; // mm/min
    let x_at = |t: f64| ((t - 2.0).max(0.0) / 60.0 * rate).min(x_end);
    let dur = 2.0 + 60.0 * x_end / rate + 1.0;
    let sx = 0.003;
    let nominal = if cmod {
        BeamConfig { width_mm: 150.0, depth_mm: 150.0, span_mm: 500.0, notch_mm: Some(25.0), ..Default::default() }
    } else {
        BeamConfig { width_mm: 150.0, depth_mm: 150.0, span_mm: 450.0, ..Default::default() }
    };
    let tol =
        BeamConfig { width_tol_mm: Some(0.5), depth_tol_mm: Some(0.5), span_tol_mm: Some(1.0), notch_tol_mm: Some(0.3), ..nominal.clone() };
    let mut truth_beam = nominal.clone();
    truth_beam.width_mm += rng.gen_range(-0.5..0.5);
    truth_beam.depth_mm += rng.gen_range(-0.5..0.5);
    truth_beam.span_mm += rng.gen_range(-1.0..1.0);
    if let Some(n) = truth_beam.notch_mm.as_mut() {
        *n += rng.gen_range(-0.3..0.3);
    }
    let curve = common::simulated_utm_curve(rng, &law, &x_at, dur, sx, "x");
    let got = if cmod { en14651::compute(&curve, &tol) } else { c1609::compute(&curve, &tol) };
    // Truth: the law sampled every µm-equivalent 1 ms, no noise, true dimensions.
    let m = (dur * 1000.0) as usize;
    let tt: Vec<i64> = (0..m).map(|k| T0 + k as i64 * 1_000_000).collect();
    let xt: Vec<f64> = (0..m).map(|k| x_at(k as f64 * 1e-3)).collect();
    let pt: Vec<f64> = xt.iter().map(|&x| law(x)).collect();
    let truth_curve = Curve::new(tt, pt, xt, vec![Some(0.0); m], 0.0, 1, 0.0, "truth").unwrap();
    let want = if cmod { en14651::compute(&truth_curve, &truth_beam) } else { c1609::compute(&truth_curve, &truth_beam) };
    (got, want)
}

#[test]
pub(crate) fn monte_carlo_about_95_percent_of_truths_within_2_sigma() {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(2026);
    for (cmod, keys) in
        [(false, &["P1", "delta1", "f1", "f150", "T150", "RT150"][..]), (true, &["FL", "fL", "fR1", "fR2", "fR3", "fR4"][..])]
    {
        let trials = 150;
        let mut within = vec![0usize; keys.len()];
        let mut within1 = vec![0usize; keys.len()];
        for _ in 0..trials {
            let (got, want) = mc_trial(&mut rng, cmod);
            for (k, key) in keys.iter().enumerate() {
                let g = got.iter().find(|e| e.key == *key).unwrap().result.as_ref().unwrap_or_else(|e| panic!("{key}: {e}"));
                let w = want.iter().find(|e| e.key == *key).unwrap().result.as_ref().unwrap().value;
                within[k] += ((g.value - w).abs() <= 2.0 * g.sigma) as usize;
                within1[k] += ((g.value - w).abs() <= g.sigma) as usize;
            }
        }
        for (k, key) in keys.iter().enumerate() {
            let c2 = 100.0 * within[k] as f64 / trials as f64;
            let c1 = 100.0 * within1[k] as f64 / trials as f64;
            println!("REPORT Monte Carlo {key}: {c2:.1} % of {trials} truths within 2σ, {c1:.1} % within 1σ");
            // ~95 % within 2σ (binomial 2σ band of 150 trials: ±3.6 %): an honest σ, not a
            // σ so large that everything is within 1σ. Measured (seed 2026, 2026-12-07):
            // within 1σ 60.0 % (f_L) to 84.0 % (RT150), within 2σ 93.3–100 %; the ceiling of
            // 90 % within 1σ is the largest plus its binomial 2σ (±6 %). A doubled σ puts
            // within 1σ what was within 2σ: F_L 93.3 %, f_L 95.3 % (97 % let those through).
            assert!((88.0..=100.0).contains(&c2), "{key}: {c2} % within 2σ");
            assert!(c1 <= 90.0, "{key}: {c1} % within 1σ — σ too large");
        }
    }
}

pub(crate) fn put(p: &Path, lines: &[String]) {
    fs::write(p, lines.join("\n") + "\n").unwrap();
}

pub(crate) fn invalid_reasons(j: &serde_json::Value) -> Vec<String> {
    j["invalid_reasons"].as_array().unwrap().iter().map(|r| r.as_str().unwrap().to_string()).collect()
}

pub(crate) fn qc_warnings(j: &serde_json::Value) -> Vec<String> {
    j["qc"]["warnings"].as_array().unwrap().iter().map(|r| r.as_str().unwrap().to_string()).collect()
}
