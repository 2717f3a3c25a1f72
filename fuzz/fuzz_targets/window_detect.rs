//! Fuzz target `window_detect`: see `tagdeflect::fuzzing::window_detect`.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| tagdeflect::fuzzing::window_detect(data));
