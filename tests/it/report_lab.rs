//! Results a lab can sign: loads from the UTM's own samples (the first peak between frame
//! sets), validity per standard, honest σ (Monte Carlo coverage), QC without false alarms,
//! series, traceability (input hashes, `report verify`), the PDF; and the faults of the
//! report's feed reader (restarts, gaps in time, absurd values, huge lines, export's outputs).

use std::fs;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Normal};
use tagdeflect_report::{c1609, en14651, BeamConfig, Curve, Entry};

use crate::common;

const T0: i64 = 1_767_225_600_000_000_000;

fn tagdeflect(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_tagdeflect")).args(args).env("TAGDEFLECT_LOG", "warn").output().expect("run tagdeflect")
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

fn read_json(p: &Path) -> serde_json::Value {
    serde_json::from_str(&fs::read_to_string(p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))).unwrap()
}

/// The one-camera config (support tags 0, 2, midspan 1) with `[specimen.beam]` appended.
fn config_with_beam(dir: &Path, beam: &str) -> PathBuf {
    let base = common::one_camera_without_beam();
    let p = dir.join("rig.toml");
    fs::write(&p, format!("{base}\n[specimen.beam]\n{beam}\n")).unwrap();
    p
}

const C1609_BEAM: &str = "width_mm = 150.0\ndepth_mm = 150.0\nspan_mm = 450.0";
const EN_BEAM: &str = "width_mm = 150.0\ndepth_mm = 150.0\nspan_mm = 500.0\nnotch_mm = 25.0";

/// A synthetic test: `x(t)` ramps after `rest_s` at `rate` mm/min (EN: `rate2` after CMOD
/// 0.1 mm), load = `law(x)`; the feed every `dt_s`, the UTM every `1/utm_hz` s (phase 3 ms).
struct Synth {
    law: fn(f64) -> f64,
    rest_s: f64,
    rate: f64,
    rate2: Option<f64>,
    x_end: f64,
    dt_s: f64,
    utm_hz: f64,
    /// σ of x per line (0: exact), and of the load per UTM sample.
    x_sigma: f64,
    load_noise: f64,
    cmod: bool,
    seed: u64,
}

impl Synth {
    fn x_at(&self, t: f64) -> f64 {
        let s = (t - self.rest_s).max(0.0) / 60.0;
        match self.rate2 {
            Some(r2) if s * self.rate > 0.1 => 0.1 + (s - 0.1 / self.rate) * r2,
            _ => s * self.rate,
        }
    }

    fn duration_s(&self) -> f64 {
        let ramp = match self.rate2 {
            Some(r2) => 60.0 * (0.1 / self.rate + (self.x_end - 0.1) / r2),
            None => 60.0 * self.x_end / self.rate,
        };
        self.rest_s + ramp
    }

