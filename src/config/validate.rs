//! Validation: the raw file ([`super::raw`]) checked whole and turned into the clean
//! [`Config`]. Every check is here or called from here (a component's own limits — the
//! detector's options, the drift model, `[report]`, `[output.mqtt]`, `[output] http`, gauges,
//! `[clock_check]`, `[sim]` — are asked of the component), and every error names file, line
//! and key through [`Locator::err`]: nothing may fail later than `tagdeflect check` would.
//!
//! The tables are checked in a fixed order (world, sync, cameras — each camera's intrinsics
//! taken inline or imported from its calibration file —, background, specimen, utm, measure,
//! report, output, sim, sim camera names, output.mqtt, gauges, clock_check); the first
//! problem found is the one reported.

use std::collections::HashSet;
use std::path::Path;
use toml::Spanned;

use crate::camera::CameraIntrinsics;
use crate::tags::TagFamily;

use super::raw::{Locator, RawBackgroundTag, RawCamera, RawConfig, RawTagSet, SpecimenTagRaw};
use super::sim::SimParamError;
use super::{
    load_calibration, BackgroundConfig, BackgroundTag, CameraConfig, CameraSource, Config, ConfigError, MeasureConfig, SpecimenConfig,
    SpecimenTag, SyncConfig, UtmConfig, WorldConfig,
};

// Sane ranges of rates and durations: values outside them are typos (1e-20 Hz would make
// a thread wait for 10^12 years; 1e23 ms overflows every timer), refused when loading.
/// Lowest camera frame rate accepted, Hz.
pub const MIN_FPS: f64 = 0.01;
/// Highest camera frame rate accepted, Hz.
pub const MAX_FPS: f64 = 1000.0;
/// Lowest UTM polling rate accepted, Hz.
pub const MIN_POLL_HZ: f64 = 0.01;
/// Highest UTM polling rate accepted, Hz.
pub const MAX_POLL_HZ: f64 = 1000.0;
/// Longest Modbus request timeout accepted, ms.
pub const MAX_TIMEOUT_MS: f64 = 60_000.0;
/// Largest frame-set tolerance accepted, ms.
pub const MAX_TOLERANCE_MS: f64 = 10_000.0;
/// Camera names that would collide with a recording's own files.
pub const RESERVED_NAMES: &[&str] = &["frames.jsonl", "utm.jsonl", "truth.jsonl", "sim_truth.jsonl", "tagdeflect.toml", "feed.jsonl"];

/// Checks the whole raw file and builds the [`Config`]; `loc` holds the text and its path,
/// whose folder anchors relative paths (calibration files, recordings, outputs).
pub(super) fn config(loc: &Locator<'_>, raw: RawConfig) -> Result<Config, ConfigError> {
    let base = loc.file.parent().unwrap_or(Path::new("."));
    let world = world(loc, raw.world)?;
    let sync = sync(loc, raw.sync)?;
    let cameras = cameras(loc, base, &raw.camera)?;
    let (background, specimen) = tag_sets(loc, raw.background, raw.specimen)?;
    let utm = match raw.utm {
        None => None,
        Some(u) => Some(validate_utm(loc, u)?),
    };
    let measure = match raw.measure {
        None => MeasureConfig::default(),
        Some(m) => measure(loc, m)?,
    };
    // [report] (the report's own checks live in report::config).
    let report = match raw.report {
        None => None,
        Some(r) => {
            let span = r.span();
            let mut r = r.into_inner();
            crate::report::config::validate_report(&r, specimen.beam.as_ref())
                .map_err(|(key, msg)| loc.err(Some(span), &format!("report.{key}"), msg))?;
            if r.out.is_relative() {
                r.out = base.join(&r.out);
            }
            Some(r)
        }
    };
    let mut output = raw.output.unwrap_or_default();
    if let Some(h) = &output.http {
        crate::sinks::http::parse_addr(h)
            .map_err(|m| loc.err(crate::sinks::http::key_span(loc.text, "output", "http"), "output.http", m))?;
    }
    if let Some(r) = &output.record {
        if r.is_relative() {
            output.record = Some(base.join(r));
        }
    }
    if let Some(f) = &output.feed {
        if f != "-" && Path::new(f).is_relative() {
            output.feed = Some(base.join(f).to_string_lossy().into_owned());
        }
    }
    if let Some(sim) = &raw.sim {
        if let Err(SimParamError { option, message }) = sim.validate() {
            let table = loc.text.find("[sim]").map_or(0..0, |i| i..loc.text.len());
            return Err(loc.err(Some(loc.key_span(table, option)), &format!("sim.{option}"), message));
        }
    }
    sim_camera_names(loc, &cameras, &raw.camera, raw.sim.as_ref())?;
    if let Some(m) = output.mqtt.as_mut() {
        m.validate(base).map_err(|(k, msg)| {
            let at = crate::sinks::mqtt::key_offset(loc.text, k);
            loc.err(at.map(|a| a..a), &format!("output.mqtt.{k}"), msg)
        })?;
    }
    let gauges = crate::solve::gauges::validate_gauges(&raw.gauge, &specimen).map_err(|e| loc.err(e.span, &e.key, e.message))?;
    let clock_check = match raw.clock_check {
        None => None,
        Some(c) => {
            let span = c.span();
            let c = c.into_inner();
            c.validate().map_err(|(k, m)| loc.err(Some(span), &format!("clock_check.{k}"), m))?;
            Some(c)
        }
    };
    Ok(Config { world, sync, cameras, background, specimen, utm, output, report, measure, sim: raw.sim, gauges, clock_check })
}

