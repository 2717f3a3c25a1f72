//! The whole configuration: one field per section, each section's type owned by the
//! component that uses it. It is what [`super::Config::load`] hands out after validation,
//! and what [`super::Config::to_toml_string`] writes into a recording, so a field's
//! `skip_serializing_if` keeps old recordings' configs as they were.

use serde::{Deserialize, Serialize};

use tagdeflect_core::camera_config::CameraConfig;
use tagdeflect_core::gauge::GaugeConfig;
use tagdeflect_core::rig::{BackgroundConfig, SpecimenConfig, TagRole, WorldConfig};
use tagdeflect_core::verification::VerificationConfig;
use tagdeflect_estimate::clock_offset::ClockCheckConfig;
use tagdeflect_estimate::measure_config::MeasureConfig;
use tagdeflect_io::sync::SyncConfig;
use tagdeflect_io::utm::config::UtmConfig;
use tagdeflect_report::ReportConfig;
use tagdeflect_sinks::output::OutputConfig;

/// `[sim]` as this build takes it: the simulated rig's parameters with the `sim` feature;
/// without it the table is kept as written (a recording made from the simulated rig still
/// replays; `source = "sim"` and `utm.address = "sim"` are refused at load).
#[cfg(feature = "sim")]
pub type SimSection = tagdeflect_sim::SimParams;
/// `[sim]` as this build takes it (built without the `sim` feature): kept as written.
#[cfg(not(feature = "sim"))]
pub type SimSection = toml::Table;

/// The whole, validated configuration.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
    /// World orientation.
    #[serde(default)]
    pub world: WorldConfig,
    /// Frame-set assembly.
    #[serde(default)]
    pub sync: SyncConfig,
    /// The cameras, in order (1 to 3 in a typical rig).
    #[serde(rename = "camera")]
    pub cameras: Vec<CameraConfig>,
    /// Tags fixed to the frame or bench: they define the world.
    pub background: BackgroundConfig,
    /// Tags on the beam: what is measured.
    pub specimen: SpecimenConfig,
    /// The testing machine over Modbus TCP (optional).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub utm: Option<UtmConfig>,
    /// Where `run` and `demo` send what they make.
    #[serde(default)]
    pub output: OutputConfig,
    /// The test report `run` writes at its end (optional; see `report`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub report: Option<ReportConfig>,
    /// Measurement options (extension of SPEC; all optional).
    #[serde(default)]
    pub measure: MeasureConfig,
    /// Parameters of the built-in simulated rig (extension of SPEC; used by
    /// `source = "sim"` cameras, `utm.address = "sim"` and `simulate`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sim: Option<SimSection>,
    /// Virtual gauges (`[[gauge]]`, see `tagdeflect_estimate::gauges`).
    #[serde(rename = "gauge", default, skip_serializing_if = "Vec::is_empty")]
    pub gauges: Vec<GaugeConfig>,
    /// The live clock check (`[clock_check]`, extension; see `tagdeflect_estimate::clock_offset`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub clock_check: Option<ClockCheckConfig>,
    /// The verification in force (`[verification]`, extension; see
    /// `tagdeflect_core::verification`): its certificate, resolved against the config's folder.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub verification: Option<VerificationConfig>,
    /// The calibration files the cameras' intrinsics were imported from (`[[camera]]
    /// calibration`, the file part of `file.yaml#cam1`), resolved against the config's folder;
    /// hashed into every test's `test.json`. Not written back: a written config carries the
    /// intrinsics inline.
    #[serde(skip)]
    pub calibration_files: Vec<std::path::PathBuf>,
}

impl Config {
    /// Index of the camera with this name.
    pub fn camera_index(&self, name: &str) -> Option<usize> {
        self.cameras.iter().position(|c| c.name == name)
    }

    /// Role of a specimen tag.
    pub fn role_of(&self, id: u32) -> Option<TagRole> {
        self.specimen.role_of(id)
    }

