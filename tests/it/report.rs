//! The test report (SPEC "Report"): the standards' quantities on synthetic curves with
//! closed-form answers, the first peak on noisy and strain-hardening curves, the CLI's
//! outputs (JSON keys, CSV read back by Python's csv module, the HTML rendered by headless
//! Chromium), bad feeds, `[specimen.beam]` validation and the report at the end of `run`.

use std::fs;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use tagdeflect_report::{c1609, en14651, BeamConfig, Curve, Entry, Quantity};

use crate::common;

const T0: i64 = 1_767_225_600_000_000_000;
const DT: i64 = 100_000_000; // 10 Hz

/// The ASTM C1609 reference specimen: 150 × 150 mm, span 450 mm (L/600 = 0.75, L/150 = 3).
const ASTM_BEAM: BeamConfig = BeamConfig {
    width_mm: 150.0,
    depth_mm: 150.0,
    span_mm: 450.0,
    notch_mm: None,
    width_tol_mm: None,
    depth_tol_mm: None,
    span_tol_mm: None,
    notch_tol_mm: None,
};
/// The EN 14651 specimen: 150 × 150 mm, notch 25 mm (h_sp = 125 mm), span 500 mm.
const EN_BEAM: BeamConfig = BeamConfig {
    width_mm: 150.0,
    depth_mm: 150.0,
    span_mm: 500.0,
    notch_mm: Some(25.0),
    width_tol_mm: None,
    depth_tol_mm: None,
    span_tol_mm: None,
    notch_tol_mm: None,
};

/// Piecewise-linear load through `(x, P)` vertices.
fn piecewise(v: &[(f64, f64)], x: f64) -> f64 {
    for w in v.windows(2) {
        let ((x0, p0), (x1, p1)) = (w[0], w[1]);
        if x <= x1 {
            return p0 + (p1 - p0) * (x - x0) / (x1 - x0);
        }
    }
    v[v.len() - 1].1
}

/// A curve sampled at `x = k·step` (uniform in time) with optional noise on x and load.
fn sampled(v: &[(f64, f64)], step: f64, x_end: f64, x_sigma: f64, load_noise: f64, seed: u64) -> Curve {
    let n = (x_end / step).round() as usize + 1;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let nx = Normal::new(0.0, x_sigma.max(1e-300)).unwrap();
    let np = Normal::new(0.0, load_noise.max(1e-300)).unwrap();
    let t: Vec<i64> = (0..n).map(|k| T0 + k as i64 * DT).collect();
    let xt: Vec<f64> = (0..n).map(|k| k as f64 * step).collect();
    let x: Vec<f64> = xt.iter().map(|&x| if x_sigma > 0.0 { x + nx.sample(&mut rng) } else { x }).collect();
    let p: Vec<f64> = xt.iter().map(|&x| piecewise(v, x) + if load_noise > 0.0 { np.sample(&mut rng) } else { 0.0 }).collect();
    let sx = vec![(x_sigma > 0.0).then_some(x_sigma); n];
    Curve::new(t, p, x, sx, 0.0, 5, 0.0, "deflection").unwrap()
}

fn get<'a>(entries: &'a [Entry], key: &str) -> &'a Quantity {
    let e = entries.iter().find(|e| e.key == key).unwrap_or_else(|| panic!("no entry {key}"));
    e.result.as_ref().unwrap_or_else(|why| panic!("{key} not determined: {why}"))
}

fn close(what: &str, got: f64, want: f64, tol: f64) {
    assert!((got - want).abs() <= tol, "{what}: {got} vs {want} (tolerance {tol})");
}

/// Softening FRC: elastic to the first peak 40 kN at 0.05 mm, down to 20 kN at 0.5 mm,
/// then linearly to 10 kN at 5 mm.
const SOFTENING: [(f64, f64); 4] = [(0.0, 0.0), (0.05, 40.0), (0.5, 20.0), (5.0, 10.0)];

