//! Fuzz target `convert`: see `tagdeflect::fuzzing::convert`.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| tagdeflect::fuzzing::convert(data));
