//! Fuzz target `archive_message`: see `tagdeflect_archive::fuzz_message`.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| tagdeflect_archive::fuzz_message(data));
