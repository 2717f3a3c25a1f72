//! Fuzz target `image`: see `tagdeflect::fuzzing::image`.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| tagdeflect::fuzzing::image(data));
