//! The integration tests: one binary, one module per area (the heavy C libraries link once).
#![allow(unsafe_code)] // signals and locks for the processes the tests start (libc::kill, flock)

mod common;

mod accuracy;
mod analog;
mod aprilgrid;
mod aravis_fake;
mod archive;
mod audit;
mod calibrate;
mod calibrate_guard;
mod cli;
mod config;
mod control;
mod demo_test;
mod detect_accuracy;
mod detect_sim;
mod docs;
mod drift;
mod faults;
mod formations;
mod gauges;
mod http;
mod lab_day;
mod lab_method;
mod live;
mod modes;
mod package;
mod preload;
mod realdata;
mod realtime_utm;
mod recording;
mod report;
mod report_folder;
mod report_lab;
mod robustness;
mod rotation;
mod simulate;
mod solve;
mod systemd_unit;
mod test_folder;
mod test_frames;
mod tracking;
mod utm_modbus;
mod v4l2_convert;
mod verify;
