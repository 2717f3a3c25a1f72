//! `demo --c1609`: the README's day as a test a lab would accept. A fibre-reinforced concrete
//! beam (elastic to a first crack, a drop, then softening to a residual load) is loaded in
//! simulated time at ASTM C1609's rates for a 150 mm deep beam (seated slowly to its preload,
//! then 0.09 mm/min of net deflection up to L/900, then 0.27 mm/min), filmed by the simulated
//! cameras and written as a recording; the recording is then played through the live pipeline `speed` times faster
//! than recorded — the feed, the UTM samples and the test folder keep the simulated times, so
//! the report checks the rates against the feed's `t_ns` as it would a real test's.
//! `[output.auto_test]` starts the test at the method's preload and stops it past L/150; the
//! report is made at stop (docs/simulation.md, "A demo that is a test").

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use tagdeflect_io::recording::FrameFormat;
use tagdeflect_sim::{LoadLaw, SimParams, SimRig};
use tagdeflect_sinks::lab_test::auto::AutoTestConfig;

use crate::config::{BeamConfig, Config};
use crate::graph::page::HttpOptions;

/// The rate up to L/900 (C1609, beams deeper than 125 mm: 0.035–0.10 mm/min), mm/min: near
/// the window's top, the test as short as the standard allows.
pub const RATE_TO_L900_MM_PER_MIN: f64 = 0.09;
/// The rate from L/900 on (C1609, deeper beams: 0.05–0.30 mm/min), mm/min.
pub const RATE_AFTER_L900_MM_PER_MIN: f64 = 0.27;
/// The seating: the machine brings the beam to its preload slowly (mm/min up to mm of
/// deflection, 1.5 kN on the demo's beam) before the test's rate, so the zero is taken on a
/// load that hardly moves; below the tenth of L/900 that the first phase's rate is checked from.
pub const SEATING_MM_PER_MIN: f64 = 0.01;
/// Where the seating ends, mm of midspan deflection.
pub const SEATING_END_MM: f64 = 0.003;
/// How far past L/150 the automatic stop lets the test go, mm.
pub const END_MARGIN_MM: f64 = 0.1;
/// Frame sets at rest before the seating: the pipeline has found every camera's pose before
/// the load rises.
const REST_FRAMES: u32 = 20;
/// The simulated beam's stiffness, kN/mm, and its first crack, mm: a 150 × 150 mm beam on a
/// 450 mm span cracking at about 35 kN (f1 ≈ 4.7 MPa).
const STIFFNESS_KN_PER_MM: f64 = 500.0;
const CRACK_DEFLECTION_MM: f64 = 0.07;

/// How the demo's test is made and played.
#[derive(Debug, Clone)]
pub struct DemoTest {
    /// How many times faster than the simulated time the test is played.
    pub speed: f64,
    /// Two cameras with 2 × 2 sub-samples per pixel instead of three with 4 × 4 (quicker to
    /// render).
    pub small: bool,
    /// Where the recording (`recording/`) and the tests' folder (`tests/`) go.
    pub root: PathBuf,
}

impl DemoTest {
    /// The simulated rig and test: C1609's loading, a softening beam.
    pub fn params(&self) -> SimParams {
        let (cameras, subsamples) = if self.small { (2, 2) } else { (3, 4) };
        let mut p = SimParams {
            cameras,
            width: 640,
            height: 480,
            fps: 1.0,
            rest_frames: REST_FRAMES,
            subsamples,
            load_law: LoadLaw::Softening,
            stiffness_kn_per_mm: STIFFNESS_KN_PER_MM,
            crack_deflection_mm: CRACK_DEFLECTION_MM,
            crack_drop: 0.15,
            residual_ratio: Some(0.45),
            softening_mm: 1.0,
            start_ns: tagdeflect_core::clock::now_epoch_ns(),
            ..SimParams::default()
        };
        let l900 = p.span_mm / 900.0;
        p.max_deflection_mm = p.span_mm / 150.0 + END_MARGIN_MM + 0.1;
        p.rates = format!("{SEATING_MM_PER_MIN}:{SEATING_END_MM},{RATE_TO_L900_MM_PER_MIN}:{l900},{RATE_AFTER_L900_MM_PER_MIN}");
        // The loading, then 20 s held (the stop and its report are made meanwhile).
        let rig = SimRig::new(&p).expect("the demo's test is valid");
        let loading_s = rig.rates_end_s().unwrap_or(0.0);
        p.frame_sets = p.rest_frames + (loading_s * p.fps).ceil() as u32 + 20;
        p
    }

