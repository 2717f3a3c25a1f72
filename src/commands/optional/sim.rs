//! `tagdeflect simulate` and `demo` (the `sim` feature): a synthetic recording with its
//! truth, and the live pipeline on the built-in simulated rig.

use std::path::PathBuf;

mod demo_test;
pub use demo_test::{DemoTest, RATE_AFTER_L900_MM_PER_MIN, RATE_TO_L900_MM_PER_MIN};

use anyhow::Result;
use clap::Subcommand;
use tagdeflect_io::recording::FrameFormat;
use tagdeflect_sim::SimParams;

use crate::config::Config;
use crate::graph::entry::{self as live, LiveOptions};
use crate::graph::page::{self, http_options, parse_http_addr};

/// The simulator's commands.
#[derive(Subcommand)]
pub enum SimCommand {
    /// Write a synthetic recording with ground truth (`truth.jsonl`).
    Simulate {
        /// The new recording folder.
        #[arg(long)]
        out: PathBuf,
        /// How the frames are written (PGM: raw pixels, no decoding cost on replay).
        #[arg(long, value_enum, default_value_t = FrameFormat::Png)]
        frame_format: FrameFormat,
        /// The simulated rig and test (each its own option).
        #[command(flatten)]
        params: SimParams,
    },
    /// The live pipeline on the built-in simulated rig (simulated cameras, simulated UTM
    /// over real Modbus TCP on loopback); the feed goes to stdout.
    Demo {
        /// Stop after this many seconds (default: until SIGTERM/SIGINT).
        #[arg(long, value_parser = crate::commands::parse_duration_s)]
        duration_s: Option<f64>,
        /// Use this config instead of the built-in demo rig.
        #[arg(long)]
        config: Option<PathBuf>,
        /// Serve the live page on ADDR (IP:PORT, port 0 = any free port) instead of
        /// 127.0.0.1:8080; the bound address is printed on stderr as http://ADDR/.
        #[arg(long, value_name = "ADDR", value_parser = parse_http_addr, conflicts_with = "no_http")]
        http: Option<std::net::SocketAddr>,
        /// Do not serve the live page.
        #[arg(long)]
        no_http: bool,
        /// Keep each test in its own folder here (as `[output] tests`; enables the control API).
        #[arg(long, value_name = "DIR")]
        tests: Option<PathBuf>,
        /// Serve the net deflection (or `[output.control] gauge`) as a control signal on a
        /// read-only Modbus TCP server at ADDR (IP:PORT; see docs/control.md).
        #[arg(long, value_name = "ADDR", value_parser = parse_control_addr)]
        control: Option<std::net::SocketAddr>,
        /// A test a lab would accept instead of the endless cycles: a cracking, softening
        /// beam loaded at ASTM C1609's rates in simulated time, started and stopped
        /// automatically, its report made at stop (docs/simulation.md). The recording and
        /// the tests' folder (`DIR/recording`, `DIR/tests`) go to DIR.
        #[arg(long, value_name = "DIR", conflicts_with_all = ["config", "control", "duration_s", "tests"])]
        c1609: Option<PathBuf>,
        /// With --c1609: play the simulated test this many times faster than recorded (the
        /// feed keeps the simulated times).
        #[arg(long, default_value_t = 2.0, requires = "c1609")]
        speed: f64,
        /// With --c1609: two cameras with 2x2 sub-samples per pixel instead of three with 4x4
        /// (quicker to simulate).
        #[arg(long, requires = "c1609")]
        small: bool,
    },
}

