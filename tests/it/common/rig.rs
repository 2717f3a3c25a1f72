//! The simulated rig as a live run's config (`demo --config`), and a test's scratch folder
//! kept when the test fails.

use std::path::{Path, PathBuf};

use tagdeflect::config::Config;
use tagdeflect_report::BeamConfig;
use tagdeflect_sim::{SimParams, SimRig};

/// The simulated rig of `params` as a config, with the demo's simulated UTM (the one
/// `Config::demo` has).
pub fn sim_rig_config(params: &SimParams) -> Config {
    let mut cfg = Config::from_sim(&SimRig::new(params).unwrap());
    cfg.utm = Some(tagdeflect_sim::live_rig::demo_utm());
    cfg
}

/// The simulated beam's width, depth and span as `[specimen.beam]` (no notch, no tolerances).
pub fn sim_beam(params: &SimParams) -> BeamConfig {
    BeamConfig { width_mm: params.beam_width_mm, depth_mm: params.beam_height_mm, span_mm: params.span_mm, ..Default::default() }
}

/// [`sim_rig_config`] with [`sim_beam`]: the beam rig a test's report needs.
pub fn beam_rig_config(params: &SimParams) -> Config {
    let mut cfg = sim_rig_config(params);
    cfg.specimen.beam = Some(sim_beam(params));
    cfg
}

/// A test's scratch folder under the build's `target/tmp/`, removed when the test passes and
/// kept (its path printed) when it fails: the logs and files of a failure seen once stay to
/// be read.
pub struct KeptOnFailure {
    dir: Option<tempfile::TempDir>,
}

impl KeptOnFailure {
    /// A new folder named after `test`.
    pub fn new(test: &str) -> Self {
        let base = PathBuf::from(env!("CARGO_TARGET_TMPDIR"));
        std::fs::create_dir_all(&base).unwrap();
        Self { dir: Some(tempfile::Builder::new().prefix(&format!("{test}-")).tempdir_in(base).unwrap()) }
    }

    /// The folder.
    pub fn path(&self) -> &Path {
        self.dir.as_ref().expect("the folder").path()
    }
}

impl Drop for KeptOnFailure {
    fn drop(&mut self) {
        if std::thread::panicking() {
            let kept = self.dir.take().expect("the folder").keep();
            eprintln!("the test failed: its folder is kept at {}", kept.display());
        }
    }
}
