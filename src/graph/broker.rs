//! The MQTT publisher in the graph (`[output.mqtt]`, the `mqtt` feature; without it
//! `broker_off.rs` stands here and refuses the section): live runs only, never a replay.

use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

use anyhow::Result;
use tagdeflect_core::feed::FeedLine;
use tagdeflect_sinks::lab_test::LabTests;
use tagdeflect_sinks::mqtt::{MqttPublisher, MqttSink};
use tagdeflect_sinks::LineSink;

use crate::config::Config;
use crate::graph::page::Page;

/// The run's MQTT publisher.
#[derive(Clone)]
pub(crate) struct Broker(Arc<MqttPublisher>);

impl Broker {
    /// Starts the publisher `[output.mqtt]` asks for (none on a replay).
    pub(crate) fn build(config: &Config, replaying: bool, record_dir: Option<&Path>) -> Result<Option<Broker>> {
        let (Some(m), false) = (&config.output.mqtt, replaying) else { return Ok(None) };
        let feed = config.output.feed.as_deref().and_then(tagdeflect_core::feed_file::feed_path);
        let p = MqttPublisher::start(m, &config.rig_info(), record_dir, feed.as_deref()).map_err(tagdeflect_core::BadInput::new)?;
        Ok(Some(Broker(Arc::new(p))))
    }

    /// The publisher as a sink of finished lines.
    pub(crate) fn sink(&self) -> Box<dyn LineSink> {
        Box::new(MqttSink(self.0.clone()))
    }

    /// Shows the delivery to the archive on the page.
    pub(crate) fn show_on(&self, page: &Page) {
        page.on_mqtt(self.0.stats());
    }

    /// Publishes each record of the tests to `<topic>/labtest/<id>` (the archive knows the tests).
    pub(crate) fn publish_lab_tests(&self, tests: &LabTests) {
        let m = self.0.clone();
        tests.set_on_record(Box::new(move |r| m.publish_lab_test(r)));
    }

    /// The publisher's own state in a live line (`mqtt_dropped`).
    pub(crate) fn apply(&self, line: &mut FeedLine) {
        line.mqtt_dropped = Some(self.0.reserve());
    }

    /// Drains the broker's buffer (at most 5 s) once every line reached the sinks.
    pub(crate) async fn finish(&self) {
        self.0.finish(Duration::from_secs(5)).await;
    }
}