/// `[world]`: `up` normalised.
fn world(loc: &Locator<'_>, w: Option<Spanned<super::raw::RawWorld>>) -> Result<WorldConfig, ConfigError> {
    let Some(w) = w else { return Ok(WorldConfig::default()) };
    let up = w.get_ref().up.clone();
    let v = *up.get_ref();
    let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    if !(n.is_finite() && n > 1e-9) {
        return Err(loc.err(Some(up.span()), "world.up", "must be a non-zero direction, e.g. [0.0, 0.0, 1.0]"));
    }
    Ok(WorldConfig { up: [v[0] / n, v[1] / n, v[2] / n] })
}

/// `[sync]`.
fn sync(loc: &Locator<'_>, s: Option<super::raw::RawSync>) -> Result<SyncConfig, ConfigError> {
    let Some(s) = s else { return Ok(SyncConfig::default()) };
    let t = *s.tolerance_ms.get_ref();
    if !(t.is_finite() && t > 0.0 && t <= MAX_TOLERANCE_MS) {
        return Err(loc.err(
            Some(s.tolerance_ms.span()),
            "sync.tolerance_ms",
            format!("must be a positive number of milliseconds up to {MAX_TOLERANCE_MS}, got {t}"),
        ));
    }
    Ok(SyncConfig { tolerance_ms: t })
}

/// Every `[[camera]]`, names unique.
fn cameras(loc: &Locator<'_>, base: &Path, raw: &[Spanned<RawCamera>]) -> Result<Vec<CameraConfig>, ConfigError> {
    if raw.is_empty() {
        return Err(loc.err(None, "camera", "at least one [[camera]] is required"));
    }
    let mut cameras = Vec::new();
    let mut names = HashSet::new();
    for (i, cam) in raw.iter().enumerate() {
        let c = resolve_camera(loc, base, i, cam)?;
        if !names.insert(c.name.clone()) {
            return Err(loc.err(
                Some(cam.get_ref().name.span()),
                &format!("camera[{i}].name"),
                format!("duplicate camera name \"{}\": names must be unique (they are folder names)", c.name),
            ));
        }
        cameras.push(c);
    }
    Ok(cameras)
}

/// `[background]` and `[specimen]`, and the ids they must not share.
fn tag_sets(
    loc: &Locator<'_>,
    bg: Option<Spanned<RawTagSet<RawBackgroundTag>>>,
    sp: Option<Spanned<RawTagSet<SpecimenTagRaw>>>,
) -> Result<(BackgroundConfig, SpecimenConfig), ConfigError> {
    let bg = bg.ok_or_else(|| loc.err(None, "background", "a [background] section is required"))?;
    let background = resolve_background(loc, bg)?;
    let sp = sp.ok_or_else(|| loc.err(None, "specimen", "a [specimen] section is required"))?;
    let sp_span = sp.span();
    let specimen = resolve_specimen(loc, sp)?;
    if specimen.family == background.family {
        if let Some(t) = specimen.tags.iter().find(|t| background.tags.iter().any(|b| b.id == t.id)) {
            return Err(loc.err(
                Some(sp_span),
                "specimen.tag.id",
                format!(
                    "id {} is both a background and a specimen tag of {}: with one family for both, ids must differ",
                    t.id, specimen.family
                ),
            ));
        }
    }
    Ok((background, specimen))
}

