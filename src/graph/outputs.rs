//! What a run writes to, each output built by its own config section (as Vector's
//! `SinkConfig::build`): the feed files and stdout (`[output] feed`), the report's copy of the
//! feed (`[report]`), the live page, the control registers (`[output.control]`), the analog output (`[output.analog]`), the MQTT
//! publisher (`[output.mqtt]`), the tests (`[output] tests`) and the recorder
//! (`[output] record`, `--record`). [`Outputs::build`] loops over the sections in that order;
//! the order is the order of the line sinks. An output that cannot be opened stops the run
//! before any camera starts (exit 2).

use std::path::Path;
use std::sync::Arc;

use anyhow::{Context, Result};
use tagdeflect_core::feed_file::FeedWriter;
use tagdeflect_core::BadInput;
use tagdeflect_report::config::ReportConfig;
use tagdeflect_sinks::analog_output::{AnalogConfig, AnalogOutput, AnalogSink};
use tagdeflect_sinks::control_output::{ControlConfig, ControlSink};
use tagdeflect_sinks::lab_test::{LabTestSink, LabTests};
use tagdeflect_sinks::recorder::Recorder;
use tagdeflect_sinks::signal_log::TestSummaries;
use tagdeflect_sinks::{FeedFileSink, LineSink};

use crate::config::Config;
use crate::graph::broker::Broker;
use crate::graph::entry::LiveOptions;
use crate::graph::page::Page;
use crate::graph::run_report::RunReport;

/// What every output of a run is built with.
pub(crate) struct OutputContext<'a> {
    pub(crate) config: &'a Config,
    pub(crate) opts: &'a LiveOptions,
    pub(crate) replaying: bool,
    pub(crate) record_dir: Option<&'a Path>,
    pub(crate) page: &'a Page,
}

impl OutputContext<'_> {
    /// A live run that measures: the report and the tests take part.
    fn live_measuring(&self) -> bool {
        !self.replaying && !self.opts.record_only
    }
}

/// The outputs of a run once built: the line sinks in order, and the handles whose end takes
/// more than a flush.
#[derive(Default)]
pub(crate) struct Outputs {
    pub(crate) sinks: Vec<Box<dyn LineSink>>,
    pub(crate) broker: Option<Broker>,
    pub(crate) run_report: Option<RunReport>,
    pub(crate) tests: Option<Arc<LabTests>>,
    pub(crate) recorder: Option<Recorder>,
    /// The control outputs' figures per test, for each stopped test's `control.json`.
    pub(crate) test_summaries: Vec<TestSummaries>,
}

/// An output of a run, built from its config section into [`Outputs`].
trait BuildOutput {
    fn build(&self, ctx: &OutputContext, out: &mut Outputs) -> Result<()>;
}

impl Outputs {
    /// Every output of a run (see the module doc); `feeds` are the caller's own (a replay's stdout).
    pub(crate) fn build(ctx: &OutputContext, feeds: Vec<FeedWriter>) -> Result<Outputs> {
        let out_cfg = &ctx.config.output;
        let feed = FeedOutput { spec: out_cfg.feed.as_deref(), rotation: &out_cfg.feed_rotation };
        let tests = TestsOutput(out_cfg.tests.as_deref());
        let record = RecordOutput(ctx.record_dir);
        let sections: [Option<&dyn BuildOutput>; 8] = [
            Some(&feed),
            ctx.config.report.as_ref().map(|r| r as &dyn BuildOutput),
            Some(ctx.page as &dyn BuildOutput),
            out_cfg.control.as_ref().map(|c| c as &dyn BuildOutput),
            out_cfg.analog.as_ref().map(|a| a as &dyn BuildOutput),
            Some(&BrokerOutput),
            Some(&tests),
            Some(&record),
        ];
        // The caller's own feeds come first: the feed's sinks, before its section's.
        let mut out = Outputs { sinks: feeds.into_iter().map(feed_sink).collect(), ..Outputs::default() };
        for section in sections.into_iter().flatten() {
            section.build(ctx, &mut out)?;
        }
        Ok(out)
    }
}

/// `[output] feed` (a file, or `-` for stdout) and `--feed`-to-stdout.
struct FeedOutput<'a> {
    spec: Option<&'a str>,
    /// `[output.feed_rotation]`.
    rotation: &'a tagdeflect_core::feed_rotation::FeedRotation,
}

/// A feed writer as a line sink.
fn feed_sink(writer: FeedWriter) -> Box<dyn LineSink> {
    Box::new(FeedFileSink(writer))
}

impl BuildOutput for FeedOutput<'_> {
    fn build(&self, ctx: &OutputContext, out: &mut Outputs) -> Result<()> {
        let mut feeds = Vec::new();
        let to_stdout = ctx.opts.feed_to_stdout;
        if to_stdout {
            feeds.push(FeedWriter::stdout());
        }
        match self.spec {
            Some("-") if !to_stdout => feeds.push(FeedWriter::stdout()),
            Some("-") | None => {}
            Some(spec) => {
                let clock = rotation_clock()?;
                feeds.push(
                    FeedWriter::append_rotating_at(Path::new(spec), self.rotation, clock)
                        .map_err(|e| BadInput::new(format!("cannot open the feed output {spec}: {e}")))?,
                )
            }
        }
        out.sinks.extend(feeds.into_iter().map(feed_sink));
        Ok(())
    }
}

/// For checking the daily cut without waiting for midnight: when set (RFC 3339, e.g.
/// `2030-01-01T23:59:30Z`), the feed rotation's UTC clock starts at that time when the feed
/// file is opened and runs on at the real rate (docs/feed.md). Never set in service.
const FEED_CLOCK_ENV: &str = "TAGDEFLECT_FEED_CLOCK_START";

