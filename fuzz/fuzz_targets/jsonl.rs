//! Fuzz target `jsonl`: see `tagdeflect::fuzzing::jsonl`.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| tagdeflect::fuzzing::jsonl(data));
