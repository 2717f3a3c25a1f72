//! `[sim]`: the parameters of the built-in simulated rig ([`SimParams`]), their defaults and
//! their checks, and the names of the rig's cameras. They are config: a config's `[sim]`
//! table, the options of `tagdeflect simulate`, what `source = "sim"` cameras and
//! `utm.address = "sim"` run. The simulator (the top-level `sim` module) is built from them
//! and imports them from here; the config never imports the simulator.

use serde::{Deserialize, Serialize};

mod check;
mod defaults;
mod phases;

use defaults::{
    is_default, is_default_bits, is_default_crack, is_default_drift_rot, is_default_drift_trans, is_default_drop, is_default_fill,
    is_default_notch, is_default_notch_width, is_default_outage, is_default_softening,
};

/// Unix time of the first frame set of a simulated recording (2026-01-01T00:00:00Z), ns.
pub const DEFAULT_START_NS: i64 = 1_767_225_600_000_000_000;

/// The load law of the simulated specimen (`simulate --load-law`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "kebab-case")]
pub enum LoadLaw {
    /// Load proportional to deflection throughout.
    #[default]
    Elastic,
    /// Elastic to the first crack, then a drop and softening to the residual level.
    Softening,
    /// Elastic to the first crack, then a small drop and hardening to the residual level.
    Hardening,
}

/// The kind of test simulated (`simulate --test`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "kebab-case")]
pub enum SimTest {
    /// Unnotched beam, two loads at `±load_span/2` (ASTM C1609 with `load_span = span/3`).
    #[default]
    FourPoint,
    /// Notched beam, one centre load, notch at midspan (EN 14651).
    ThreePointNotched,
}

/// The simulated rig's three camera places, left to right.
pub const SIM_CAMERA_NAMES: [&str; 3] = ["left", "centre", "right"];

/// Which of the three camera places ([`SIM_CAMERA_NAMES`]) a rig of `count` cameras uses.
pub fn camera_places(count: usize) -> Vec<usize> {
    match count {
        1 => vec![1],
        2 => vec![0, 2],
        _ => vec![0, 1, 2],
    }
}

/// The names of a rig's cameras, in order (what a config with `sim` cameras must list).
pub fn camera_names(count: usize) -> Vec<String> {
    camera_places(count).into_iter().map(|k| SIM_CAMERA_NAMES[k].to_string()).collect()
}

