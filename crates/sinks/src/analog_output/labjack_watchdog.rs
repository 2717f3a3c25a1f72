//! LabJack T-series watchdog (`[output.analog] labjack_watchdog_s`): the device's own
//! watchdog takes over when tagdeflect stops talking to it (killed, crashed, the network
//! cut). The device clears its watchdog on any communication; tagdeflect writes every frame
//! set, so the watchdog trips `labjack_watchdog_s` seconds after the last write.
//!
//! On a trip the device drives the valid line low (a DIO update of that line only: every
//! other line is inhibited) and, with a safe voltage (`on_invalid = <volts>`), sets the DAC
//! to it; with `on_invalid = "hold"` the DAC keeps its last value (the valid line tells the
//! controller). It does not reset the device.
//!
//! The registers are LabJack's `*_DEFAULT` watchdog registers, addresses from LabJack's
//! register map (`ljm_constants.json`, all UINT32 but the DACs' FLOAT32 voltages): they are
//! stored in the device's flash, so they are read first and written only when they differ
//! (a connect does not wear the flash). The map asks the watchdog disabled while the others
//! are written: the plan writes `WATCHDOG_ENABLE_DEFAULT` 0 first and 1 last.

use tagdeflect_io::utm::config::{ValueType, WordOrder};

use super::config::{AnalogConfig, DigitalOutput, RegisterWrite, LABJACK_FIO0};

/// `WATCHDOG_ENABLE_DEFAULT` (UINT32): 1 enables the watchdog.
pub const ENABLE: u16 = 61600;
/// `WATCHDOG_TIMEOUT_S_DEFAULT` (UINT32): seconds without communication before a trip.
pub const TIMEOUT_S: u16 = 61604;
/// `WATCHDOG_RESET_ENABLE_DEFAULT` (UINT32): 1 resets the device on a trip.
pub const RESET_ENABLE: u16 = 61620;
/// `WATCHDOG_DIO_ENABLE_DEFAULT` (UINT32): 1 updates the DIO lines on a trip.
pub const DIO_ENABLE: u16 = 61630;
/// `WATCHDOG_DIO_STATE_DEFAULT` (UINT32): the lines' states after a trip (bit n = DIO n).
pub const DIO_STATE: u16 = 61632;
/// `WATCHDOG_DIO_DIRECTION_DEFAULT` (UINT32): the lines' directions after a trip (1 = out).
pub const DIO_DIRECTION: u16 = 61634;
/// `WATCHDOG_DIO_INHIBIT_DEFAULT` (UINT32): lines a trip leaves alone (bit set = inhibited).
pub const DIO_INHIBIT: u16 = 61636;
/// `WATCHDOG_DAC0_ENABLE_DEFAULT` (UINT32); DAC1's is 10 registers on.
pub const DAC0_ENABLE: u16 = 61640;
/// `WATCHDOG_DAC0_DEFAULT` (FLOAT32 volts); DAC1's is 10 registers on.
pub const DAC0_VOLTS: u16 = 61642;
/// The block read to compare: `ENABLE` to DAC1's voltage.
pub const BLOCK: (u16, u16) = (ENABLE, DAC0_VOLTS + 10 + 2 - ENABLE);
/// DIO lines of the T-series (FIO, EIO, CIO, MIO: 23).
const DIO_LINES: u32 = 23;