    /// What the measurement is built from.
    pub fn measurement(&self) -> tagdeflect_estimate::measure::MeasurementRig {
        tagdeflect_estimate::measure::MeasurementRig {
            world: self.world.clone(),
            cameras: self.cameras.clone(),
            background: self.background.clone(),
            specimen: self.specimen.clone(),
            measure: self.measure.clone(),
            gauges: self.gauges.clone(),
            clock_check: self.clock_check.clone(),
            utm_poll_hz: self.utm.as_ref().map(|u| u.poll_hz),
        }
    }

    /// What the live page, the metrics and the MQTT status show of the rig.
    pub fn rig_info(&self) -> tagdeflect_sinks::RigInfo {
        tagdeflect_sinks::RigInfo {
            cameras: self.cameras.clone(),
            world: self.world.clone(),
            specimen: self.specimen.clone(),
            utm: self.utm.as_ref().map(|u| u.address.clone()),
            cmod_gauge: self.cmod_gauge(),
            rate_windows: match &self.specimen.beam {
                None => Default::default(),
                Some(beam) => {
                    [tagdeflect_report::Standard::AstmC1609, tagdeflect_report::Standard::AstmC1856, tagdeflect_report::Standard::En14651]
                        .into_iter()
                        .filter_map(|std| {
                            let name = serde_json::to_value(std).ok()?.as_str()?.to_string();
                            let w = serde_json::to_value(tagdeflect_report::validity::rate_windows(std, beam)).ok()?;
                            Some((name, w))
                        })
                        .collect()
                }
            },
        }
    }

    /// The CMOD gauge by the report's rule ([`tagdeflect_report::choose_cmod_gauge`]) among
    /// the configured gauges: `[report] cmod_gauge`, else the one `opening` gauge, else the
    /// gauge named `cmod` (any case), else the only one named like an opening.
    pub fn cmod_gauge(&self) -> Option<String> {
        let names: Vec<String> = self.gauges.iter().map(|g| g.name.clone()).collect();
        let asked = self.report.as_ref().and_then(|r| r.cmod_gauge.as_deref());
        tagdeflect_report::choose_cmod_gauge(&self.gauges, &names, asked).ok()
    }

    /// [`tagdeflect_core::verification::geometry_sha256`] of this config: what a verification
    /// certificate records and a later run compares.
    pub fn geometry_sha256(&self) -> String {
        tagdeflect_core::verification::geometry_sha256(self.world.up, &self.background, &self.specimen, &self.cameras)
    }

    /// The rig as the verification in force is compared with (`bumps` and `camera_poses` added
    /// by whoever saw them).
    pub fn rig_now(&self) -> anyhow::Result<tagdeflect_core::verification::RigNow> {
        let mut calibration_files = Vec::new();
        for p in self.calibration_files.iter().filter(|p| p.is_file()) {
            let sha256 = tagdeflect_report::sha256_file(p).map_err(|e| anyhow::anyhow!("hashing {}: {e}", p.display()))?;
            calibration_files.push(tagdeflect_core::verification::HashedPath { path: p.display().to_string(), sha256 });
        }
        Ok(tagdeflect_core::verification::RigNow { calibration_files, geometry_sha256: self.geometry_sha256(), ..Default::default() })
    }

    /// The posed cameras' placements, by name (`poses` in the config's camera order).
    pub fn camera_placements(
        &self,
        poses: &[Option<tagdeflect_core::camera::Pose>],
    ) -> Vec<tagdeflect_core::verification::CameraPlacement> {
        let placed = |(c, p): (&tagdeflect_core::camera_config::CameraConfig, &Option<tagdeflect_core::camera::Pose>)| {
            p.as_ref().map(|p| tagdeflect_core::verification::CameraPlacement::from_pose(&c.name, p))
        };
        self.cameras.iter().zip(poses).filter_map(placed).collect()
    }

    /// The verification in force now (`None` without `[verification]`).
    pub fn verification_in_force(&self) -> anyhow::Result<Option<tagdeflect_core::verification::InForce>> {
        self.verification_in_force_placed(&[])
    }

