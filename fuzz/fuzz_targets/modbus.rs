//! Fuzz target `modbus`: see `tagdeflect::fuzzing::modbus`.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| tagdeflect::fuzzing::modbus(data));
