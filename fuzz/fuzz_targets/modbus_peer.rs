//! Fuzz target `modbus_peer`: see `tagdeflect::fuzzing::modbus_peer`.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| tagdeflect::fuzzing::modbus_peer(data));
