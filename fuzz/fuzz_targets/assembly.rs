//! Fuzz target `assembly`: see `tagdeflect::fuzzing::assembly`.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| tagdeflect::fuzzing::assembly(data));
