//! Fuzz target `calibration`: see `tagdeflect::fuzzing::calibration`.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| tagdeflect::fuzzing::calibration(data));
