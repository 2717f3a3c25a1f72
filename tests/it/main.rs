//! The integration tests: one binary, one module per area (the heavy C libraries link once).

mod common;

mod accuracy;
mod aravis_fake;
mod cli;
mod config;
mod detect_accuracy;
mod detect_sim;
mod gauges;
mod live;
mod realdata;
mod recording;
mod report;
mod simulate;
mod solve;
mod systemd_unit;
mod tracking;
mod utm_modbus;
mod v4l2_convert;