/// Closed forms of SOFTENING on ASTM_BEAM.
fn softening_truth() -> [(&'static str, f64); 8] {
    let p600 = 20.0 - 10.0 * (0.75 - 0.5) / 4.5;
    let p150 = 20.0 - 10.0 * (3.0 - 0.5) / 4.5;
    let t150 = 0.5 * 40.0 * 0.05 + 0.5 * (40.0 + 20.0) * 0.45 + 0.5 * (20.0 + p150) * 2.5;
    let f = |p: f64| 1000.0 * p * 450.0 / (150.0 * 150.0 * 150.0);
    let rt = 150.0 * t150 * 1000.0 / (f(40.0) * 150.0 * 150.0 * 150.0) * 100.0;
    [("P1", 40.0), ("delta1", 0.05), ("Pp", 40.0), ("P600", p600), ("P150", p150), ("T150", t150), ("f1", f(40.0)), ("RT150", rt)]
}

#[test]
fn c1609_on_a_piecewise_linear_curve_matches_the_closed_form() {
    let curve = sampled(&SOFTENING, 0.01, 5.0, 0.0, 0.0, 1);
    let e = c1609::compute(&curve, &ASTM_BEAM);
    // Noise-free, vertices on samples, a straight ramp in time: exact up to rounding.
    for (key, want) in softening_truth() {
        close(key, get(&e, key).value, want, 1e-9 * want.abs().max(1.0));
    }
    close("deltap", get(&e, "deltap").value, 0.05, 1e-12);
    close("f600", get(&e, "f600").value, get(&e, "P600").value * 1000.0 * 450.0 / 150.0f64.powi(3), 1e-12);
    close("f150", get(&e, "f150").value, get(&e, "P150").value * 1000.0 * 450.0 / 150.0f64.powi(3), 1e-12);
    // f = P·L/(b·d²): 40 kN on the reference beam is 5.333 MPa; R_T,150 = T150 / (P1 · L/150).
    close("f1 by hand", get(&e, "f1").value, 16.0 / 3.0, 1e-9);
    close("RT150 as T150/(P1·L/150)", get(&e, "RT150").value, 100.0 * get(&e, "T150").value / (40.0 * 3.0), 1e-9);
    assert_eq!(get(&e, "T150").unit, "J");
    assert_eq!(get(&e, "RT150").unit, "%");
}

#[test]
fn c1609_sigma_follows_the_feed_sigma_through_the_slope() {
    // x ramp noise-free but given a σ of 2 µm per point: σ(P600) = |dP/dδ| · σ(δ̃), the
    // smoothed δ̃ of 5 points at the centre of its window has σ/√5.
    let n = 501;
    let t: Vec<i64> = (0..n).map(|k| T0 + k as i64 * DT).collect();
    let x: Vec<f64> = (0..n).map(|k| k as f64 * 0.01).collect();
    let p: Vec<f64> = x.iter().map(|&x| piecewise(&SOFTENING, x)).collect();
    let curve = Curve::new(t, p, x, vec![Some(0.002); n], 0.001, 5, 0.01, "deflection").unwrap();
    let e = c1609::compute(&curve, &ASTM_BEAM);
    let slope = 10.0 / 4.5;
    let sx = (0.002f64.powi(2) / 5.0 + 0.001f64.powi(2)).sqrt();
    let sp = 0.01 / 12f64.sqrt();
    let want = ((slope * sx).powi(2) + sp * sp).sqrt();
    close("sigma P600", get(&e, "P600").sigma, want, 0.02 * want);
    // P1: one reading and the sampling of the peak (the rise into it, 8 kN per point: r/√3).
    close("sigma P1", get(&e, "P1").sigma, (sp * sp + (8.0f64 / 3f64.sqrt()).powi(2)).sqrt(), 1e-9);
    assert!(get(&e, "T150").sigma > 0.0 && get(&e, "T150").sigma < 0.01 * get(&e, "T150").value);
}

/// EN 14651 curve against CMOD: LOP 16 kN at 0.03 mm, down to 12 kN at 0.1 mm, then linear
/// to 8 kN at 4 mm.
const NOTCHED: [(f64, f64); 4] = [(0.0, 0.0), (0.03, 16.0), (0.1, 12.0), (4.0, 8.0)];

fn notched_truth() -> [(&'static str, f64); 6] {
    let fr = |c: f64| 0.32 * (12.0 - 4.0 * (c - 0.1) / 3.9); // 3·F·l/(2·b·h_sp²) = 0.32 MPa per kN
    [("FL", 16.0), ("fL", 0.32 * 16.0), ("fR1", fr(0.5)), ("fR2", fr(1.5)), ("fR3", fr(2.5)), ("fR4", fr(3.5))]
}

#[test]
fn en14651_on_a_piecewise_linear_curve_matches_the_closed_form() {
    let curve = sampled(&NOTCHED, 0.005, 4.0, 0.0, 0.0, 1);
    let e = en14651::compute(&curve, &EN_BEAM);
    for (key, want) in notched_truth() {
        close(key, get(&e, key).value, want, 1e-9 * want.abs().max(1.0));
    }
    assert_eq!(get(&e, "fR1").unit, "MPa");
    // An LOP at the end of the 0.05 mm interval: the interpolated load there counts.
    let rising = [(0.0, 0.0), (0.2, 20.0), (4.0, 30.0)];
    let e = en14651::compute(&sampled(&rising, 0.0075, 4.0, 0.0, 0.0, 1), &EN_BEAM);
    close("FL at 0.05 mm", get(&e, "FL").value, 5.0, 1e-9);
}

#[test]
fn first_peak_on_a_noisy_curve() {
    // 2.5 µm of deflection per frame set, σ 3 µm on deflection and 0.05 kN on load.
    let truth = softening_truth();
    for seed in 1..=5 {
        let curve = sampled(&SOFTENING, 0.0025, 5.0, 0.003, 0.05, seed);
        let e = c1609::compute(&curve, &ASTM_BEAM);
        // P1: the largest reading near the peak, so biased up by about one σ of the load.
        close("P1", get(&e, "P1").value, 40.0, 0.2);
        close("delta1", get(&e, "delta1").value, 0.05, 0.006);
        for key in ["P600", "P150", "T150"] {
            let want = truth.iter().find(|t| t.0 == key).unwrap().1;
            let q = get(&e, key);
            assert!((q.value - want).abs() <= 4.0 * q.sigma, "seed {seed} {key}: {} ± {} vs {want}", q.value, q.sigma);
        }
    }
}

#[test]
fn first_peak_on_a_strain_hardening_curve() {
    // First crack at 30 kN / 0.05 mm, a small drop to 27 kN, hardening to the peak 40 kN at
    // 1.5 mm, softening after: P1 is the first crack, not the peak.
    let hardening = [(0.0, 0.0), (0.05, 30.0), (0.1, 27.0), (1.5, 40.0), (5.0, 20.0)];
    for (noise, seed) in [(0.0, 1), (0.05, 2), (0.05, 3)] {
        let curve = sampled(&hardening, 0.0025, 5.0, noise * 0.06, noise, seed);
        let e = c1609::compute(&curve, &ASTM_BEAM);
        close("P1", get(&e, "P1").value, 30.0, 0.2);
        close("delta1", get(&e, "delta1").value, 0.05, 0.006);
        close("Pp", get(&e, "Pp").value, 40.0, 0.2);
        close("deltap", get(&e, "deltap").value, 1.5, 0.01);
    }
    // Hardening without any fall after the first crack (a kink only): the slope first
    // becomes zero at the peak, so P1 = Pp.
    let kink = [(0.0, 0.0), (0.05, 30.0), (1.5, 40.0), (5.0, 20.0)];
    let e = c1609::compute(&sampled(&kink, 0.0025, 5.0, 0.0, 0.0, 1), &ASTM_BEAM);
    close("P1 of a kink", get(&e, "P1").value, 40.0, 1e-9);
    // A curve still rising at its end has no first peak: reported as undetermined.
    let e = c1609::compute(&sampled(&[(0.0, 0.0), (5.0, 50.0)], 0.01, 2.0, 0.0, 0.0, 1), &ASTM_BEAM);
    let p1 = e.iter().find(|e| e.key == "P1").unwrap();
    assert!(p1.result.is_err(), "{:?}", p1.result);
    assert!(e.iter().find(|e| e.key == "P150").unwrap().result.is_err(), "2 mm never reaches L/150 = 3 mm");
}

// ----------------------------------------------------------------------------------------
// The command line on synthetic feeds.

fn tagdeflect(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_tagdeflect")).args(args).env("TAGDEFLECT_LOG", "warn").output().expect("run tagdeflect")
}

/// `tagdeflect report FEED --config CFG --standard STANDARD --out OUT`.
fn report(feed: &Path, cfg: &Path, standard: &str, out: &Path) -> Output {
    tagdeflect(&[
        "report",
        feed.to_str().unwrap(),
        "--config",
        cfg.to_str().unwrap(),
        "--standard",
        standard,
        "--out",
        out.to_str().unwrap(),
    ])
}

/// The one-camera config with the given `[specimen.beam]` appended.
fn config_with_beam(dir: &Path, beam: &str) -> PathBuf {
    let base = common::one_camera_without_beam();
    let p = dir.join("rig.toml");
    fs::write(&p, format!("{base}\n[specimen.beam]\n{beam}\n")).unwrap();
    p
}

/// A feed of the one-camera rig (support tags 0 and 2, midspan tag 1, z up) following `v`
/// against `x`, sampled every `step`; with `cmod`, `x` is the CMOD gauge instead.
fn synthetic_feed(v: &[(f64, f64)], step: f64, x_end: f64, cmod: bool) -> String {
    let n = (x_end / step).round() as usize + 1;
    let mut s = String::new();
    for k in 0..n {
        let x = k as f64 * step;
        let p = piecewise(v, x);
        let defl = if cmod { 0.85 * x + 0.04 * (x > 0.0) as u8 as f64 } else { x };
        let tag = |id: u32, dz: f64| serde_json::json!({"id": id, "pos_mm": [0.0, 0.0, dz], "disp_mm": [0.0, 0.0, dz], "views": 1, "sigma_mm": [0.004, 0.01, 0.002]});
        let mut line = serde_json::json!({
            "seq": k, "t_ns": T0 + k as i64 * DT, "load_kN": p, "stroke_mm": defl * 1.1,
            "tags": [tag(0, 0.0), tag(1, -defl), tag(2, 0.0)],
            "net_deflection_mm": defl, "utm": "ok", "dropped_sets": 0,
            "cameras": [{"name": "front", "frame": true, "background_tags": 5, "specimen_tags": 3, "posed": true}],
        });
        if cmod {
            line["gauges"] = serde_json::json!({"cmod": {"value": x, "sigma": 0.002, "unit": "mm"}});
        }
        if (200..210).contains(&k) {
            line["utm"] = "down".into();
        }
        s.push_str(&line.to_string());
        s.push('\n');
    }
    s
}

const SPEC_C1609_KEYS: [&str; 12] = ["P1", "delta1", "f1", "Pp", "deltap", "fp", "P600", "P150", "f600", "f150", "T150", "RT150"];
const SPEC_EN14651_KEYS: [&str; 6] = ["FL", "fL", "fR1", "fR2", "fR3", "fR4"];

fn read_json(p: &Path) -> serde_json::Value {
    serde_json::from_str(&fs::read_to_string(p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))).unwrap()
}

#[test]
fn report_cli_writes_html_json_csv_and_plots_for_c1609() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = config_with_beam(dir.path(), "width_mm = 150.0\ndepth_mm = 150.0\nspan_mm = 450.0");
    let feed = dir.path().join("feed.jsonl");
    fs::write(&feed, synthetic_feed(&SOFTENING, 0.01, 5.0, false)).unwrap();
    let out = dir.path().join("report");
    let o = report(&feed, &cfg, "astm-c1609", &out);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    for f in ["report.html", "report.json", "curve.csv", "load_deflection.png", "load_deflection.svg", "time.png", "time.svg"] {
        assert!(out.join(f).is_file(), "{f} missing");
    }
    let j = read_json(&out.join("report.json"));
    assert_eq!(j["standard"], "astm-c1609");
    assert_eq!(j["specimen"]["span_mm"], 450.0);
    assert!(j["qc"].is_object());
    for key in SPEC_C1609_KEYS {
        let q = &j[key];
        assert!(q["value"].is_f64() && q["sigma"].is_f64() && q["unit"].is_string(), "{key}: {q}");
    }
    for (key, want) in softening_truth() {
        // σ of the tags makes the smoothing and the σ non-zero; a straight ramp stays exact.
        // Rounded to two significant digits of its σ: within a twentieth of σ.
        close(key, j[key]["value"].as_f64().unwrap(), want, 1e-6 * want.abs().max(1.0) + j[key]["sigma"].as_f64().unwrap() / 20.0);
    }
    // σ of the net deflection from the tags: midspan σz 2 µm, the two supports averaged.
    let sx = j["curve"]["x_reference_sigma_mm"].as_f64().unwrap();
    close("reference σ", sx, (0.002f64.powi(2) + 0.002f64.powi(2) / 2.0).sqrt(), 1e-9);
    assert_eq!(j["qc"]["utm_outages"].as_array().unwrap().len(), 1);
    assert_eq!(j["qc"]["utm_down_lines"], 10);
    assert_eq!(j["qc"]["tags"].as_array().unwrap().len(), 3);
    let html = fs::read_to_string(out.join("report.html")).unwrap();
    assert!(html.contains("<svg") && !html.contains("<script") && !html.contains("src=\"http"), "self-contained, plots inline");
    assert!(
        html.contains("No test method was named: the built-in rules of") && !html.contains("have not been checked against"),
        "the report names the rules in force (no blanket disclaimer)"
    );
    let png = fs::read(out.join("load_deflection.png")).unwrap();
    assert!(png.starts_with(b"\x89PNG"));

    // The CSV read back with Python's csv module.
    let script = r#"
import csv, sys
rows = list(csv.reader(open(sys.argv[1], newline='')))
h = rows[0]
need = ['t_ns', 'load [kN]', 'stroke [mm]', 'net_deflection [mm]', 'tag0_dx [mm]', 'tag1_dz [mm]', 'tag2_dz [mm]']
missing = [c for c in need if c not in h]
assert not missing, missing
i, j = h.index('load [kN]'), h.index('net_deflection [mm]')
body = rows[1:]
t = [int(r[0]) for r in body]
assert t == sorted(t)
print(len(body), float(body[75][i]), float(body[75][j]), float(body[-1][h.index('tag1_dz [mm]')]))
"#;
    let o = Command::new(common::python()).arg("-c").arg(script).arg(out.join("curve.csv")).output().unwrap();
    assert!(o.status.success(), "python csv: {}", String::from_utf8_lossy(&o.stderr));
    let v: Vec<f64> = String::from_utf8_lossy(&o.stdout).split_whitespace().map(|s| s.parse().unwrap()).collect();
    assert_eq!(v[0], 501.0);
    close("load at row 75", v[1], piecewise(&SOFTENING, 0.75), 1e-9);
    close("net deflection at row 75", v[2], 0.75, 1e-12);
    close("tag 1 dz at the end", v[3], -5.0, 1e-12);

    // The page as a browser shows it.
    let shot = dir.path().join("report.png");
    screenshot(&out.join("report.html"), &shot, (1000, 2600));
    let img = image::open(&shot).unwrap().to_rgb8();
    assert_eq!(img.dimensions(), (1000, 2600));
    let dark_blue = img.pixels().filter(|p| p[2] > 120 && p[0] < 90 && p[1] < 120).count();
    let ink = img.pixels().filter(|p| p[0] < 100 && p[1] < 100 && p[2] < 100).count();
    assert!(dark_blue > 500, "the plot's curve (blue) is rendered: {dark_blue} px");
    assert!(ink > 5000, "text is rendered: {ink} px");
    if let Ok(keep) = std::env::var("TAGDEFLECT_KEEP_SCREENSHOT") {
        fs::copy(&shot, keep).unwrap();
    }
}