    /// Writes `feed.jsonl` and `utm.jsonl` into `dir`; returns the feed's path.
    fn write(&self, dir: &Path) -> PathBuf {
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
fn softening(x: f64) -> f64 {
    if x <= 0.05 {
        800.0 * x
    } else if x <= 0.5 {
        30.0 - 10.0 * (x - 0.05) / 0.45
    } else {
        20.0 - 10.0 * (x - 0.5) / 4.5
    }
}

/// Against CMOD: elastic to 16 kN at 0.03 mm, a drop to 12 kN, then down to 8 kN at 4 mm.
fn notched(x: f64) -> f64 {
    if x <= 0.03 {
        16.0 / 0.03 * x
    } else {
        12.0 - 4.0 * (x - 0.03) / 3.97
    }
}

fn report(feed: &Path, cfg: &Path, standard: &str, out: &Path, extra: &[&str]) -> Output {
    let mut a =
        vec!["report", feed.to_str().unwrap(), "--config", cfg.to_str().unwrap(), "--standard", standard, "--out", out.to_str().unwrap()];
    a.extend_from_slice(extra);
    if !extra.contains(&"--pdf-please") {
        a.push("--no-pdf");
    }
    a.retain(|x| *x != "--pdf-please");
    tagdeflect(&a)
}

fn value(j: &serde_json::Value, key: &str) -> (f64, f64) {
    let q = &j[key];
    (q["value"].as_f64().unwrap_or_else(|| panic!("{key}: {q} ({})", j["undetermined"])), q["sigma"].as_f64().unwrap())
}

#[test]
fn the_first_peak_between_frame_sets_is_the_utm_s_peak() {
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
fn clean(cmod: bool, seed: u64) -> Synth {
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
fn with_load_at(text: &str, line: usize, kn: f64) -> String {
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
fn one_glitched_load_sample_is_flagged_and_never_the_peak() {
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
fn a_clean_test_of_each_kind_is_valid_without_qc_warnings() {
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
fn hardening(x: f64) -> f64 {
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
fn a_stated_hardening_response_accepts_a_first_peak_beyond_l_150() {
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
fn the_demo_feed_is_not_a_valid_test() {
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
/// says, UTM at 100 Hz with load noise and resolution, a clock offset known to its σ, the
/// beam's true dimensions within the config's tolerances. Returns the report's entries and
/// the truth's (a noise-free, densely sampled curve with the true dimensions).
fn mc_trial(rng: &mut rand_chacha::ChaCha8Rng, cmod: bool) -> (Vec<Entry>, Vec<Entry>) {
    let law: fn(f64) -> f64 = if cmod { notched } else { softening };
    let (rate, x_end) = if cmod { (1.2, 3.7) } else { (0.9, 3.2) }; // mm/min
    let x_at = |t: f64| ((t - 2.0).max(0.0) / 60.0 * rate).min(x_end);
    let dur = 2.0 + 60.0 * x_end / rate + 1.0;
    let sx = 0.003;
    let ref_sigma = 0.001;
    let (load_noise, res) = (0.03, 0.01);
    let (offset_s, offset_sigma_s) = (0.020, 0.004);
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
    let nx = Normal::new(0.0, sx).unwrap();
    let np = Normal::new(0.0, load_noise).unwrap();
    let ref_err = Normal::new(0.0, ref_sigma).unwrap().sample(rng);
    // The alignment's error: the UTM stamps are off by what the clock check did not catch.
    let t_err = Normal::new(0.0, offset_sigma_s).unwrap().sample(rng);
    let phase: f64 = rng.gen_range(0.0..0.01);
    let n = (dur / 0.1) as usize;
    let t_ns: Vec<i64> = (0..n).map(|k| T0 + k as i64 * 100_000_000).collect();
    let x: Vec<f64> = (0..n).map(|k| x_at(k as f64 * 0.1) + ref_err + nx.sample(rng)).collect();
    let p_frames: Vec<f64> = (0..n).map(|k| law(x_at(k as f64 * 0.1))).collect();
    let feed_curve = Curve::new(t_ns, p_frames, x, vec![Some(sx); n], ref_sigma, 5, res, "x").unwrap();
    let utm: Vec<tagdeflect_io::utm::UtmSample> = (0..(dur * 100.0) as usize)
        .map(|j| {
            let t_true = j as f64 * 0.01 + phase;
            let p = law(x_at(t_true)) + np.sample(rng);
            let p = (p / res).round() * res;
            // Stamped on the UTM clock (offset ahead), taken at t_true.
            let stamp = t_true + offset_s + t_err;
            tagdeflect_io::utm::UtmSample { t_ns: T0 + (stamp * 1e9).round() as i64, load_kn: p, stroke_mm: None }
        })
        .collect();
    let curve = feed_curve.on_utm(&utm, (offset_s * 1e9).round() as i64, offset_sigma_s, res, 2.0).unwrap();
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
fn monte_carlo_about_95_percent_of_truths_within_2_sigma() {
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

// ----------------------------------------------------------------------------------------
// Faults of the feed reader and of export.

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

fn put(p: &Path, lines: &[String]) {
    fs::write(p, lines.join("\n") + "\n").unwrap();
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

// ----------------------------------------------------------------------------------------
// Series, traceability, PDF.

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

// ----------------------------------------------------------------------------------------
// Validity end to end: the UTM stream's gaps and outages, a test stopped early.

fn invalid_reasons(j: &serde_json::Value) -> Vec<String> {
    j["invalid_reasons"].as_array().unwrap().iter().map(|r| r.as_str().unwrap().to_string()).collect()
}

fn qc_warnings(j: &serde_json::Value) -> Vec<String> {
    j["qc"]["warnings"].as_array().unwrap().iter().map(|r| r.as_str().unwrap().to_string()).collect()
}

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

// ----------------------------------------------------------------------------------------
// QC without false alarms: every standard, every load law.

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

// ----------------------------------------------------------------------------------------
// What a lab files, rounding, traceability.

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