/// Parameters of the simulated rig (`[sim]` in a config; the options of `simulate`).
///
/// Every field is also a `--kebab-case` option of `tagdeflect simulate` (flatten this
/// struct into the subcommand with `#[command(flatten)]`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
#[serde(deny_unknown_fields, default)]
pub struct SimParams {
    /// Seed of every random choice (noise, jitter, dropped frames, texture); 0 to 2^63 - 1
    /// (it is written into the recording's TOML config, whose integers are signed 64-bit).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 1, value_parser = clap::value_parser!(u64).range(..=i64::MAX as u64)))]
    pub seed: u64,
    /// Number of cameras (1 to 3): 1 = centre, 2 = left + right, 3 = left + centre + right.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 3))]
    pub cameras: u32,
    /// Image width, pixels (the focal length follows the width of a 4:3 frame: the view stays the same).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 1280))]
    pub width: u32,
    /// Image height, pixels.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 960))]
    pub height: u32,
    /// Number of frame sets to write.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 40))]
    pub frame_sets: u32,
    /// Frame rate of every camera, Hz.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 10.0))]
    pub fps: f64,
    /// Sensor noise, standard deviation in grey levels (added after the blur).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 2.0))]
    pub noise_sigma: f64,
    /// Optical blur, standard deviation of a Gaussian in pixels (0 = none).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 0.6))]
    pub blur_sigma: f64,
    /// Discrete Gaussian kernel over the integrated pixels (the camera's processing after
    /// the pixel, not the optics), standard deviation in pixels (0 = none).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 0.0))]
    #[serde(skip_serializing_if = "is_default")]
    pub post_blur_px: f64,
    /// Amount of a 3×3 sharpening kernel over the integrated pixels (0 = none, 1 = the
    /// identity plus the image minus its 4-neighbour mean).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 0.0))]
    #[serde(skip_serializing_if = "is_default")]
    pub sharpen: f64,
    /// A colour (RGGB Bayer) sensor: the grey scene's mosaic demosaiced bilinearly and
    /// converted back to grey.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = false))]
    #[serde(skip_serializing_if = "is_default")]
    pub bayer: bool,
    /// A colour (RGGB Bayer) sensor whose raw mosaic the product converts (V4L2 `RGGB`,
    /// GenICam `BayerRG8`): the grey scene through the sites' unequal responses to grey (red
    /// 0.62, greens 1.0 and 0.98, blue 0.74), read noise at each photosite, 8 bits, then the
    /// product's conversion (each site's gain equalised, no demosaic). 8-bit only; not with
    /// `bayer`.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = false))]
    #[serde(skip_serializing_if = "is_default")]
    pub bayer_raw: bool,
    /// Radius of a defocus disk before the pixel (the optics: a lens focused off the target
    /// plane spreads a point's light uniformly over a disk), pixels (0 = none).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 0.0))]
    #[serde(skip_serializing_if = "is_default")]
    pub defocus_radius_px: f64,
    /// An elliptical (astigmatic) Gaussian blur before the pixel: σ along its major axis,
    /// pixels (0 = none; with `astig_minor_px` and `astig_angle_deg`).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 0.0))]
    #[serde(skip_serializing_if = "is_default")]
    pub astig_major_px: f64,
    /// σ of the elliptical blur across its major axis, pixels (0 < minor ≤ major).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 0.0))]
    #[serde(skip_serializing_if = "is_default")]
    pub astig_minor_px: f64,
    /// Angle of the elliptical blur's major axis from the image's x axis towards its y axis
    /// (down), degrees.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 0.0, allow_hyphen_values = true))]
    #[serde(skip_serializing_if = "is_default")]
    pub astig_angle_deg: f64,
    /// Fraction of each pixel's area that integrates the light (a centred square; 1 = the
    /// whole pixel).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 1.0))]
    #[serde(skip_serializing_if = "is_default_fill")]
    pub fill_factor: f64,
    /// JPEG compression of every stored frame at this quality (1 to 100; none by default):
    /// the frame is encoded and decoded as a camera that sends JPEG would.
    #[cfg_attr(feature = "clap", arg(long))]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub jpeg_quality: Option<u8>,
    /// Bit depth of the sensor's digitisation (8 to 16): noise is added to the light, which
    /// is digitised to this many bits and kept at that depth (above 8: recordings hold 16-bit
    /// PNG frames with an `sBIT` chunk; with `jpeg_quality` the frames are 8-bit JPEG).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 8))]
    #[serde(skip_serializing_if = "is_default_bits")]
    pub bit_depth: u32,
    /// Exposure, as a fraction of the light of the default scene (whose tags' black and white
    /// are 28 and 228 grey levels of 8 bits): a shorter exposure or a dimmer lab scales every
    /// level before digitisation (e.g. 0.0625: black 1.75, white 14.25). `noise_sigma` stays the
    /// read noise, in grey levels of 8 bits.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 1.0))]
    #[serde(skip_serializing_if = "is_default_fill")]
    pub exposure: f64,
    /// Full-well capacity of the sensor, electrons at the top of its range (255 grey levels
    /// of 8 bits): each pixel's photon shot noise is drawn from its electron count (σ = √e)
    /// before the camera's processing after the pixel; 0 = no shot noise (`noise_sigma` alone).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 0.0))]
    #[serde(skip_serializing_if = "is_default")]
    pub full_well_e: f64,
    /// Motion blur (camera shake) on every n-th frame set, one camera at a time in turn (0 = never).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 0))]
    pub motion_blur_every: u32,
    /// Length of the motion-blur streak, pixels.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 3.0))]
    pub motion_blur_px: f64,
    /// Per-frame timing jitter of each camera, standard deviation in ms (clipped at 3 sigma).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 1.0))]
    pub jitter_ms: f64,
    /// Probability that a camera drops a frame (the frame is simply absent).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 0.0))]
    pub drop_prob: f64,
    /// Camera (index from 0) bumped mid-run; none by default.
    #[cfg_attr(feature = "clap", arg(long))]
    pub bump_camera: Option<u32>,
    /// Frame set from which the bumped camera has its new pose.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 20))]
    pub bump_at: u32,
    /// Rotation of the bump, degrees (about an oblique axis through the camera centre).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 0.3))]
    pub bump_rot_deg: f64,
    /// Translation of the bump, mm.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 2.0))]
    pub bump_trans_mm: f64,
    /// Camera (index from 0) that drifts slowly (thermal, creep) over the recording; none by
    /// default. Its pose turns and shifts linearly from the first frame set to the last.
    #[cfg_attr(feature = "clap", arg(long))]
    pub drift_camera: Option<u32>,
    /// Total rotation of the drift over the recording, degrees (about an oblique, mostly
    /// horizontal axis through the camera centre).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 0.05, allow_hyphen_values = true))]
    #[serde(skip_serializing_if = "is_default_drift_rot")]
    pub drift_rot_deg: f64,
    /// Total shift of the drifting camera's centre over the recording, mm (mostly downward).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 0.3, allow_hyphen_values = true))]
    #[serde(skip_serializing_if = "is_default_drift_trans")]
    pub drift_trans_mm: f64,
    /// Frame set at which the drift starts (before it the camera is still): a leg settling
    /// in the middle of a test.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 0))]
    #[serde(skip_serializing_if = "is_default")]
    pub drift_start_set: u32,
    /// Frame sets over which the drift happens, from `drift_start_set` on (the camera is
    /// still again after them); 0: until the last frame set.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 0))]
    #[serde(skip_serializing_if = "is_default")]
    pub drift_sets: u32,
    /// Specimen tag id hidden (covered by a grey card) from one camera for a while; none by default.
    #[cfg_attr(feature = "clap", arg(long))]
    pub hide_tag: Option<u32>,
    /// Background tag id (tag25h9) hidden (covered by a grey card, as by a person walking
    /// past) from `hide_camera` over the same frame sets as `hide_tag`; none by default.
    #[cfg_attr(feature = "clap", arg(long))]
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub hide_background_tag: Option<u32>,
    /// Camera (index from 0) that loses sight of `hide_tag` and `hide_background_tag`.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 0))]
    pub hide_camera: u32,
    /// First frame set in which the tag is hidden.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 10))]
    pub hide_from: u32,
    /// Number of frame sets the tag stays hidden.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 10))]
    pub hide_count: u32,
    /// Radial distortion k1 of every camera (mild lens; k2 = -k1/2, tiny tangential terms).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = -0.05, allow_hyphen_values = true))]
    pub k1: f64,
    /// Camera (index from 0) with a strongly distorting lens; none by default.
    #[cfg_attr(feature = "clap", arg(long))]
    pub strong_distortion_camera: Option<u32>,
    /// k1 of the strongly distorting lens.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = -0.25, allow_hyphen_values = true))]
    pub strong_k1: f64,
    /// Midspan deflection at the end of the ramp, mm (positive downward).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 6.0))]
    pub max_deflection_mm: f64,
    /// Frame sets at rest before the load ramp starts.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 3))]
    pub rest_frames: u32,
    /// Frame sets held at `max_deflection_mm` at the end of the recording, after the ramp
    /// (0: the ramp ends at the last frame set). With `rest_frames + hold_frames ≥
    /// frame_sets − 1` there is no ramp: the deflection steps from 0 to the maximum at set
    /// `rest_frames` (a step response, `bench --estimators`). Not with `cyclic`.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 0))]
    #[serde(skip_serializing_if = "is_default")]
    pub hold_frames: u32,
    /// The seating, frame sets (0, the default: none): after the rest the machine brings the
    /// beam slowly to `seat_mm` over this many sets — as a real machine seats a specimen up to
    /// its preload before loading it at the method's rate — and the ramp goes on from there
    /// over the sets left. Counted in frame sets, so no load on the PC changes the load a set sees.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 0))]
    #[serde(skip_serializing_if = "is_default")]
    pub seat_frames: u32,
    /// The midspan deflection at the end of the seating, mm (just above the preload's).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 0.0))]
    #[serde(skip_serializing_if = "is_default")]
    pub seat_mm: f64,
    /// The ramp's first part, from the seating's end (or from 0) up to this midspan deflection
    /// (mm), at a quarter of the rate of the rest, the ramp's time unchanged — as an EN 14651
    /// machine loads at 0.05 mm/min of CMOD up to 0.1 mm, then at 0.2 mm/min (§8). 0, the
    /// default: one rate.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 0.0))]
    #[serde(default, skip_serializing_if = "is_default")]
    pub slow_to_mm: f64,
    /// A verification run instead of a test (docs/verification.md): the beam is a rigid bar,
    /// moved as one (no bending, no load) by these vertical displacements, mm downward,
    /// comma-separated (e.g. "0,0.5,1,2,1,0.5,0"), each held for an equal share of
    /// `frame_sets`; the steps and their time windows are written to `verify_steps.json`.
    /// Empty: a test.
    #[cfg_attr(feature = "clap", arg(long, default_value = ""))]
    #[serde(skip_serializing_if = "String::is_empty")]
    pub verify_steps: String,
    /// A test loaded at given rates instead of the ramp over `frame_sets`: the midspan
    /// deflection's rate by phase, `RATE[:UNTIL_MM],…` in mm/min (e.g. "0.075:0.5,0.25": 0.075
    /// mm/min up to 0.5 mm, then 0.25 mm/min), after the rest and up to `max_deflection_mm`
    /// (held there); a standard's loading in simulated time. Takes the place of `cyclic`.
    /// Empty: the ramp.
    #[cfg_attr(feature = "clap", arg(long, default_value = ""))]
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub rates: String,
    /// With `verify_steps`: the half width (mm, along the beam from midspan) of the block a
    /// stage moves, the rest of the bar held still — a two-part verification target whose
    /// midspan tags drop by the steps while the support tags stay, so the net deflection (and
    /// the `net` gauge, added to the config) follows the steps. 0: the whole bar moves.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 0.0))]
    #[serde(skip_serializing_if = "is_default")]
    pub verify_stage_half_width_mm: f64,
    /// Repeat the load history (rest, ramp up, ramp down) instead of holding at the maximum
    /// after the ramp (for long live demos).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = false))]
    pub cyclic: bool,
    /// Beam length, mm.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 550.0))]
    pub beam_length_mm: f64,
    /// Beam height, mm.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 150.0))]
    pub beam_height_mm: f64,
    /// Beam width (depth into the scene), mm.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 150.0))]
    pub beam_width_mm: f64,
    /// Support span, mm (supports at ±span/2).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 450.0))]
    pub span_mm: f64,
    /// Distance between the two loads, mm (default span/3: loads at the third points).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 150.0))]
    pub load_span_mm: f64,
    /// Number of specimen tags (1 to 15): middle row (midspan, supports), then top and bottom
    /// rows, then the load points.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 9))]
    pub specimen_tags: u32,
    /// Edge of a specimen tag's black square (tag36h11), mm.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 30.0))]
    pub specimen_tag_mm: f64,
    /// Edge of a background tag's black square (tag25h9), mm.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 70.0))]
    pub background_tag_mm: f64,
    /// UTM sampling rate, Hz.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 50.0))]
    pub utm_hz: f64,
    /// Phase of the UTM samples against the frame clock, ms.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 7.0))]
    pub utm_phase_ms: f64,
    /// Beam stiffness: load per mm of midspan deflection, kN/mm.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 10.0))]
    pub stiffness_kn_per_mm: f64,
    /// Machine compliance: stroke per kN beyond the beam's own deflection, mm/kN.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 0.01))]
    pub compliance_mm_per_kn: f64,
    /// Shuffle the lines of frames.jsonl (SPEC allows any order across cameras).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = false))]
    pub shuffle: bool,
    /// Time of the first frame set, ns since the Unix epoch.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = DEFAULT_START_NS))]
    pub start_ns: i64,
    /// Sub-samples per pixel along each axis where a pixel straddles an edge (area integration).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 8))]
    pub subsamples: u32,
    /// Fault injection: the UTM goes silent this many seconds after the first frame set
    /// (live: the simulated Modbus server stops answering; `simulate`: no UTM samples in the
    /// window); never by default.
    #[cfg_attr(feature = "clap", arg(long))]
    pub utm_outage_at_s: Option<f64>,
    /// Length of the UTM outage, seconds.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 5.0))]
    #[serde(skip_serializing_if = "is_default_outage")]
    pub utm_outage_s: f64,

