//! Fuzz target `modbus_peer`: see `tagdeflect::fuzzing::modbus_peer`.
//!
//! libFuzzer's panic hook aborts on every panic, also on one the code under test catches.
//! The poller catches one panic on purpose: tokio-modbus 0.15 panics decoding a reply that
//! claims more coil bytes than it carries (slowtec/tokio-modbus#298), and the poller turns
//! that into a malformed-reply fault (`utm::modbus::poll_guarded`). Panics raised inside
//! tokio-modbus's codec are therefore let through to that catch; every other panic still
//! aborts and is reported as a crash.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(
    init: {
        let abort_hook = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            let in_codec = info.location().is_some_and(|l| l.file().contains("tokio-modbus") && l.file().contains("codec"));
            if !in_codec {
                abort_hook(info);
            }
        }));
    },
    |data: &[u8]| tagdeflect::fuzzing::modbus_peer(data)
);