/// `[measure]`, with the detector's and the drift model's own limits.
fn measure(loc: &Locator<'_>, m: Spanned<MeasureConfig>) -> Result<MeasureConfig, ConfigError> {
    let span = m.span();
    let m = m.into_inner();
    if !(m.quad_decimate.is_finite() && m.quad_decimate >= 1.0) {
        return Err(loc.err(Some(span), "measure.quad_decimate", "must be >= 1.0 (1 = full resolution)"));
    }
    if m.detector_threads == 0 {
        return Err(loc.err(Some(span), "measure.detector_threads", "must be >= 1"));
    }
    // The detector's own limits, checked here so nothing fails after `check`.
    let opts = crate::detect::DetectorOptions {
        quad_decimate: m.quad_decimate,
        nthreads: m.detector_threads,
        ..crate::detect::DetectorOptions::default()
    };
    if let Err(crate::detect::DetectError::BadOption { name, value, expected }) = opts.validate() {
        let key = match name {
            "nthreads" => "measure.detector_threads",
            "quad_decimate" => "measure.quad_decimate",
            _ => "measure",
        };
        return Err(loc.err(Some(span), key, format!("{value} is out of range: {expected}")));
    }
    if !(m.full_search_interval_s.is_finite() && m.full_search_interval_s > 0.0 && m.full_search_interval_s <= 3600.0) {
        let span = loc.key_span(span, "full_search_interval_s");
        return Err(loc.err(
            Some(span),
            "measure.full_search_interval_s",
            format!("must be in (0, 3600] seconds, got {}", m.full_search_interval_s),
        ));
    }
    if let Err((key, msg)) = crate::solve::DriftConfig::from_measure(&m).validate() {
        return Err(loc.err(Some(span), &format!("measure.drift_{key}"), msg));
    }
    Ok(m)
}

/// Simulated cameras are the rig's cameras, by name and in order.
fn sim_camera_names(
    loc: &Locator<'_>,
    cameras: &[CameraConfig],
    raw: &[Spanned<RawCamera>],
    sim: Option<&super::sim::SimParams>,
) -> Result<(), ConfigError> {
    if !cameras.iter().any(|c| c.source.is_sim()) {
        return Ok(());
    }
    let params = sim.cloned().unwrap_or_default();
    let names = super::sim::camera_names(params.cameras as usize);
    for (i, (cam, raw_cam)) in cameras.iter().zip(raw).enumerate() {
        if cam.source.is_sim() && names.get(i) != Some(&cam.name) {
            return Err(loc.err(
                Some(raw_cam.get_ref().name.span()),
                &format!("camera[{i}].name"),
                format!(
                    "sim camera {i} is named \"{}\" but the simulated rig's camera {i} is {}: a config with sim cameras lists the rig's cameras ({names:?}) in order",
                    cam.name,
                    names.get(i).map_or("missing (see `[sim] cameras`)".to_string(), |n| format!("\"{n}\""))
                ),
            ));
        }
    }
    Ok(())
}