    // Real tests (see `sim::law`). Written to a config only when not at their defaults, so
    // recordings of the default rig are unchanged.
    /// The test: `four-point` (loads at `±load_span/2`) or `three-point-notched` (centre
    /// load, notch at midspan, tags straddling it; `load_span_mm` is then ignored).
    #[cfg_attr(feature = "clap", arg(long, value_enum, default_value_t = SimTest::FourPoint))]
    #[serde(skip_serializing_if = "is_default")]
    pub test: SimTest,
    /// The load law: `elastic` (load = stiffness × deflection), `softening` or `hardening`
    /// (elastic to the first crack, then to `residual_ratio` × the first-crack load).
    #[cfg_attr(feature = "clap", arg(long, value_enum, default_value_t = LoadLaw::Elastic))]
    #[serde(skip_serializing_if = "is_default")]
    pub load_law: LoadLaw,
    /// Midspan deflection at the first crack, mm (first-crack load = stiffness × this).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 0.3))]
    #[serde(skip_serializing_if = "is_default_crack")]
    pub crack_deflection_mm: f64,
    /// Sudden drop of the load at the first crack, fraction of the first-crack load.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 0.1))]
    #[serde(skip_serializing_if = "is_default_drop")]
    pub crack_drop: f64,
    /// Residual load / first-crack load that the law tends to (default 0.5 softening, 1.5 hardening).
    #[cfg_attr(feature = "clap", arg(long))]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub residual_ratio: Option<f64>,
    /// Deflection scale of the approach to the residual level after the crack, mm.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 0.5))]
    #[serde(skip_serializing_if = "is_default_softening")]
    pub softening_mm: f64,
    /// Notch depth (three-point-notched), mm.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 25.0))]
    #[serde(skip_serializing_if = "is_default_notch")]
    pub notch_mm: f64,
    /// Notch width (three-point-notched), mm.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 3.0))]
    #[serde(skip_serializing_if = "is_default_notch_width")]
    pub notch_width_mm: f64,
    /// Height of the crack tip (the halves' hinge) above the bottom face after cracking, mm
    /// (default: notch + 0.6 × (height − notch)).
    #[cfg_attr(feature = "clap", arg(long))]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub crack_tip_mm: Option<f64>,
    /// Offset of the UTM's clock against the cameras' clock, ms: a UTM sample taken at true
    /// time t is stamped t + offset.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 0.0, allow_hyphen_values = true))]
    #[serde(skip_serializing_if = "is_default")]
    pub utm_clock_offset_ms: f64,
}

