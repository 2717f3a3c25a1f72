//! Fuzz target `config`: see `tagdeflect::fuzzing::config`.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| tagdeflect::fuzzing::config(data));