fn resolve_camera(loc: &Locator<'_>, base: &Path, i: usize, cam: &Spanned<RawCamera>) -> Result<CameraConfig, ConfigError> {
    let span = cam.span();
    let c = cam.get_ref();
    let key = |k: &str| format!("camera[{i}].{k}");
    let name = c.name.get_ref().trim().to_string();
    if name.is_empty() || name.contains(['/', '\\']) || name == "." || name == ".." || name.chars().any(|ch| ch.is_control()) {
        return Err(loc.err(Some(c.name.span()), &key("name"), "must be a non-empty name usable as a folder name (no slashes)"));
    }
    if let Some(f) = RESERVED_NAMES.iter().find(|f| f.eq_ignore_ascii_case(&name)) {
        return Err(loc.err(
            Some(c.name.span()),
            &key("name"),
            format!(
                "\"{name}\" is the name of a recording's own file ({f}): the camera's folder would collide with it; choose another name"
            ),
        ));
    }
    let mut source = CameraSource::parse(&c.source).map_err(|m| loc.err(Some(span.clone()), &key("source"), m))?;
    if let CameraSource::Recording { dir } = &mut source {
        if dir.is_relative() {
            *dir = base.join(&*dir);
        }
    }
    if let Some(f) = &c.fps {
        if !(f.get_ref().is_finite() && (MIN_FPS..=MAX_FPS).contains(f.get_ref())) {
            return Err(loc.err(
                Some(f.span()),
                &key("fps"),
                format!("must be a frame rate from {MIN_FPS} to {MAX_FPS} Hz, got {}", f.get_ref()),
            ));
        }
    }
    let mut intr: Option<CameraIntrinsics> = None;
    if let Some(cal) = &c.calibration {
        if c.fx.is_some() || c.fy.is_some() || c.cx.is_some() || c.cy.is_some() || c.dist.is_some() {
            return Err(loc.err(Some(cal.span()), &key("calibration"), "give either `calibration` or fx/fy/cx/cy/dist, not both"));
        }
        let p = base.join(cal.get_ref());
        intr = Some(load_calibration(&p).map_err(|e| loc.err(Some(cal.span()), &key("calibration"), e.to_string()))?);
    }
    let (width, height) = match (&c.width, &c.height, &intr) {
        (Some(w), Some(h), _) => (*w.get_ref(), *h.get_ref()),
        (None, None, Some(i)) if i.width > 0 && i.height > 0 => (i.width, i.height),
        (None, _, _) => return Err(loc.err(Some(span), &key("width"), "missing: the image width in pixels is required")),
        (_, None, _) => return Err(loc.err(Some(span), &key("height"), "missing: the image height in pixels is required")),
    };
    if width == 0 || height == 0 {
        return Err(loc.err(Some(span), &key("width"), "width and height must be positive"));
    }
    let intr = match intr {
        Some(mut i) => {
            i.width = width;
            i.height = height;
            i
        }
        None => {
            let need = |v: Option<f64>, k: &str| {
                v.ok_or_else(|| {
                    loc.err(Some(span.clone()), &key(k), "missing: give fx, fy, cx, cy (and optionally dist), or `calibration = \"file\"`")
                })
            };
            let fx = need(c.fx.as_ref().map(|v| *v.get_ref()), "fx")?;
            let fy = need(c.fy.as_ref().map(|v| *v.get_ref()), "fy")?;
            let cx = need(c.cx, "cx")?;
            let cy = need(c.cy, "cy")?;
            let mut dist = [0.0; 5];
            if let Some(d) = &c.dist {
                let v = d.get_ref();
                if v.len() > 5 || v.len() < 4 {
                    return Err(loc.err(
                        Some(d.span()),
                        &key("dist"),
                        format!("expected 4 or 5 coefficients [k1, k2, p1, p2, k3], got {}", v.len()),
                    ));
                }
                dist[..v.len()].copy_from_slice(v);
            }
            CameraIntrinsics { width, height, fx, fy, cx, cy, dist }
        }
    };
    for (k, v, sp) in [("fx", intr.fx, c.fx.as_ref().map(|s| s.span())), ("fy", intr.fy, c.fy.as_ref().map(|s| s.span()))] {
        if !(v.is_finite() && v > 0.0) {
            return Err(loc.err(sp.or(Some(span.clone())), &key(k), format!("focal length must be positive, got {v}")));
        }
    }
    if intr.dist.iter().any(|d| !d.is_finite()) || !intr.cx.is_finite() || !intr.cy.is_finite() {
        return Err(loc.err(Some(span), &key("dist"), "intrinsics must be finite numbers"));
    }
    if c.rvec.is_some() != c.tvec_mm.is_some() {
        return Err(loc.err(Some(span), &key("rvec"), "give both `rvec` and `tvec_mm` for a fixed pose, or neither"));
    }
    Ok(CameraConfig {
        name,
        source,
        fps: c.fps.as_ref().map(|f| *f.get_ref()),
        width,
        height,
        fx: intr.fx,
        fy: intr.fy,
        cx: intr.cx,
        cy: intr.cy,
        dist: intr.dist,
        rvec: c.rvec,
        tvec_mm: c.tvec_mm,
    })
}

