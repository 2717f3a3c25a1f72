//! Fuzz target `roi`: see `tagdeflect::fuzzing::roi`.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| tagdeflect::fuzzing::roi(data));