    /// [`Config::verification_in_force`] with the cameras posed now at `placed` (compared with
    /// where they were when verified).
    pub fn verification_in_force_placed(
        &self,
        placed: &[tagdeflect_core::verification::CameraPlacement],
    ) -> anyhow::Result<Option<tagdeflect_core::verification::InForce>> {
        let Some(v) = &self.verification else { return Ok(None) };
        let now_ns = tagdeflect_core::clock::now_epoch_ns();
        let mut now = self.rig_now()?;
        now.camera_poses = placed.to_vec();
        Ok(Some(tagdeflect_core::verification::assess(&v.certificate, v.valid_days, &now, now_ns)?))
    }

    /// What the report needs of the rig.
    pub fn test_rig(&self) -> tagdeflect_report::TestRig {
        tagdeflect_report::TestRig { world: self.world.clone(), specimen: self.specimen.clone(), gauges: self.gauges.clone() }
    }

    /// The rules of `[output.auto_test]` with what the rest of the config says about a
    /// test's end: the standard (the table's, else `[report] standard`), the span
    /// (`[specimen.beam]`) for ASTM's L/150, and the CMOD gauge for EN 14651's 4 mm —
    /// `[report] cmod_gauge`, else the one `opening` gauge, else the gauge named `cmod`.
    /// A problem (key under `output.auto_test`) when an end the table asks for cannot be
    /// known, or there is no load to start from.
    pub fn auto_rules(&self) -> Result<Option<tagdeflect_sinks::lab_test::auto::AutoRules>, tagdeflect_core::Problem> {
        use tagdeflect_core::Problem;
        let Some(c) = &self.output.auto_test else { return Ok(None) };
        let here = |k: &str, m: String| Err(Problem::new(format!("output.auto_test{k}"), m));
        if self.utm.is_none() {
            return here("", "an automatic start needs the load: configure [utm] (the testing machine)".into());
        }
        let report_standard =
            self.report.as_ref().and_then(|r| serde_json::to_value(r.standard).ok()).and_then(|v| v.as_str().map(str::to_string));
        let method = match (&c.method, &self.output.tests) {
            (None, _) => None,
            (Some(name), tests) => {
                let tests = tests.as_deref().unwrap_or(std::path::Path::new("."));
                match tagdeflect_core::method::library::find(tests, name) {
                    Ok(m) => Some(m),
                    Err(e) => return here(".method", e.to_string()),
                }
            }
        };
        if let (Some(m), Some(s)) = (&method, &c.standard) {
            if *s != m.method.standard {
                return here(".standard", format!("\"{s}\" but method {} is {}", m.method.name, m.method.standard));
            }
        }
        let standard = method.as_ref().map(|m| m.method.standard.clone()).or(c.standard.clone()).or(report_standard);
        let span_mm = self.specimen.beam.as_ref().map(|b| b.span_mm);
        let cmod_gauge = self.cmod_gauge();
        if c.stop_at_end {
            match standard.as_deref() {
                Some("astm-c1609" | "astm-c1856") if span_mm.is_none() => {
                    return here(".standard", "the test's end (L/150) needs the span: add [specimen.beam] with span_mm, or set stop_at_end = false".into())
                }
                Some("en-14651") if cmod_gauge.is_none() => {
                    return here(
                        ".standard",
                        "EN 14651's end (CMOD 4 mm) needs a CMOD gauge: add an `opening` [[gauge]] across the notch (or name one in [report] cmod_gauge), or set stop_at_end = false".into(),
                    )
                }
                _ => {}
            }
        }
        Ok(Some(tagdeflect_sinks::lab_test::auto::AutoRules {
            config: c.clone(),
            standard,
            span_mm,
            cmod_gauge,
            method: method.map(|m| (m.method.clone(), m.reference())),
        }))
    }
}

impl tagdeflect_io::recording::RecordedConfig for Config {
    type Error = super::ConfigError;
    fn load(path: &std::path::Path) -> Result<Self, Self::Error> {
        Config::load(path)
    }
    fn cameras(&self) -> &[CameraConfig] {
        &self.cameras
    }
    fn to_toml_string(&self) -> String {
        Config::to_toml_string(self)
    }
}