/// The first-peak strength end to end: on a strain-hardening curve (first crack 30 kN at
/// 0.05 mm, a drop to 27 kN, hardening to the maximum 40 kN at 1.5 mm) the report's f1 is the
/// FIRST peak's load in f = P·L/(b·d²), never the maximum's (5.33 MPa here, not 4.00).
#[test]
fn a_reported_f1_comes_from_the_first_peak_when_the_maximum_comes_later() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = config_with_beam(dir.path(), "width_mm = 150.0\ndepth_mm = 150.0\nspan_mm = 450.0");
    let feed = dir.path().join("feed.jsonl");
    let hardening = [(0.0, 0.0), (0.05, 30.0), (0.1, 27.0), (1.5, 40.0), (5.0, 20.0)];
    fs::write(&feed, synthetic_feed(&hardening, 0.0025, 5.0, false)).unwrap();
    let out = dir.path().join("report");
    let o = report(&feed, &cfg, "astm-c1609", &out);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let j = read_json(&out.join("report.json"));
    let value = |key: &str| j[key]["value"].as_f64().unwrap_or_else(|| panic!("{key}: {}", j[key]));
    let strength = |p_kn: f64| p_kn * 1e3 * 450.0 / (150.0 * 150.0 * 150.0);
    close("P1", value("P1"), 30.0, 0.3);
    close("Pp", value("Pp"), 40.0, 0.3);
    close("f1 from the first peak's load", value("f1"), strength(value("P1")), 1e-3);
    close("f1", value("f1"), strength(30.0), strength(0.3));
    close("fp from the maximum's load", value("fp"), strength(value("Pp")), 1e-3);
}