/// The feed rotation's UTC clock: the system's, or [`FEED_CLOCK_ENV`]'s.
fn rotation_clock() -> Result<tagdeflect_core::feed_file::UtcClock> {
    let Some(v) = std::env::var_os(FEED_CLOCK_ENV) else { return Ok(Box::new(chrono::Utc::now)) };
    let text = v.to_string_lossy();
    let start = chrono::DateTime::parse_from_rfc3339(&text)
        .map_err(|e| BadInput::new(format!("{FEED_CLOCK_ENV}={text:?}: not an RFC 3339 time ({e})")))?
        .with_timezone(&chrono::Utc);
    tracing::warn!("{FEED_CLOCK_ENV}: the feed rotation's clock starts at {start} (a check of the daily cut; never in service)");
    let opened = std::time::Instant::now();
    Ok(Box::new(move || start + chrono::Duration::from_std(opened.elapsed()).unwrap_or_default()))
}

/// `[report]`: this run's feed copied into the report folder, the report written at the end.
impl BuildOutput for ReportConfig {
    fn build(&self, ctx: &OutputContext, out: &mut Outputs) -> Result<()> {
        if !ctx.live_measuring() {
            return Ok(());
        }
        if let Some((report, writer)) = RunReport::start(ctx.config)? {
            out.sinks.push(Box::new(FeedFileSink(writer)));
            out.run_report = Some(report);
        }
        Ok(())
    }
}

/// The live page as a sink of finished lines.
impl BuildOutput for Page {
    fn build(&self, _ctx: &OutputContext, out: &mut Outputs) -> Result<()> {
        out.sinks.extend(self.sink()?);
        Ok(())
    }
}

/// `[output.control]`: the gauge as a control signal (`tagdeflect_sinks::control_output`).
impl BuildOutput for ControlConfig {
    fn build(&self, _ctx: &OutputContext, out: &mut Outputs) -> Result<()> {
        let sink = ControlSink::start(self).map_err(|e| BadInput::new(e.to_string()))?;
        if let Ok(c) = sink.0.lock() {
            out.test_summaries.push(c.test_summaries());
        }
        out.sinks.push(Box::new(sink));
        Ok(())
    }
}

/// `[output.analog]`: the gauge as a voltage on a networked DAQ (`tagdeflect_sinks::analog_output`);
/// live runs only: a replay never drives the machine.
impl BuildOutput for AnalogConfig {
    fn build(&self, ctx: &OutputContext, out: &mut Outputs) -> Result<()> {
        if ctx.replaying {
            tracing::info!("[output.analog]: not written on a replay");
            return Ok(());
        }
        let analog = AnalogOutput::start(self).map_err(|e| BadInput::new(e.to_string()))?;
        out.test_summaries.push(analog.test_summaries());
        out.sinks.push(Box::new(AnalogSink(analog)));
        Ok(())
    }
}

/// `[output.mqtt]`: the MQTT publisher (live runs only; never on a replay).
struct BrokerOutput;

impl BuildOutput for BrokerOutput {
    fn build(&self, ctx: &OutputContext, out: &mut Outputs) -> Result<()> {
        if let Some(b) = Broker::build(ctx.config, ctx.replaying, ctx.record_dir)? {
            out.sinks.push(b.sink());
            b.show_on(ctx.page);
            out.broker = Some(b);
        }
        Ok(())
    }
}

/// `[output] tests`: their lines are a sink, their control API on the page, each record
/// published to the archive.
struct TestsOutput<'a>(Option<&'a Path>);

impl BuildOutput for TestsOutput<'_> {
    fn build(&self, ctx: &OutputContext, out: &mut Outputs) -> Result<()> {
        if !ctx.live_measuring() && !(ctx.opts.tests_in_replay && !ctx.opts.record_only) {
            return Ok(());
        }
        let Some(dir) = self.0 else {
            if ctx.config.output.auto_test.is_some() {
                return Err(BadInput::new(
                    "[output.auto_test]: automatic tests need the tests' folder: set [output] tests or --tests DIR".to_string(),
                )
                .into());
            }
            return Ok(());
        };
        let placed = crate::graph::lab_test::PlacementWatch::new(ctx.config);
        let t = crate::graph::lab_test::start(ctx.config, dir, ctx.page, placed.clone())?;
        crate::graph::control_file::install(&t, ctx.config, out.test_summaries.clone());
        if ctx.config.verification.is_some() {
            out.sinks.push(Box::new(placed));
        }
        out.sinks.push(Box::new(LabTestSink(t.clone())));
        if let Some(b) = &out.broker {
            b.publish_lab_tests(&t);
        }
        out.tests = Some(t);
        Ok(())
    }
}

/// The recorder (`tagdeflect_sinks::recorder`): retries after write errors; its state in every
/// feed line and on the page.
struct RecordOutput<'a>(Option<&'a Path>);

impl BuildOutput for RecordOutput<'_> {
    fn build(&self, ctx: &OutputContext, out: &mut Outputs) -> Result<()> {
        let Some(dir) = self.0 else { return Ok(()) };
        let config = ctx.config;
        let frames = 8 * config.cameras.len().max(1);
        let recorder = Recorder::start(dir, config, config.output.record_format, frames)
            .with_context(|| format!("cannot record into {}", dir.display()))?;
        tracing::info!("recording into {}", dir.display());
        ctx.page.on_recording(dir, recorder.status());
        out.recorder = Some(recorder);
        Ok(())
    }
}
