//! The assembly of the sections: each checked by its component (a [`Problem`] with a key
//! path relative to the section, prefixed here), then the checks that span sections. The
//! tables are checked in a fixed order (world, sync, cameras — each camera's intrinsics taken
//! inline or imported from its calibration file —, background, specimen, utm, measure,
//! report, output, sim, sim camera names, output.mqtt, gauges, output.control, output.analog, clock_check,
//! verification); the first problem
//! found is the one reported.

use std::path::Path;

use tagdeflect_core::camera_config::{resolve_cameras, CameraConfig};
use tagdeflect_core::rig::{resolve_tag_sets, WorldConfig};
use tagdeflect_core::Problem;

use super::raw::RawConfig;
use super::{Config, SimSection};

/// Checks the whole raw file and builds the [`Config`]; `base` (the config's folder) anchors
/// relative paths (calibration files, recordings, outputs).
pub(super) fn config(raw: RawConfig, base: &Path) -> Result<Config, Problem> {
    let world = match raw.world {
        None => WorldConfig::default(),
        Some(w) => w.normalised().map_err(|p| p.within("world"))?,
    };
    let sync = raw.sync.unwrap_or_default();
    sync.validate().map_err(|p| p.within("sync"))?;
    let cameras = resolve_cameras(&raw.camera, base)?;
    let calibration_files = raw
        .camera
        .iter()
        .filter_map(|c| c.calibration.as_ref())
        .map(|c| tagdeflect_core::calibration_file::calibration_file_path(&base.join(c)))
        .collect();
    let (background, specimen) = resolve_tag_sets(raw.background.as_ref(), raw.specimen.as_ref())?;
    if let Some(u) = &raw.utm {
        u.validate().map_err(|p| p.within("utm"))?;
    }
    let measure = raw.measure.unwrap_or_default();
    measure.validate().map_err(|p| p.within("measure"))?;
    // [report] (the report's own checks live in tagdeflect_report::config).
    let report = match raw.report {
        None => None,
        Some(mut r) => {
            r.validate_with(specimen.beam.as_ref()).map_err(|p| p.within("report"))?;
            if r.out.is_relative() {
                r.out = base.join(&r.out);
            }
            Some(r)
        }
    };
    let output = raw.output.unwrap_or_default().resolve(base).map_err(|p| p.within("output"))?;
    check_sim(raw.sim.as_ref(), &cameras)?;
    let output = output.resolve_mqtt(base).map_err(|p| p.within("output"))?;
    let gauges = tagdeflect_core::gauge::resolve_gauges(&raw.gauge, &specimen)?;
    if let Some(c) = &output.control {
        let names: Vec<String> = gauges.iter().map(|g| g.name.clone()).collect();
        c.validate_against(&names).map_err(|p| p.within("output.control"))?;
    }
    if let Some(a) = &output.analog {
        let names: Vec<String> = gauges.iter().map(|g| g.name.clone()).collect();
        let utm = raw.utm.as_ref().map(|u| u.address.to_string());
        a.validate(&names, utm.as_deref()).map_err(|p| p.within("output.analog"))?;
    }
    if let Some(c) = &raw.clock_check {
        c.validate().map_err(|p| p.within("clock_check"))?;
    }
    let verification = match raw.verification {
        None => None,
        Some(mut v) => {
            v.validate().map_err(|p| p.within("verification"))?;
            v.certificate = base.join(&v.certificate);
            Some(v)
        }
    };
    let config = Config {
        world,
        sync,
        cameras,
        background,
        specimen,
        utm: raw.utm,
        output,
        report,
        measure,
        sim: raw.sim,
        gauges,
        clock_check: raw.clock_check,
        verification,
        calibration_files,
    };
    config.auto_rules()?;
    Ok(config)
}

/// `[sim]` checked by the simulator, and simulated cameras are the rig's cameras, by name
/// and in order.
#[cfg(feature = "sim")]
fn check_sim(sim: Option<&SimSection>, cameras: &[CameraConfig]) -> Result<(), Problem> {
    if let Some(sim) = sim {
        sim.validate().map_err(|p| p.within("sim"))?;
    }
    if !cameras.iter().any(|c| c.source.is_sim()) {
        return Ok(());
    }
    let params = sim.cloned().unwrap_or_default();
    let names = tagdeflect_sim::camera_names(params.cameras as usize);
    for (i, cam) in cameras.iter().enumerate() {
        if cam.source.is_sim() && names.get(i) != Some(&cam.name) {
            return Err(Problem::new(
                format!("camera[{i}].name"),
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

/// Without the simulator, `[sim]` is kept as written and simulated cameras or a simulated
/// UTM are refused when a run starts them, not at load: a recording made from the simulated
/// rig carries `source = "sim"` cameras and replays in every build (replay ignores camera
/// sources).
#[cfg(not(feature = "sim"))]
fn check_sim(_sim: Option<&SimSection>, _cameras: &[CameraConfig]) -> Result<(), Problem> {
    Ok(())
}