#[test]
fn report_cli_en14651_from_a_cmod_gauge() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = config_with_beam(dir.path(), "width_mm = 150.0\ndepth_mm = 150.0\nspan_mm = 500.0\nnotch_mm = 25.0");
    let feed = dir.path().join("feed.jsonl");
    fs::write(&feed, synthetic_feed(&NOTCHED, 0.005, 4.0, true)).unwrap();
    let out = dir.path().join("en");
    let o = report(&feed, &cfg, "en-14651", &out);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let j = read_json(&out.join("report.json"));
    assert_eq!(j["standard"], "en-14651");
    assert_eq!(j["specimen"]["h_sp_mm"], 125.0);
    for (key, want) in notched_truth() {
        // Rounded to two significant digits of its σ: within a twentieth of σ.
        close(key, j[key]["value"].as_f64().unwrap(), want, 1e-6 * want.abs().max(1.0) + j[key]["sigma"].as_f64().unwrap() / 20.0);
        if key.starts_with("fR") {
            assert!(j[key]["sigma"].as_f64().unwrap() > 0.0, "{key}: σ from the gauge's σ");
        }
    }
    for key in SPEC_EN14651_KEYS {
        assert!(j[key]["unit"].is_string(), "{key}");
    }
    assert!(out.join("load_cmod.svg").is_file() && out.join("load_cmod.png").is_file());
    let csv = fs::read_to_string(out.join("curve.csv")).unwrap();
    assert!(csv.lines().next().unwrap().contains("cmod [mm],cmod_sigma [mm]"), "{}", csv.lines().next().unwrap());
    // EN 14651 without a notch in the config, or without a CMOD gauge in the feed: exit 2.
    let plain = config_with_beam(dir.path(), "width_mm = 150.0\ndepth_mm = 150.0\nspan_mm = 500.0");
    let o = report(&feed, &plain, "en-14651", &out);
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("notch_mm"), "{}", String::from_utf8_lossy(&o.stderr));
    let cfg = config_with_beam(dir.path(), "width_mm = 150.0\ndepth_mm = 150.0\nspan_mm = 500.0\nnotch_mm = 25.0");
    let no_gauge = dir.path().join("plain.jsonl");
    fs::write(&no_gauge, synthetic_feed(&NOTCHED, 0.005, 1.0, false)).unwrap();
    let o = report(&no_gauge, &cfg, "en-14651", &out);
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("cmod"), "{}", String::from_utf8_lossy(&o.stderr));
}