// The flags of `tagdeflect simulate` are these fields (derived with the `clap` feature,
// which the binary turns on): their defaults must be the `[sim]` defaults.
#[cfg(all(test, feature = "clap"))]
mod tests {
    use super::*;
    use clap::Parser;
    use tagdeflect_core::Problem;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        params: SimParams,
    }

    #[test]
    fn clap_defaults_equal_serde_defaults() {
        let cli = Cli::try_parse_from(["x"]).unwrap();
        assert_eq!(cli.params, SimParams::default());
        let from_toml: SimParams = toml::from_str("").unwrap();
        assert_eq!(from_toml, SimParams::default());
        SimParams::default().validate().unwrap();
    }

    #[test]
    fn options_parse_and_are_validated() {
        let cli = Cli::try_parse_from(["x", "--cameras", "1", "--k1", "-0.2", "--bump-camera", "0", "--shuffle"]).unwrap();
        assert_eq!(cli.params.cameras, 1);
        assert_eq!(cli.params.k1, -0.2);
        assert_eq!(cli.params.bump_camera, Some(0));
        assert!(cli.params.shuffle);
        cli.params.validate().unwrap();
        let bad = SimParams { cameras: 4, ..SimParams::default() };
        assert!(matches!(bad.validate(), Err(Problem { key, .. }) if key == "cameras"));
        let cli = Cli::try_parse_from(["x", "--drift-camera", "1", "--drift-rot-deg", "-0.05", "--drift-trans-mm", "0.3"]).unwrap();
        assert_eq!((cli.params.drift_camera, cli.params.drift_rot_deg, cli.params.drift_trans_mm), (Some(1), -0.05, 0.3));
        cli.params.validate().unwrap();
        let bad = SimParams { drift_camera: Some(3), ..SimParams::default() };
        assert!(bad.validate().unwrap_err().to_string().contains("drift_camera"));
        let bad = SimParams { hide_tag: Some(20), ..SimParams::default() };
        assert!(bad.validate().unwrap_err().to_string().contains("hide_tag"));
        let bad = SimParams { bayer_raw: true, bayer: true, ..SimParams::default() };
        assert!(bad.validate().unwrap_err().to_string().contains("bayer_raw"));
        let bad = SimParams { bayer_raw: true, bit_depth: 12, ..SimParams::default() };
        assert!(bad.validate().unwrap_err().to_string().contains("bayer_raw"));
        SimParams { bayer_raw: true, ..SimParams::default() }.validate().unwrap();
        let bad = SimParams { post_blur_px: -1.0, ..SimParams::default() };
        assert!(bad.validate().unwrap_err().to_string().contains("post_blur_px"));
        let bad = SimParams { sharpen: f64::NAN, ..SimParams::default() };
        assert!(bad.validate().unwrap_err().to_string().contains("sharpen"));
        for (bad, key) in [
            (SimParams { defocus_radius_px: -0.5, ..SimParams::default() }, "defocus_radius_px"),
            (SimParams { astig_major_px: 1.0, astig_minor_px: 1.5, ..SimParams::default() }, "astig_minor_px"),
            (SimParams { astig_major_px: 1.0, ..SimParams::default() }, "astig_minor_px"),
            (SimParams { astig_angle_deg: f64::INFINITY, ..SimParams::default() }, "astig_angle_deg"),
            (SimParams { fill_factor: 0.0, ..SimParams::default() }, "fill_factor"),
            (SimParams { jpeg_quality: Some(0), ..SimParams::default() }, "jpeg_quality"),
            (SimParams { bit_depth: 17, ..SimParams::default() }, "bit_depth"),
            (SimParams { exposure: 0.0, ..SimParams::default() }, "exposure"),
            (SimParams { exposure: 1.5, ..SimParams::default() }, "exposure"),
            (SimParams { full_well_e: 50.0, ..SimParams::default() }, "full_well_e"),
            (SimParams { full_well_e: f64::NAN, ..SimParams::default() }, "full_well_e"),
        ] {
            assert!(matches!(bad.validate(), Err(Problem { key: k, .. }) if k == key), "{key}");
        }
        let cli = Cli::try_parse_from([
            "x",
            "--defocus-radius-px",
            "1.5",
            "--astig-major-px",
            "1",
            "--astig-minor-px",
            "0.4",
            "--astig-angle-deg",
            "-30",
            "--fill-factor",
            "0.5",
            "--jpeg-quality",
            "90",
            "--bit-depth",
            "12",
            "--exposure",
            "0.06",
            "--full-well-e",
            "32000",
        ])
        .unwrap();
        let p = &cli.params;
        assert_eq!((p.defocus_radius_px, p.astig_major_px, p.astig_minor_px, p.astig_angle_deg), (1.5, 1.0, 0.4, -30.0));
        assert_eq!((p.fill_factor, p.jpeg_quality, p.bit_depth), (0.5, Some(90), 12));
        assert_eq!((p.exposure, p.full_well_e), (0.06, 32000.0));
        p.validate().unwrap();
        let text = toml::to_string(&SimParams::default()).unwrap();
        assert!(!["fill_factor", "bit_depth", "jpeg", "exposure", "full_well"].iter().any(|k| text.contains(k)), "{text}");
        let bad = SimParams { hide_background_tag: Some(11), ..SimParams::default() };
        assert!(bad.validate().unwrap_err().to_string().contains("hide_background_tag"));
        assert!(SimParams { hide_background_tag: Some(10), ..SimParams::default() }.validate().is_ok());
        assert!(toml::from_str::<SimParams>("colour = 3").is_err());
    }
}