    /// The config the test is played with: the rig's, its beam, the UTM (played from the
    /// recording), the tests' folder and the automatic start (at the method's preload) and stop.
    pub fn config(&self, rig: &SimRig) -> Config {
        let p = rig.params();
        let mut cfg = Config::from_sim(rig);
        cfg.utm = Some(tagdeflect_sim::live_rig::demo_utm());
        cfg.specimen.beam =
            Some(BeamConfig { width_mm: p.beam_width_mm, depth_mm: p.beam_height_mm, span_mm: p.span_mm, ..BeamConfig::default() });
        cfg.output.tests = Some(self.root.join("tests"));
        cfg.output.auto_test = Some(AutoTestConfig {
            start_load_kn: 0.5,
            rearm_load_kn: None,
            specimen: "demo-c1609".into(),
            standard: Some("astm-c1609".into()),
            method: Some("C1609-19".into()),
            stop_at_end: true,
            end_margin_mm: END_MARGIN_MM,
            stop_below_peak_fraction: 0.0,
        });
        cfg.checked("<demo --c1609>").expect("the demo test's config is valid")
    }

    /// Simulates the test into `root/recording` and plays it (see the module doc); returns
    /// the test's folder once its report is made.
    /// `linger`: the page stays up after the test until a signal.
    pub fn run(&self, http: Option<HttpOptions>, linger: bool) -> Result<PathBuf> {
        std::fs::create_dir_all(&self.root).with_context(|| format!("cannot create {}", self.root.display()))?;
        let params = self.params();
        let rig = SimRig::new(&params)?;
        let rec = self.root.join("recording");
        eprintln!(
            "demo --c1609: simulating {} frame sets ({:.1} min of an ASTM C1609 test at {RATE_TO_L900_MM_PER_MIN} then {RATE_AFTER_L900_MM_PER_MIN} mm/min) into {}",
            params.frame_sets,
            params.frame_sets as f64 / params.fps / 60.0,
            rec.display()
        );
        let started = Instant::now();
        crate::commands::simulate::simulate_as(&params, &rec, FrameFormat::Png)?;
        eprintln!("simulated in {:.0} s; playing it {}× faster than recorded", started.elapsed().as_secs_f64(), self.speed);
        tagdeflect_io::sources::playback::set_playback_speed(self.speed);
        let config = self.config(&rig);
        crate::graph::entry::replay_as_test(&rec, config, http, linger)?;
        let folder = wait_for_report(&self.root.join("tests"), Duration::from_secs(120))?;
        print_verdict(&folder)?;
        Ok(folder)
    }
}

/// The one test folder under `tests`, once its `test.json` (written last) is there.
fn wait_for_report(tests: &Path, timeout: Duration) -> Result<PathBuf> {
    let until = Instant::now() + timeout;
    loop {
        let done: Vec<PathBuf> = std::fs::read_dir(tests)
            .map(|d| d.flatten().map(|e| e.path()).filter(|p| p.join("test.json").is_file()).collect())
            .unwrap_or_default();
        if let Some(f) = done.into_iter().next() {
            return Ok(f);
        }
        if Instant::now() > until {
            bail!("the demo's test did not stop with a report within {} s (see the log above)", timeout.as_secs());
        }
        std::thread::sleep(Duration::from_millis(200));
    }
}

/// Prints the report's verdict and its main values on stderr.
fn print_verdict(folder: &Path) -> Result<()> {
    let path = folder.join("report").join("report.json");
    let text = std::fs::read_to_string(&path).with_context(|| format!("the test made no report: {}", path.display()))?;
    let j: serde_json::Value = serde_json::from_str(&text).with_context(|| format!("{}", path.display()))?;
    let num =
        |k: &str| j.get(k).and_then(|v| v.get("value").or(Some(v))).and_then(|v| v.as_f64()).map_or("—".into(), |v| format!("{v:.3}"));
    eprintln!(
        "test {}: valid {} — f1 {} MPa, f600 {} MPa, f150 {} MPa; report: {}",
        folder.display(),
        j["valid"],
        num("f1"),
        num("f600"),
        num("f150"),
        folder.join("report").join("report.html").display()
    );
    if let Some(r) = j["invalid_reasons"].as_array().filter(|r| !r.is_empty()) {
        for reason in r {
            eprintln!("  invalid: {}", reason.as_str().unwrap_or_default());
        }
    }
    Ok(())
}