#[test]
fn export_writes_the_csv_alone() {
    let dir = tempfile::tempdir().unwrap();
    let feed = dir.path().join("feed.jsonl");
    fs::write(&feed, synthetic_feed(&NOTCHED, 0.05, 1.0, true)).unwrap();
    let csv = dir.path().join("out/feed.csv");
    fs::create_dir_all(dir.path().join("out")).unwrap();
    let o = tagdeflect(&["export", feed.to_str().unwrap(), "--csv", csv.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let text = fs::read_to_string(&csv).unwrap();
    let mut lines = text.lines();
    assert_eq!(
        lines.next().unwrap(),
        "t_ns,time [s],load [kN],stroke [mm],net_deflection [mm],cmod [mm],cmod_sigma [mm],tag0_dx [mm],tag0_dy [mm],tag0_dz [mm],tag1_dx [mm],tag1_dy [mm],tag1_dz [mm],tag2_dx [mm],tag2_dy [mm],tag2_dz [mm]"
    );
    assert_eq!(lines.count(), 21);
}

#[test]
fn a_corrupt_feed_line_is_one_error_naming_file_and_line() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = config_with_beam(dir.path(), "width_mm = 150.0\ndepth_mm = 150.0\nspan_mm = 450.0");
    let good = synthetic_feed(&SOFTENING, 0.05, 5.0, false);
    let mut lines: Vec<&str> = good.lines().collect();
    lines[7] = "{\"seq\": 7, \"t_ns\": \"soon\"}";
    let feed = dir.path().join("bad.jsonl");
    fs::write(&feed, lines.join("\n") + "\n").unwrap();
    let out = dir.path().join("r");
    let o = report(&feed, &cfg, "astm-c1609", &out);
    assert_eq!(o.status.code(), Some(2));
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(e.contains("bad.jsonl:8:"), "{e}");
    assert_eq!(e.trim().lines().count(), 1, "one line: {e}");
    assert!(!out.exists(), "nothing written");
    let o = tagdeflect(&["export", feed.to_str().unwrap(), "--csv", dir.path().join("x.csv").to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("bad.jsonl:8:"));

    // A truncated last line (a writer killed mid-line) is skipped with a warning.
    let cut = &good[..good.len() - 40];
    fs::write(&feed, cut).unwrap();
    let o = report(&feed, &cfg, "astm-c1609", &out);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(e.contains("truncated last line skipped"), "{e}");
    let j = read_json(&out.join("report.json"));
    assert!(j["qc"]["warnings"].as_array().unwrap().iter().any(|w| w.as_str().unwrap().contains("truncated")));
}

#[test]
fn beam_and_report_tables_are_validated_with_file_line_and_key() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = config_with_beam(dir.path(), "width_mm = 150.0\ndepth_mm = 150.0\nspan_mm = 450.0\nnotch_mm = 160.0");
    let o = tagdeflect(&["check", "--config", cfg.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(2));
    let e = String::from_utf8_lossy(&o.stderr);
    let line = fs::read_to_string(&cfg).unwrap().lines().position(|l| l.starts_with("notch_mm")).unwrap() + 1;
    assert!(e.contains(&format!("rig.toml:{line}: `specimen.beam.notch_mm`")), "{e}");
    let cfg = config_with_beam(dir.path(), "width_mm = 150.0\ndepth_mm = 150.0\nspan_mm = 450.0\nheight_mm = 3.0");
    let e = String::from_utf8_lossy(&tagdeflect(&["check", "--config", cfg.to_str().unwrap()]).stderr).into_owned();
    assert!(e.contains("height_mm"), "{e}");
    // [report] for EN 14651 needs a notch.
    let cfg = config_with_beam(
        dir.path(),
        "width_mm = 150.0\ndepth_mm = 150.0\nspan_mm = 450.0\n[report]\nstandard = \"en-14651\"\nout = \"reports\"",
    );
    let o = tagdeflect(&["check", "--config", cfg.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("`report.standard`"), "{}", String::from_utf8_lossy(&o.stderr));
    // A good one parses and round-trips through the config writer.
    let cfg = config_with_beam(
        dir.path(),
        "width_mm = 100.0\ndepth_mm = 100.0\nspan_mm = 300.0\n[report]\nstandard = \"astm-c1856\"\nout = \"reports\"",
    );
    let c = tagdeflect::config::Config::load(&cfg).unwrap();
    assert_eq!(c.specimen.beam.as_ref().unwrap().span_mm, 300.0);
    assert_eq!(c.report.as_ref().unwrap().out, dir.path().join("reports"));
    let again = tagdeflect::config::Config::from_toml_str(&c.to_toml_string(), &cfg).unwrap();
    assert_eq!(again.specimen.beam, c.specimen.beam);
}

#[test]
fn run_writes_the_report_at_its_end() {
    let dir = tempfile::tempdir().unwrap();
    // One simulated 640x480 camera at 5 fps and the simulated UTM (Modbus TCP on loopback).
    let params = tagdeflect_sim::SimParams {
        cameras: 1,
        width: 640,
        height: 480,
        fps: 5.0,
        frame_sets: 15,
        rest_frames: 2,
        subsamples: 2,
        ..Default::default()
    };
    let mut cfg = tagdeflect::config::Config::from_sim(&tagdeflect_sim::SimRig::new(&params).unwrap());
    cfg.utm = tagdeflect::config::Config::demo().utm;
    cfg.specimen.beam = Some(ASTM_BEAM);
    cfg.output.feed = Some(dir.path().join("feed.jsonl").to_string_lossy().into_owned());
    cfg.report = Some(tagdeflect_report::ReportConfig::new(tagdeflect_report::Standard::AstmC1609, dir.path().join("reports")));
    let path = dir.path().join("rig.toml");
    fs::write(&path, cfg.to_toml_string()).unwrap();
    let o = tagdeflect(&["run", "--config", path.to_str().unwrap(), "--duration-s", "4"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let runs: Vec<PathBuf> = fs::read_dir(dir.path().join("reports")).unwrap().map(|e| e.unwrap().path()).collect();
    assert_eq!(runs.len(), 1, "{runs:?}");
    let j = read_json(&runs[0].join("report.json"));
    assert_eq!(j["standard"], "astm-c1609");
    assert!(j["qc"]["lines"].as_u64().unwrap() >= 5, "{}", j["qc"]);
    assert!(j["Pp"]["value"].as_f64().unwrap() > 1.0, "a load from the simulated UTM: {}", j["Pp"]);
    assert!(runs[0].join("report.html").is_file() && runs[0].join("feed.jsonl").is_file() && runs[0].join("tagdeflect.toml").is_file());
    // Every UTM sample at its own rate beside the feed (50 Hz against 5 frame sets a second),
    // and the report's loads from them.
    let utm = fs::read_to_string(runs[0].join("utm.jsonl")).unwrap();
    let samples: Vec<tagdeflect_io::utm::UtmSample> = utm.lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    let lines = j["qc"]["lines"].as_u64().unwrap() as usize;
    assert!(samples.len() > 5 * lines, "{} UTM samples for {lines} feed lines", samples.len());
    assert!(samples.windows(2).all(|w| w[0].t_ns < w[1].t_ns));
    assert_eq!(j["curve"]["load_from_utm"], true, "{}", j["load_source"]);
    assert_eq!(fs::read_to_string(dir.path().join("utm.jsonl")).unwrap(), utm, "beside the [output] feed too");
    // The copy of the feed is this run's feed, line for line.
    assert_eq!(fs::read_to_string(runs[0].join("feed.jsonl")).unwrap(), fs::read_to_string(dir.path().join("feed.jsonl")).unwrap());
}

// ----------------------------------------------------------------------------------------
// Headless Chromium (Debian's `chromium`).

/// A child process killed on drop.
struct Kill(Child);

impl Drop for Kill {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Screenshots a local HTML file with headless Chromium.
pub fn screenshot(html: &Path, png: &Path, (w, h): (u32, u32)) {
    let profile = tempfile::tempdir().unwrap();
    let child = Command::new("chromium")
        .args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-quic",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--hide-scrollbars",
        ])
        .arg(format!("--user-data-dir={}", profile.path().display()))
        .arg(format!("--screenshot={}", png.display()))
        .arg(format!("--window-size={w},{h}"))
        .arg(format!("file://{}", html.canonicalize().unwrap().display()))
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("Debian's chromium is needed (scripts/setup.sh installs it)");
    let mut guard = Kill(child);
    let deadline = Instant::now() + Duration::from_secs(90);
    loop {
        if let Some(status) = guard.0.try_wait().unwrap() {
            assert!(status.success(), "chromium exited with {status}");
            break;
        }
        assert!(Instant::now() < deadline, "chromium did not finish the screenshot within 90 s");
        std::thread::sleep(Duration::from_millis(100));
    }
    assert!(png.is_file(), "chromium wrote no screenshot");
}

// ----------------------------------------------------------------------------------------
// End to end: `simulate` (a real test) → `replay` → `report`, against the truth.

/// A simulated real test: two 960x720 cameras, the law's load from a 50 Hz UTM.
fn sim_test(
    test: tagdeflect_sim::SimTest,
    law: tagdeflect_sim::LoadLaw,
    frame_sets: u32,
    max_deflection_mm: f64,
    seed: u64,
) -> tagdeflect_sim::SimParams {
    tagdeflect_sim::SimParams {
        cameras: 2,
        width: 960,
        height: 720,
        frame_sets,
        rest_frames: 3,
        subsamples: 4,
        test,
        load_law: law,
        span_mm: if test == tagdeflect_sim::SimTest::ThreePointNotched { 500.0 } else { 450.0 },
        stiffness_kn_per_mm: 100.0,
        max_deflection_mm,
        // The UTM read at 2 kHz: the first crack (between frame sets) is sampled within 0.3 %.
        utm_hz: 2000.0,
        seed,
        ..tagdeflect_sim::SimParams::default()
    }
}

/// Simulates, replays into `feed.jsonl` and runs `tagdeflect report` with the recording's
/// config; returns the report, the truth lines and the feed lines.
fn simulate_replay_report(
    dir: &Path,
    p: &tagdeflect_sim::SimParams,
    standard: &str,
) -> (serde_json::Value, Vec<tagdeflect_sim::SimTruthLine>, Vec<tagdeflect_sim::SimTruthLine>, Vec<tagdeflect_core::feed::FeedLine>) {
    let rec = common::simulate(dir, "rec", p);
    let (_, lines, _) = common::replay_lines(&rec, false);
    let feed = dir.join("feed.jsonl");
    fs::write(&feed, lines.iter().map(|l| l.to_json() + "\n").collect::<String>()).unwrap();
    let out = dir.join("report");
    let cfg = rec.join("tagdeflect.toml");
    let utm = rec.join("utm.jsonl");
    let o = tagdeflect(&[
        "report",
        feed.to_str().unwrap(),
        "--config",
        cfg.to_str().unwrap(),
        "--standard",
        standard,
        "--out",
        out.to_str().unwrap(),
        "--utm",
        utm.to_str().unwrap(),
        "--no-pdf",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let truth: Vec<tagdeflect_sim::SimTruthLine> =
        tagdeflect_io::recording::read_jsonl_file(&rec.join(tagdeflect_sim::SIM_TRUTH_FILE)).unwrap();
    let samples: Vec<tagdeflect_io::utm::UtmSample> = tagdeflect_io::recording::read_jsonl_file(&utm).unwrap();
    let on_utm = truth_on_utm(&truth, &samples);
    (read_json(&out.join("report.json")), truth, on_utm, lines)
}

/// The truth at the UTM's samples: the true gauges interpolated from the frame sets' truth at
/// each sample's time (the simulated UTM reads the law without noise).
fn truth_on_utm(truth: &[tagdeflect_sim::SimTruthLine], utm: &[tagdeflect_io::utm::UtmSample]) -> Vec<tagdeflect_sim::SimTruthLine> {
    let (t0, t1) = (truth[0].t_ns, truth[truth.len() - 1].t_ns);
    utm.iter()
        .filter(|s| s.t_ns >= t0 && s.t_ns <= t1)
        .map(|s| {
            let i = truth.partition_point(|l| l.t_ns < s.t_ns).max(1);
            let (a, b) = (&truth[i - 1], &truth[i]);
            let w = (s.t_ns - a.t_ns) as f64 / (b.t_ns - a.t_ns) as f64;
            let mut l = a.clone();
            l.t_ns = s.t_ns;
            l.load_kn = s.load_kn;
            for (k, v) in l.gauges.iter_mut() {
                *v += w * (b.gauges[k] - *v);
            }
            l
        })
        .collect()
}

/// The truth's curve: true load against the true gauge `x`, at the frame sets' times.
fn truth_curve(truth: &[tagdeflect_sim::SimTruthLine], x: &str) -> Curve {
    let t: Vec<i64> = truth.iter().map(|l| l.t_ns).collect();
    let p: Vec<f64> = truth.iter().map(|l| l.load_kn).collect();
    let xs: Vec<f64> = truth.iter().map(|l| l.gauges[x]).collect();
    let n = t.len();
    Curve::new(t, p, xs, vec![Some(0.0); n], 0.0, 5, 0.0, "truth").unwrap()
}

/// Each key of the report within `k·σ + floor` of the same quantity computed on the truth.
fn against_truth(label: &str, j: &serde_json::Value, truth: &[Entry], checks: &[(&str, f64)]) {
    for &(key, floor) in checks {
        let t = get(truth, key).value;
        let v = j[key]["value"].as_f64().unwrap_or_else(|| panic!("{label}: {key} missing: {}", j["undetermined"]));
        let s = j[key]["sigma"].as_f64().unwrap();
        println!("REPORT {label} {key}: {v:.4} ± {s:.4} {} (truth {t:.4}; error {:+.4})", j[key]["unit"].as_str().unwrap(), v - t);
        assert!((v - t).abs() <= 3.0 * s + floor, "{label} {key}: {v} ± {s} vs truth {t} (floor {floor})");
    }
}

#[test]
fn simulated_softening_test_end_to_end_matches_the_truth() {
    use tagdeflect_sim::{LoadLaw, SimTest};
    let dir = tempfile::tempdir().unwrap();
    let p = sim_test(SimTest::FourPoint, LoadLaw::Softening, 28, 4.0, 71);
    let (j, _, truth, lines) = simulate_replay_report(dir.path(), &p, "astm-c1609");
    assert!(lines.iter().all(|l| l.gauges.contains_key("net")), "the net deflection gauge in every line");
    assert_eq!(j["curve"]["load_from_utm"], true);
    // The first crack (30 kN, between two frame sets) from the 2 kHz UTM: within 0.5 %.
    let (p1, s1) = (j["P1"]["value"].as_f64().unwrap(), j["P1"]["sigma"].as_f64().unwrap());
    println!("REPORT simulated softening: P1 {p1} ± {s1} kN vs the first crack 30 kN");
    assert!((p1 - 30.0).abs() <= 0.005 * 30.0, "P1 {p1}");
    assert!(j["curve"]["x"].as_str().unwrap().contains("gauge net"), "the config's net_deflection gauge is used: {}", j["curve"]);
    let t = c1609::compute(&truth_curve(&truth, "net"), &ASTM_BEAM);
    // Floors: loads 1 % of the first-crack load (the UTM is sampled at 50 Hz and interpolated
    // at the frame set's time while the law drops at the crack), deflections 10 µm.
    let pc = 100.0 * 0.3;
    let fk = |kn: f64| 1000.0 * kn * 450.0 / 150.0f64.powi(3);
    against_truth(
        "softening",
        &j,
        &t,
        &[
            ("P1", 0.01 * pc),
            ("delta1", 0.01),
            ("f1", fk(0.01 * pc)),
            ("Pp", 0.01 * pc),
            ("deltap", 0.01),
            ("P600", 0.01 * pc),
            ("P150", 0.01 * pc),
            ("f600", fk(0.01 * pc)),
            ("f150", fk(0.01 * pc)),
            ("T150", 0.15),
            ("RT150", 0.3),
        ],
    );
    // And the law itself: the first peak is the last sample before the crack (k·δ ≤ 30 kN).
    let p1 = j["P1"]["value"].as_f64().unwrap();
    assert!(p1 <= pc + 0.5 && p1 > 0.8 * pc, "P1 {p1} vs the first-crack load {pc}");
    // The reference above runs the report's own arithmetic on the truth; this one does not:
    // the simulator's law P(δ) in closed form against its own net deflection, the standard's
    // quantities read off it here plainly (no code of the report).
    let law = closed_form_c1609(&p, 450.0);
    for (key, t, floor) in [
        ("P1", law.p1, 0.005 * pc),
        ("delta1", law.delta1, 0.01),
        ("P600", law.p600, 0.01 * pc),
        ("P150", law.p150, 0.01 * pc),
        // T150 was 1.29 J (2.6 %) low here while its σ said 0.21 J: the 5-point smoothing
        // straddled the start of loading (measured 2026-12-02: 49.68 J; 51.05 unsmoothed).
        // With the window shrunk at kinks (curve.rs) it is 51.04 ± 0.27 against 50.97.
        ("T150", law.t150, 0.15),
    ] {
        let (v, s) = (j[key]["value"].as_f64().unwrap(), j[key]["sigma"].as_f64().unwrap());
        println!("REPORT softening vs the closed-form law {key}: {v:.4} ± {s:.4} (law {t:.4}; error {:+.4})", v - t);
        assert!((v - t).abs() <= 2.0 * s + floor, "{key}: {v} ± {s} vs the law's {t}");
    }
    // Not σ-scaled alone (a σ grown twofold lets twice the error through): T150's error and σ
    // themselves. Measured: 2026-12-07 51.010 ± 0.110 J against the law's 50.973 (+0.037 J);
    // 2026-12-02 51.04 ± 0.27 J (+0.07 J, before the smoothing shrank at kinks). Ceilings
    // 1.4 × the largest error (0.10 J) and 1.4 × today's σ (0.16 J).
    let (t150, s150) = (j["T150"]["value"].as_f64().unwrap(), j["T150"]["sigma"].as_f64().unwrap());
    assert!((t150 - law.t150).abs() <= 0.10, "T150 {t150} J vs the law's {}: more than 0.10 J off", law.t150);
    assert!(s150 <= 0.16, "T150's σ {s150} J (measured 0.110)");
    // No clock offset in this rig: the feed's clock check, when it has one, agrees with 0.
    let clock = &j["qc"]["clock_offset"];
    if !clock.is_null() {
        let (v, s) = (clock["value"]["value"].as_f64().unwrap(), clock["value"]["sigma"].as_f64().unwrap());
        assert!(v.abs() <= 3.0 * s + 1.0, "clock offset {v} ± {s} ms in a rig without one: {clock}");
    }
}

/// ASTM C1609's quantities from the simulator's law in closed form: `P(δ)` (the law of
/// `tagdeflect_sim::load_at`) against the true net deflection at δ (the simulator's gauge
/// truth), δ sampled every 0.2 µm; P at L/600 and L/150 interpolated, T150 by the
/// trapezoid rule up to L/150.
struct C1609Law {
    p1: f64,
    delta1: f64,
    p600: f64,
    p150: f64,
    t150: f64,
}

fn closed_form_c1609(p: &tagdeflect_sim::SimParams, span_mm: f64) -> C1609Law {
    let rig = tagdeflect_sim::SimRig::new(p).unwrap();
    let n = 20_000;
    let net_at = |d: f64| rig.gauge_truth(d)["net"];
    let pts: Vec<(f64, f64)> = (0..=n)
        .map(|i| {
            let d = p.max_deflection_mm * i as f64 / n as f64;
            (net_at(d), tagdeflect_sim::load_at(p, d))
        })
        .collect();
    let at = |x: f64| {
        let i = pts.iter().position(|q| q.0 >= x).expect("the test reaches the deflection");
        let (a, b) = (pts[i - 1], pts[i]);
        a.1 + (b.1 - a.1) * (x - a.0) / (b.0 - a.0)
    };
    let (x600, x150) = (span_mm / 600.0, span_mm / 150.0);
    let mut t150 = 0.0;
    for w in pts.windows(2) {
        let (a, b) = (w[0], w[1]);
        if a.0 >= x150 {
            break;
        }
        let hi = b.0.min(x150);
        let pb = if b.0 > x150 { a.1 + (b.1 - a.1) * (x150 - a.0) / (b.0 - a.0) } else { b.1 };
        t150 += 0.5 * (a.1 + pb) * (hi - a.0);
    }
    C1609Law {
        p1: p.stiffness_kn_per_mm * p.crack_deflection_mm,
        delta1: net_at(p.crack_deflection_mm),
        p600: at(x600),
        p150: at(x150),
        t150,
    }
}

#[test]
fn simulated_notched_test_cmod_and_residual_strengths_match_the_truth() {
    use tagdeflect_sim::{LoadLaw, SimTest};
    let dir = tempfile::tempdir().unwrap();
    // 200 frame sets: the CMOD moves 0.004 mm per set before the crack, so F_L (the peak in
    // CMOD 0–0.05 mm) is resolved; at 30 sets one set spanned the crack and F_L came out 10.6
    // ± 7 kN (measured 2026-12-02).
    let p = sim_test(SimTest::ThreePointNotched, LoadLaw::Softening, 200, 5.5, 73);
    let (j, truth, on_utm, lines) = simulate_replay_report(dir.path(), &p, "en-14651");
    // The CMOD gauge against the truth's, line by line (two 960x720 cameras).
    let err: Vec<f64> = lines.iter().zip(&truth).map(|(l, t)| l.gauges["cmod"].value - t.gauges["cmod"]).collect();
    let rms = (err.iter().map(|e| e * e).sum::<f64>() / err.len() as f64).sqrt();
    let worst = err.iter().map(|e| e.abs()).fold(0.0, f64::max);
    println!("REPORT notched: CMOD gauge vs truth, RMS {rms:.4} mm, max {worst:.4} mm over {} lines", lines.len());
    // With two 960x720 cameras the gauge's σ is about 0.015 mm. A line's σ leaves out the
    // first frame set's error, which every line carries (an offset common to the run; the
    // report adds it as the zero reference's σ): each error against both, σ checked both
    // ways (the fraction within 2σ and the RMS of error/σ), no error beyond 4σ. Measured
    // 2026-12-02: mean error −0.018 mm, 0.012 mm about it, line σ 0.014 mm; against the line
    // σ alone 84.5 % within 2σ, RMS error/σ 1.47.
    assert!(rms <= 0.03, "CMOD RMS {rms} mm");
    let s_ref = j["curve"]["x_reference_sigma_mm"].as_f64().unwrap();
    assert!(s_ref > 0.005, "the CMOD's zero reference σ {s_ref} mm is in the report");
    let z: Vec<f64> = lines.iter().zip(&err).map(|(l, e)| e / l.gauges["cmod"].sigma.hypot(s_ref)).collect();
    let within2 = z.iter().filter(|v| v.abs() <= 2.0).count() as f64 / z.len() as f64;
    let rms_z = (z.iter().map(|v| v * v).sum::<f64>() / z.len() as f64).sqrt();
    let worst_z = z.iter().map(|v| v.abs()).fold(0.0, f64::max);
    println!("REPORT notched: CMOD error/σ: {:.1} % within 2σ, RMS {rms_z:.2}, worst {worst_z:.2}σ", 100.0 * within2);
    assert!(
        within2 >= 0.9 && (0.6..=1.3).contains(&rms_z) && worst_z <= 4.0,
        "CMOD σ: {within2} within 2σ, RMS error/σ {rms_z}, worst {worst_z}σ"
    );
    assert_eq!(j["specimen"]["notch_mm"], 25.0);
    let (fl, sl) = (j["FL"]["value"].as_f64().unwrap(), j["FL"]["sigma"].as_f64().unwrap());
    println!("REPORT simulated notched: F_L {fl} ± {sl} kN vs the first crack 30 kN");
    let t = en14651::compute(&truth_curve(&on_utm, "cmod"), &EN_BEAM);
    let mpa = |kn: f64| 0.32 * kn; // 3·F·l/(2·b·h_sp²) on 150 × 150, notch 25, l = 500
    let pc = 100.0 * 0.3;
    against_truth(
        "notched",
        &j,
        &t,
        &[
            ("FL", 0.01 * pc),
            ("fL", mpa(0.01 * pc)),
            ("fR1", mpa(0.01 * pc)),
            ("fR2", mpa(0.01 * pc)),
            ("fR3", mpa(0.01 * pc)),
            ("fR4", mpa(0.01 * pc)),
        ],
    );
    // The reference above runs the report's own arithmetic on the truth; this one does not:
    // the simulator's law F(δ) against its own true CMOD at δ, f_R,j = 3·F_j·l / (2·b·h_sp²)
    // written out here (no code of the report).
    // F_L in closed form: the law's largest load while the true CMOD is within 0.05 mm. The
    // notch opens elastically before the crack (Tada's relation, `tagdeflect_sim::law`), past
    // 0.05 mm before the first crack (k·δ_c) on this beam: F_L is the load there.
    let rig = tagdeflect_sim::SimRig::new(&p).unwrap();
    let fl_law = (0..=20_000)
        .map(|i| p.max_deflection_mm * i as f64 / 20_000.0)
        .take_while(|&d| rig.gauge_truth(d)["cmod"] <= 0.05)
        .map(|d| tagdeflect_sim::load_at(&p, d))
        .fold(0.0, f64::max);
    assert!(fl_law < p.stiffness_kn_per_mm * p.crack_deflection_mm, "the notch opens 0.05 mm before the first crack: {fl_law} kN");
    println!("REPORT notched vs the closed-form law FL: {fl:.4} ± {sl:.4} kN (law {fl_law:.4}; error {:+.4})", fl - fl_law);
    assert!((fl - fl_law).abs() <= 2.0 * sl + 0.01 * pc, "F_L {fl} ± {sl} vs the law's {fl_law}");
    let law = closed_form_en14651(&p, 500.0, 150.0, 150.0 - 25.0);
    for (key, t) in ["fR1", "fR2", "fR3", "fR4"].into_iter().zip(law) {
        let (v, s) = (j[key]["value"].as_f64().unwrap(), j[key]["sigma"].as_f64().unwrap());
        println!("REPORT notched vs the closed-form law {key}: {v:.4} ± {s:.4} MPa (law {t:.4}; error {:+.4})", v - t);
        assert!((v - t).abs() <= 2.0 * s + mpa(0.01 * pc), "{key}: {v} ± {s} vs the law's {t}");
    }
    // Not σ-scaled alone: F_L's and fR1's errors and σ themselves. Measured 2026-12-07 with
    // the notch opening elastically before the crack (F_L now on the elastic climb, where the
    // CMOD crosses 0.05 mm): F_L 12.2 ± 1.6 kN against the law's 12.29 (−0.09; the σ is the
    // CMOD gauge's, ~0.0065 mm, times the climb's |dF/dCMOD| ≈ 246 kN/mm — before, with the
    // mouth opening only at the crack, 28.60 ± 0.94 against 30, −1.40), fR1 6.4100 ± 0.0260
    // MPa against 6.4433 (−0.033; earlier runs −0.014 to −0.060, σ 0.024–0.052).
    // Ceilings: 1.4 × the largest error (F_L 2.0 kN, fR1 0.085 MPa); σ 1.5 × today's (F_L
    // 2.4 kN, fR1 0.036 MPa — a doubled σ, 3.2 kN or 0.048 MPa, does not pass). Since F_L is
    // read where the gauge can tell it (its crossing from a line fitted to the CMOD over time,
    // `lop.rs`): 12.5 ± 1.9 kN against 12.29; with that line fitted across the start of
    // loading it was 10.8 ± 2.9, which these bounds caught.
    let fr1 = (j["fR1"]["value"].as_f64().unwrap(), j["fR1"]["sigma"].as_f64().unwrap());
    assert!((fl - fl_law).abs() <= 2.0, "F_L {fl} kN vs the law's {fl_law}: more than 2 kN off");
    assert!(sl <= 2.4, "F_L's σ {sl} kN (measured 1.6)");
    assert!((fr1.0 - law[0]).abs() <= 0.085, "fR1 {} MPa vs the law's {}: more than 0.085 MPa off", fr1.0, law[0]);
    assert!(fr1.1 <= 0.036, "fR1's σ {} MPa (measured 0.024)", fr1.1);
}

/// EN 14651's residual flexural strengths f_R,1..4 from the simulator's law in closed form:
/// the load `F(δ)` of `tagdeflect_sim::load_at` at the δ where the true CMOD (the
/// simulator's gauge truth, from the rendered tags' poses) reaches 0.5, 1.5, 2.5 and 3.5 mm,
/// δ sampled every 0.3 µm, then `3·F·l / (2·b·h_sp²)` (kN → N).
fn closed_form_en14651(p: &tagdeflect_sim::SimParams, span_mm: f64, width_mm: f64, h_sp_mm: f64) -> [f64; 4] {
    let rig = tagdeflect_sim::SimRig::new(p).unwrap();
    let n = 20_000;
    let pts: Vec<(f64, f64)> = (0..=n)
        .map(|i| {
            let d = p.max_deflection_mm * i as f64 / n as f64;
            (rig.gauge_truth(d)["cmod"], tagdeflect_sim::load_at(p, d))
        })
        .collect();
    [0.5, 1.5, 2.5, 3.5].map(|cmod| {
        let i = pts.iter().position(|q| q.0 >= cmod).unwrap_or_else(|| panic!("the test reaches CMOD {cmod} mm"));
        let (a, b) = (pts[i - 1], pts[i]);
        let f_kn = a.1 + (b.1 - a.1) * (cmod - a.0) / (b.0 - a.0);
        3.0 * f_kn * 1000.0 * span_mm / (2.0 * width_mm * h_sp_mm * h_sp_mm)
    })
}
