//! Accuracy per image formation (docs/accuracy.md, "Today's figures per formation"): the
//! three-camera 1280x960 scene of `accuracy::three_cameras_1280x960_moderate_noise` (noise
//! σ 2, tags ~28 px, 16 frame sets, seed 11) with no blur, then with one formation each.
//! The table is a measurement, not a pass/fail: it is printed by
//! `cargo test --test it formations:: -- --ignored --nocapture` (13 scenes, several minutes).
//! The formations cheap enough to assert run in `accuracy::` with floors.
//! `TAGDEFLECT_FORMATIONS=bayer,ellip` (substrings of the formations' names, any case) runs
//! only those besides the sharp scene; `TAGDEFLECT_FORMATIONS_SEED=12` renders them with another
//! seed (the seed-to-seed spread); `TAGDEFLECT_FORMATIONS_NOISE=0` with no read noise (the
//! bias alone). The product's own switches apply too: `TAGDEFLECT_EDGE_MODEL=formation-sites`
//! fits the edges with the physical formation where it predicts held-out edges better than the
//! profile (docs/accuracy.md, "The physical formation").

use crate::common::*;
use tagdeflect_sim::SimParams;

/// The three-camera scene with sharp optics (no blur before or after the pixels).
pub fn sharp_scene() -> SimParams {
    SimParams {
        cameras: 3,
        width: 1280,
        height: 960,
        frame_sets: 16,
        noise_sigma: scene_noise(),
        blur_sigma: 0.0,
        seed: scene_seed(),
        subsamples: scene_subsamples(),
        ..SimParams::default()
    }
}

/// The scenes' read noise: σ 2 grey levels, or `TAGDEFLECT_FORMATIONS_NOISE` (0: what is
/// left is bias, and the 8-bit rounding).
fn scene_noise() -> f64 {
    std::env::var("TAGDEFLECT_FORMATIONS_NOISE").ok().and_then(|v| v.parse().ok()).unwrap_or(2.0)
}

/// Sub-samples per pixel axis where a pixel straddles an edge: the renderer's 8, or
/// `TAGDEFLECT_FORMATIONS_SUBSAMPLES` (its integration error against the fit's).
fn scene_subsamples() -> u32 {
    std::env::var("TAGDEFLECT_FORMATIONS_SUBSAMPLES").ok().and_then(|v| v.parse().ok()).unwrap_or(8)
}

/// The scenes' seed: 11, or `TAGDEFLECT_FORMATIONS_SEED` (the seed-to-seed spread).
fn scene_seed() -> u64 {
    std::env::var("TAGDEFLECT_FORMATIONS_SEED").ok().and_then(|v| v.parse().ok()).unwrap_or(11)
}

/// The scenes of the table: (formation, its `simulate` options, parameters).
pub fn formation_scenes() -> Vec<(&'static str, &'static str, SimParams)> {
    let s = sharp_scene;
    vec![
        ("sharp", "--blur-sigma 0", s()),
        ("Gaussian 0.7 px before the pixel (optics)", "--blur-sigma 0.7", SimParams { blur_sigma: 0.7, ..s() }),
        ("Gaussian 0.7 px after the pixel", "--post-blur-px 0.7", SimParams { post_blur_px: 0.7, ..s() }),
        ("3×3 sharpening, amount 1", "--sharpen 1", SimParams { sharpen: 1.0, ..s() }),
        ("3×3 sharpening, amount 0.5", "--sharpen 0.5", SimParams { sharpen: 0.5, ..s() }),
        ("Bayer RGGB, bilinear demosaic", "--bayer", SimParams { bayer: true, ..s() }),
        ("Bayer RGGB raw mosaic, converted by the product", "--bayer-raw", SimParams { bayer_raw: true, ..s() }),
        ("defocus disk r = 1.5 px", "--defocus-radius-px 1.5", SimParams { defocus_radius_px: 1.5, ..s() }),
        (
            "elliptical 1.0/0.4 px at 30°",
            "--astig-major-px 1 --astig-minor-px 0.4 --astig-angle-deg 30",
            SimParams { astig_major_px: 1.0, astig_minor_px: 0.4, astig_angle_deg: 30.0, ..s() },
        ),
        ("fill factor 0.5", "--fill-factor 0.5", SimParams { fill_factor: 0.5, ..s() }),
        ("JPEG quality 90", "--jpeg-quality 90", SimParams { jpeg_quality: Some(90), ..s() }),
        ("10-bit sensor", "--bit-depth 10", SimParams { bit_depth: 10, ..s() }),
        ("12-bit sensor", "--bit-depth 12", SimParams { bit_depth: 12, ..s() }),
    ]
}