impl SimCommand {
    /// Runs the command.
    pub fn run(self) -> Result<()> {
        match self {
            SimCommand::Simulate { out, frame_format, params } => simulate(&out, frame_format, &params),
            SimCommand::Demo { c1609: Some(root), speed, small, http, no_http, .. } => {
                if !(speed.is_finite() && speed > 0.0 && speed <= 1000.0) {
                    return Err(tagdeflect_core::BadInput::new(format!("--speed {speed}: a factor above 0, at most 1000")).into());
                }
                // The tests' control API lives on the page: without one asked for, a free
                // loopback port serves it.
                let any_port = std::net::SocketAddr::from(([127, 0, 0, 1], 0));
                let http = demo_http(http, no_http, false)?.or_else(|| http_options(Some(any_port), true));
                DemoTest { speed, small, root }.run(http, !no_http).map(|_| ())
            }
            SimCommand::Demo { duration_s, config, http, no_http, tests, control, .. } => {
                let mut cfg = match config {
                    Some(p) => Config::load(&p)?,
                    None => Config::demo(),
                };
                if let Some(addr) = control {
                    let c =
                        cfg.output.control.get_or_insert_with(|| tagdeflect_sinks::control_output::ControlConfig::on(&addr.to_string()));
                    c.modbus = addr.to_string();
                }
                if no_http {
                    cfg.output.http = None;
                }
                if tests.is_some() {
                    cfg.output.tests = tests;
                }
                // The page by default on loopback; a taken default port only costs the page.
                let http = demo_http(http, no_http, cfg.output.http.is_some())?;
                live::run(cfg, LiveOptions { duration_s, feed_to_stdout: true, http, ..LiveOptions::default() })
            }
        }
    }
}

/// Whether `c` is one of the simulator's bad-input errors (exit 2).
pub fn is_bad_input(c: &(dyn std::error::Error + 'static)) -> bool {
    c.is::<tagdeflect_sim::SimError>()
}

/// `simulate`: the recording, and a one-line summary on stderr.
fn simulate(out: &std::path::Path, frame_format: FrameFormat, params: &SimParams) -> Result<()> {
    let summary = anyhow::Context::with_context(crate::commands::simulate::simulate_as(params, out, frame_format), || {
        format!("simulating into {}", out.display())
    })?;
    eprintln!(
        "simulated {} frame sets ({} frames, {} dropped, {} UTM samples) into {}; final midspan deflection {:.3} mm",
        summary.frame_sets,
        summary.frames,
        summary.dropped,
        summary.utm_samples,
        summary.dir.display(),
        summary.final_deflection_mm
    );
    Ok(())
}

/// `demo --control ADDR`: a listen address, the control output's port if none is given.
fn parse_control_addr(s: &str) -> Result<std::net::SocketAddr, String> {
    tagdeflect_core::listen::parse_listen_addr(s, tagdeflect_sinks::control_output::EXAMPLE_PORT).map_err(|e| e.to_string())
}

/// The live page of `demo`: `--http ADDR` must be served (an error if it cannot be);
/// without it the config's `[output] http` is used, else [`DEFAULT_ADDR`] on loopback, where
/// a port another program holds only costs the page (a warning); `--no-http`: none.
///
/// [`DEFAULT_ADDR`]: tagdeflect_sinks::http::DEFAULT_ADDR
fn demo_http(http: Option<std::net::SocketAddr>, no_http: bool, configured: bool) -> Result<Option<page::HttpOptions>> {
    Ok(match (http, no_http) {
        (_, true) => None,
        (Some(addr), false) => http_options(Some(addr), true),
        (None, false) if configured => None,
        (None, false) => http_options(page::default_addr(), false),
    })
}

#[cfg(all(test, feature = "http"))]
mod tests {
    use super::*;

    #[test]
    fn demo_serves_the_default_page_on_loopback_and_only_warns_when_its_port_is_taken() {
        let default = demo_http(None, false, false).unwrap().unwrap();
        assert_eq!(default.addr, std::net::SocketAddr::from(([127, 0, 0, 1], 8080)));
        assert!(default.addr.ip().is_loopback());
        assert!(!default.required, "a taken default port costs only the page");
        let given: std::net::SocketAddr = "127.0.0.1:0".parse().unwrap();
        let asked = demo_http(Some(given), false, false).unwrap().unwrap();
        assert_eq!((asked.addr, asked.required), (given, true), "--http ADDR must be served");
        assert!(demo_http(None, true, false).unwrap().is_none());
        assert!(demo_http(Some(given), true, false).unwrap().is_none());
        assert!(demo_http(None, false, true).unwrap().is_none(), "the config's [output] http is served by the graph");
    }
}
