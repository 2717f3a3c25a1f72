//! The MQTT publisher's place in a build without the `mqtt` feature: `[output.mqtt]` on a live
//! run is refused, and no value of [`Broker`] exists (`broker.rs` stands here with the feature).

use std::path::Path;

use anyhow::Result;
use tagdeflect_core::feed::FeedLine;
use tagdeflect_sinks::lab_test::LabTests;
use tagdeflect_sinks::LineSink;

use crate::config::Config;
use crate::graph::page::Page;

/// No publisher in this build.
#[derive(Clone)]
pub(crate) enum Broker {}

impl Broker {
    /// Refuses `[output.mqtt]` on a live run.
    pub(crate) fn build(config: &Config, replaying: bool, _record_dir: Option<&Path>) -> Result<Option<Broker>> {
        match (&config.output.mqtt, replaying) {
            (Some(_), false) => {
                Err(tagdeflect_core::BadInput::new("[output.mqtt]: this build has no MQTT publisher: build with the `mqtt` feature").into())
            }
            _ => Ok(None),
        }
    }

    pub(crate) fn sink(&self) -> Box<dyn LineSink> {
        match *self {}
    }

    pub(crate) fn show_on(&self, _page: &Page) {
        match *self {}
    }

    pub(crate) fn publish_lab_tests(&self, _tests: &LabTests) {
        match *self {}
    }

    pub(crate) fn apply(&self, _line: &mut FeedLine) {
        match *self {}
    }

    pub(crate) async fn finish(&self) {
        match *self {}
    }
}