/// Prints the table of docs/accuracy.md: each scene rendered, replayed (tracking mode) and
/// compared with truth.
#[test]
#[ignore = "a measurement of several minutes: run with --ignored --nocapture"]
fn accuracy_per_formation_table() {
    log_to_stderr();
    let dir = tempfile::tempdir().unwrap();
    let mut rows = Vec::new();
    let mut sharp_rms = None;
    let only: Vec<String> = std::env::var("TAGDEFLECT_FORMATIONS")
        .map(|v| v.split(',').map(|s| s.trim().to_lowercase()).filter(|s| !s.is_empty()).collect())
        .unwrap_or_default();
    let chosen = |k: usize, name: &str| k == 0 || only.is_empty() || only.iter().any(|o| name.to_lowercase().contains(o.as_str()));
    for (k, (name, options, p)) in formation_scenes().into_iter().enumerate().filter(|(k, (name, _, _))| chosen(*k, name)) {
        let rec = simulate(dir.path(), &format!("f{k}"), &p);
        let (rec_, lines, summary) = replay_lines(&rec, false);
        let acc = tagdeflect::accuracy::evaluate(&rec_.config, &rec_.truth, &lines);
        println!("ACCURACY {name}: {acc}");
        let stats = &summary.stats;
        println!("DRIFT {name}: D = {:?}, white noise {:?} px² per corner coordinate", stats.model_drift_px2, stats.white_noise_px2);
        println!("AXES {name}: {}", axes(&rec_.truth, &lines));
        let rms = acc.disp_rms_mm;
        let base = *sharp_rms.get_or_insert(rms);
        rows.push(format!(
            "| {name} | `{options}` | {rms:.4} mm | {:.2} | {:.4} mm | {} | {:.1} % | {} | {} | {} | {} | {} |",
            rms / base,
            acc.vertical_rms_mm,
            acc.net_rms_mm.map_or("—".into(), |v| format!("{v:.4} mm")),
            100.0 * acc.coverage(),
            acc.within_2sigma.map_or("—".into(), |v| format!("{:.1} %", 100.0 * v)),
            acc.z_rms.map_or("—".into(), |v| format!("{v:.2}")),
            acc.disp_within_2sigma.map_or("—".into(), |v| format!("{:.1} %", 100.0 * v)),
            acc.disp_z_rms.map_or("—".into(), |v| format!("{v:.2}")),
            summary.stats.model_drift_px2.map_or("—".into(), |v| format!("{v:.2e}")),
        ));
        std::fs::remove_dir_all(&rec).ok();
    }
    println!("| formation | `simulate` options | displacement RMS | × sharp | vertical RMS | net deflection RMS | coverage | within 2σ | RMS error/σ | within 2σ (displacement σ) | RMS error/σ (displacement σ) | D, px² |");
    println!("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |");
    for r in &rows {
        println!("{r}");
    }
    let expected = formation_scenes().iter().enumerate().filter(|(k, (name, _, _))| chosen(*k, name)).count();
    assert_eq!(rows.len(), expected);
}

/// The product's log on stderr when `RUST_LOG` is set: e.g.
/// `RUST_LOG=tagdeflect_detect::refine::formation=debug` prints each camera's formation
/// choice with its held-out scores.
fn log_to_stderr() {
    if std::env::var_os("RUST_LOG").is_some() {
        let filter = tracing_subscriber::EnvFilter::from_default_env();
        let _ = tracing_subscriber::fmt().with_env_filter(filter).with_writer(std::io::stderr).try_init();
    }
}

/// The displacement errors' RMS per world axis (x along the beam, y the cameras' depth, z
/// up), then split into each set's mean over the tags (what is common to them) and each tag's
/// rest: where an error lies, and whether it is common to the tags.
fn axes(truth: &[tagdeflect_io::recording::TruthLine], lines: &[tagdeflect_core::feed::FeedLine]) -> String {
    use std::collections::HashMap;
    let mut first: HashMap<u32, [f64; 3]> = HashMap::new();
    let (mut all, mut common, mut n) = ([0.0f64; 3], [0.0f64; 3], 0usize);
    for line in lines {
        let tr = tagdeflect::accuracy::truth_at(truth, line.t_ns);
        let errs: Vec<[f64; 3]> = line
            .tags
            .iter()
            .filter_map(|t| {
                let p = tr.get(&t.id)?;
                let p0 = *first.entry(t.id).or_insert([p.x, p.y, p.z]);
                Some([0, 1, 2].map(|k| t.disp_mm[k] - (p[k] - p0[k])))
            })
            .collect();
        let mean = [0, 1, 2].map(|k| errs.iter().map(|e| e[k]).sum::<f64>() / errs.len().max(1) as f64);
        for e in &errs {
            (0..3).for_each(|k| (all[k], common[k]) = (all[k] + e[k] * e[k], common[k] + mean[k] * mean[k]));
        }
        n += errs.len();
    }
    let rms = |v: [f64; 3]| v.map(|s| (s / n.max(1) as f64).sqrt());
    let (a, c) = (rms(all), rms(common));
    format!(
        "RMS x {:.4}, y (depth) {:.4}, z (up) {:.4} mm; common to the set's tags x {:.4}, y {:.4}, z {:.4} mm",
        a[0], a[1], a[2], c[0], c[1], c[2]
    )
}
