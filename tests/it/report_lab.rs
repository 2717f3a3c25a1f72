//! Results a lab can sign: loads from the UTM's own samples (the first peak between frame
//! sets), validity per standard, honest σ (Monte Carlo coverage), QC without false alarms,
//! series, traceability (input hashes, `report verify`), the PDF; and the faults of the
//! report's feed reader (restarts, gaps in time, absurd values, huge lines, export's outputs).

use std::fs;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Normal};
use tagdeflect::report::{c1609, en14651, BeamConfig, Curve, Entry};

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
    let base = fs::read_to_string(common::root().join("config/one-camera.toml")).unwrap();
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
    let utm: Vec<tagdeflect::utm::UtmSample> = (0..(dur * 100.0) as usize)
        .map(|j| {
            let t_true = j as f64 * 0.01 + phase;
            let p = law(x_at(t_true)) + np.sample(rng);
            let p = (p / res).round() * res;
            // Stamped on the UTM clock (offset ahead), taken at t_true.
            let stamp = t_true + offset_s + t_err;
            tagdeflect::utm::UtmSample { t_ns: T0 + (stamp * 1e9).round() as i64, load_kn: p, stroke_mm: None }
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
            // σ so large that everything is within 1σ.
            assert!((88.0..=100.0).contains(&c2), "{key}: {c2} % within 2σ");
            assert!(c1 < 97.0, "{key}: {c1} % within 1σ — σ too large");
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
    assert!(String::from_utf8_lossy(&o.stdout).contains("every input as when the report was made (3 files)"));
    // One changed byte of the UTM stream.
    let utm = dir.path().join("t/utm.jsonl");
    let text = fs::read_to_string(&utm).unwrap();
    fs::write(&utm, text.replacen("\"load_kN\":", "\"load_kN\": ", 1)).unwrap();
    let o = tagdeflect(&["report", "verify", out.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(2));
    let so = String::from_utf8_lossy(&o.stdout);
    assert!(so.contains("CHANGED  utm") && so.contains("same     feed"), "{so}");
    assert!(stderr(&o).contains("1 input(s) differ"), "{}", stderr(&o));
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