fn parse_family(loc: &Locator<'_>, section: &str, f: &Spanned<String>) -> Result<TagFamily, ConfigError> {
    f.get_ref().parse::<TagFamily>().map_err(|e| loc.err(Some(f.span()), &format!("{section}.family"), e))
}

fn check_size(loc: &Locator<'_>, section: &str, s: &Spanned<f64>) -> Result<f64, ConfigError> {
    let v = *s.get_ref();
    if !(v.is_finite() && v > 0.0) {
        return Err(loc.err(Some(s.span()), &format!("{section}.size_mm"), format!("must be a positive edge length in mm, got {v}")));
    }
    Ok(v)
}

fn resolve_background(loc: &Locator<'_>, bg: Spanned<RawTagSet<RawBackgroundTag>>) -> Result<BackgroundConfig, ConfigError> {
    let span = bg.span();
    let bg = bg.into_inner();
    if let Some(b) = &bg.beam {
        return Err(loc.err(Some(b.span()), "background.beam", "the beam's geometry belongs in [specimen.beam]"));
    }
    let family = parse_family(loc, "background", &bg.family)?;
    let size_mm = check_size(loc, "background", &bg.size_mm)?;
    if bg.tag.is_empty() {
        return Err(loc.err(Some(span), "background.tag", "at least one [[background.tag]] with world corners is required"));
    }
    let mut ids = HashSet::new();
    let mut tags = Vec::new();
    for (i, t) in bg.tag.iter().enumerate() {
        let t = t.get_ref();
        let key = format!("background.tag[{i}]");
        let id = *t.id.get_ref();
        if !ids.insert(id) {
            return Err(loc.err(Some(t.id.span()), &format!("{key}.id"), format!("duplicate background tag id {id}")));
        }
        if id >= family.code_count() {
            return Err(loc.err(
                Some(t.id.span()),
                &format!("{key}.id"),
                format!("{family} has ids 0..{}, got {id}", family.code_count() - 1),
            ));
        }
        let c = t.corners_mm.get_ref();
        let cspan = Some(t.corners_mm.span());
        if c.len() != 4 || c.iter().any(|p| p.len() != 3) {
            return Err(loc.err(
                cspan,
                &format!("{key}.corners_mm"),
                format!("expected 4 corners of [x, y, z] mm (bottom-left, bottom-right, top-right, top-left), got {} corners", c.len()),
            ));
        }
        let p: Vec<[f64; 3]> = c.iter().map(|p| [p[0], p[1], p[2]]).collect();
        check_square(&p, size_mm).map_err(|m| loc.err(cspan.clone(), &format!("{key}.corners_mm"), m))?;
        tags.push(BackgroundTag { id, corners_mm: [p[0], p[1], p[2], p[3]] });
    }
    Ok(BackgroundConfig { family, size_mm, tags })
}

/// Checks that four world corners form a planar square whose edge matches `size_mm`
/// (within 2 %, so measured positions with small survey errors pass).
fn check_square(p: &[[f64; 3]], size_mm: f64) -> Result<(), String> {
    let v = |a: usize, b: usize| nalgebra::Vector3::new(p[b][0] - p[a][0], p[b][1] - p[a][1], p[b][2] - p[a][2]);
    if p.iter().flatten().any(|x| !x.is_finite()) {
        return Err("corners must be finite numbers".into());
    }
    let edges = [v(0, 1), v(1, 2), v(2, 3), v(3, 0)];
    let lens: Vec<f64> = edges.iter().map(|e| e.norm()).collect();
    if lens.iter().any(|&l| l < 1e-6) {
        return Err("degenerate square: two corners coincide".into());
    }
    let mean = lens.iter().sum::<f64>() / 4.0;
    if lens.iter().any(|&l| (l - mean).abs() > 0.02 * mean) {
        return Err(format!("not a square: edge lengths {:.2?} mm differ", lens));
    }
    let d1 = v(0, 2).norm();
    let d2 = v(1, 3).norm();
    if (d1 - d2).abs() > 0.02 * d1 || (d1 - mean * 2f64.sqrt()).abs() > 0.03 * d1 {
        return Err(format!("not a square: diagonals {d1:.2} and {d2:.2} mm (edges {mean:.2} mm)"));
    }
    let n = edges[0].cross(&edges[1]).normalize();
    if n.dot(&v(0, 3)).abs() > 0.02 * mean {
        return Err("the four corners are not in one plane".into());
    }
    if (mean - size_mm).abs() > 0.02 * size_mm {
        return Err(format!("edge {mean:.2} mm does not match background.size_mm = {size_mm}"));
    }
    Ok(())
}

