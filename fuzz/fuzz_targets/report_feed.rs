//! Fuzz target `report_feed`: see `tagdeflect::fuzzing::report_feed`.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| tagdeflect::fuzzing::report_feed(data));