/// The writes that set the watchdog up for `config` (`None` without `labjack_watchdog_s`),
/// the disable first and the enable last.
pub fn plan(config: &AnalogConfig) -> Option<Vec<RegisterWrite>> {
    let timeout_s = config.labjack_watchdog_s?;
    let u32w =
        |register: u16, value: u32| RegisterWrite { register, data_type: ValueType::U32, word_order: WordOrder::Abcd, value: value as f64 };
    let dac = 10 * config.channel as u16;
    let all = (1u32 << DIO_LINES) - 1;
    let mut w = vec![u32w(ENABLE, 0), u32w(TIMEOUT_S, timeout_s), u32w(RESET_ENABLE, 0)];
    match valid_dio(config) {
        Some(line) => {
            w.extend([u32w(DIO_ENABLE, 1), u32w(DIO_STATE, 0), u32w(DIO_DIRECTION, 1 << line), u32w(DIO_INHIBIT, all & !(1 << line))])
        }
        None => w.push(u32w(DIO_ENABLE, 0)),
    }
    match config.on_invalid.safe_v() {
        Some(v) => w.extend([
            u32w(DAC0_ENABLE + dac, 1),
            RegisterWrite { register: DAC0_VOLTS + dac, data_type: ValueType::F32, word_order: WordOrder::Abcd, value: v },
        ]),
        None => w.push(u32w(DAC0_ENABLE + dac, 0)),
    }
    w.push(u32w(ENABLE, 1));
    Some(w)
}

/// The valid line's DIO number when it is one of the T-series' DIO registers (2000 + n).
fn valid_dio(config: &AnalogConfig) -> Option<u32> {
    match config.valid_line()? {
        DigitalOutput::Register(r) if (LABJACK_FIO0..LABJACK_FIO0 + DIO_LINES as u16).contains(&r) => Some((r - LABJACK_FIO0) as u32),
        _ => None,
    }
}

/// True when the registers read (`words`, from [`BLOCK`]'s start) already hold every value of
/// `plan` with the watchdog enabled: nothing needs writing.
pub fn already_set(plan: &[RegisterWrite], words: &[u16]) -> bool {
    plan.iter().skip(1).all(|w| {
        let at = (w.register - ENABLE) as usize;
        let Ok(want) = tagdeflect_io::utm::codec::encode(&w.register_config(), w.value) else { return false };
        words.get(at..at + want.len()) == Some(&want[..])
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::analog_output::config::OnInvalid;

    #[test]
    fn the_plan_disables_first_drives_only_the_valid_line_and_enables_last() {
        let mut c = AnalogConfig::labjack("127.0.0.1:502", 1.0);
        assert!(plan(&c).is_none());
        c.labjack_watchdog_s = Some(2);
        c.on_invalid = OnInvalid::Volts(0.5);
        c.channel = 1;
        c.valid_output = Some(DigitalOutput::Register(2003));
        let p = plan(&c).unwrap();
        let regs: Vec<(u16, f64)> = p.iter().map(|w| (w.register, w.value)).collect();
        assert_eq!(
            regs,
            vec![
                (ENABLE, 0.0),
                (TIMEOUT_S, 2.0),
                (RESET_ENABLE, 0.0),
                (DIO_ENABLE, 1.0),
                (DIO_STATE, 0.0),
                (DIO_DIRECTION, 8.0),
                (DIO_INHIBIT, f64::from(0x7F_FFFF & !8u32)),
                (DAC0_ENABLE + 10, 1.0),
                (DAC0_VOLTS + 10, 0.5),
                (ENABLE, 1.0),
            ]
        );
        assert_eq!(p[8].data_type, ValueType::F32);
        // Read back as written, nothing to write; one register off, everything is written.
        let mut words = vec![0u16; BLOCK.1 as usize];
        for w in &p[1..] {
            let at = (w.register - ENABLE) as usize;
            let enc = tagdeflect_io::utm::codec::encode(&w.register_config(), w.value).unwrap();
            words[at..at + enc.len()].copy_from_slice(&enc);
        }
        assert!(already_set(&p, &words));
        words[(TIMEOUT_S - ENABLE) as usize + 1] = 3;
        assert!(!already_set(&p, &words));
        // Hold: the DAC is left alone on a trip.
        c.on_invalid = OnInvalid::Hold;
        assert!(plan(&c).unwrap().iter().any(|w| w.register == DAC0_ENABLE + 10 && w.value == 0.0));
    }
}