fn resolve_specimen(loc: &Locator<'_>, sp: Spanned<RawTagSet<SpecimenTagRaw>>) -> Result<SpecimenConfig, ConfigError> {
    let span = sp.span();
    let sp = sp.into_inner();
    let family = parse_family(loc, "specimen", &sp.family)?;
    let size_mm = check_size(loc, "specimen", &sp.size_mm)?;
    if sp.tag.is_empty() {
        return Err(loc.err(Some(span), "specimen.tag", "at least one [[specimen.tag]] is required"));
    }
    let mut ids = HashSet::new();
    let mut tags = Vec::new();
    for (i, t) in sp.tag.iter().enumerate() {
        let t = t.get_ref();
        let id = *t.id.get_ref();
        if !ids.insert(id) {
            return Err(loc.err(Some(t.id.span()), &format!("specimen.tag[{i}].id"), format!("duplicate specimen tag id {id}")));
        }
        if id >= family.code_count() {
            return Err(loc.err(
                Some(t.id.span()),
                &format!("specimen.tag[{i}].id"),
                format!("{family} has ids 0..{}, got {id}", family.code_count() - 1),
            ));
        }
        tags.push(SpecimenTag { id, role: t.role });
    }
    let beam = match &sp.beam {
        None => None,
        Some(b) => Some(b.get_ref().resolve().map_err(|(span, key, msg)| loc.err(Some(span), &format!("specimen.beam.{key}"), msg))?),
    };
    Ok(SpecimenConfig { family, size_mm, tags, beam })
}

fn validate_utm(loc: &Locator<'_>, u: Spanned<UtmConfig>) -> Result<UtmConfig, ConfigError> {
    let span = Some(u.span());
    let u = u.into_inner();
    if u.address != "sim" && u.address.parse::<std::net::SocketAddr>().is_err() && !u.address.contains(':') {
        return Err(loc.err(span, "utm.address", format!("\"{}\" is not host:port (e.g. \"192.0.2.10:502\") or \"sim\"", u.address)));
    }
    let table = span.clone().unwrap_or(0..0);
    if !(u.poll_hz.is_finite() && (MIN_POLL_HZ..=MAX_POLL_HZ).contains(&u.poll_hz)) {
        return Err(loc.err(
            Some(loc.key_span(table.clone(), "poll_hz")),
            "utm.poll_hz",
            format!("must be from {MIN_POLL_HZ} to {MAX_POLL_HZ} Hz, got {}", u.poll_hz),
        ));
    }
    if !(u.timeout_ms.is_finite() && u.timeout_ms >= 1.0 && u.timeout_ms <= MAX_TIMEOUT_MS) {
        return Err(loc.err(
            Some(loc.key_span(table, "timeout_ms")),
            "utm.timeout_ms",
            format!("must be from 1 to {MAX_TIMEOUT_MS} milliseconds, got {}", u.timeout_ms),
        ));
    }
    for (name, r) in [("load", Some(&u.load)), ("stroke", u.stroke.as_ref())] {
        if let Some(r) = r {
            if !(r.scale.is_finite() && r.offset.is_finite()) || r.scale == 0.0 {
                return Err(loc.err(
                    span.clone(),
                    &format!("utm.{name}.scale"),
                    "scale must be a non-zero finite number and offset finite",
                ));
            }
            if r.register as u32 + r.value_type.registers() as u32 > 65536 {
                return Err(loc.err(span.clone(), &format!("utm.{name}.register"), "register address out of range"));
            }
        }
    }
    Ok(u)
}
