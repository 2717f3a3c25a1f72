//! Requests checked on the byte stream before tokio-modbus's decoder sees them: the MBAP
//! header (protocol 0, a length of 2–254 bytes: the unit id and a PDU of at most 253) and,
//! for the functions whose PDU carries counts, that the counts and the PDU's length agree
//! (Modbus Application Protocol v1.1b3). tokio-modbus 0.15 indexes past the PDU on a "write
//! multiple coils" (0x0F) whose quantity exceeds its byte count — a panic inside its codec —
//! so such a frame must never reach it: the connection gets the exception "illegal data
//! value" and is closed (a bad header: closed without a reply, its framing cannot be
//! trusted).

/// The MBAP header's length: transaction (2), protocol (2), length (2), unit (1).
pub(super) const MBAP_LEN: usize = 7;
/// Most bytes the MBAP length may count: the unit id and a PDU of at most 253 bytes.
const MAX_MBAP_LENGTH: usize = 254;

/// A request refused, and what its client is sent.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(super) struct Refusal {
    /// What was wrong, for the log.
    pub why: String,
    /// The exception reply (empty: closed without one).
    pub reply: Vec<u8>,
}

/// What a scan of received bytes found: the length of the whole, well-formed frames at their
/// start, and the refusal of the frame after them, if it is malformed.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(super) struct Scan {
    /// Bytes of whole frames that passed.
    pub passed: usize,
    /// The next frame, refused.
    pub refused: Option<Refusal>,
}

/// Scans `buf` from its start: whole frames pass; a partial one waits for more bytes, unless
/// its header is already wrong.
pub(super) fn scan(buf: &[u8]) -> Scan {
    let mut at = 0;
    while buf.len() - at >= MBAP_LEN {
        let h = &buf[at..at + MBAP_LEN];
        let protocol = u16::from_be_bytes([h[2], h[3]]);
        let length = u16::from_be_bytes([h[4], h[5]]) as usize;
        if protocol != 0 || !(2..=MAX_MBAP_LENGTH).contains(&length) {
            let why = format!("MBAP header with protocol {protocol} and length {length} (0 and 2–{MAX_MBAP_LENGTH} expected)");
            return Scan { passed: at, refused: Some(Refusal { why, reply: Vec::new() }) };
        }
        let end = at + 6 + length;
        if buf.len() < end {
            break;
        }
        let pdu = &buf[at + MBAP_LEN..end];
        if let Err(why) = check_pdu(pdu) {
            let reply = vec![h[0], h[1], 0, 0, 0, 3, h[6], pdu[0] | 0x80, 0x03];
            let why = format!("function 0x{:02X}: {why}", pdu[0]);
            return Scan { passed: at, refused: Some(Refusal { why, reply }) };
        }
        at = end;
    }
    Scan { passed: at, refused: None }
}

/// A request PDU's counts agree with each other and with its length.
fn check_pdu(pdu: &[u8]) -> Result<(), String> {
    let word = |at: usize| u16::from_be_bytes([pdu[at], pdu[at + 1]]) as usize;
    let exact = |n: usize| if pdu.len() == n { Ok(()) } else { Err(format!("{} bytes, {n} expected", pdu.len())) };
    match pdu[0] {
        0x01..=0x06 => exact(5),
        0x11 => exact(1),
        0x16 => exact(7),
        0x0F => {
            exact_at_least(pdu, 6)?;
            let (quantity, count) = (word(3), pdu[5] as usize);
            counts_agree("coils", quantity, 0x07B0, count, quantity.div_ceil(8))?;
            exact(6 + count)
        }
        0x10 => {
            exact_at_least(pdu, 6)?;
            let (quantity, count) = (word(3), pdu[5] as usize);
            counts_agree("registers", quantity, 0x7B, count, 2 * quantity)?;
            exact(6 + count)
        }
        0x17 => {
            exact_at_least(pdu, 10)?;
            let (read, write, count) = (word(3), word(7), pdu[9] as usize);
            if !(1..=0x7D).contains(&read) {
                return Err(format!("{read} registers to read (1–125)"));
            }
            counts_agree("registers to write", write, 0x79, count, 2 * write)?;
            exact(10 + count)
        }
        _ => Ok(()),
    }
}

fn exact_at_least(pdu: &[u8], n: usize) -> Result<(), String> {
    if pdu.len() < n {
        return Err(format!("{} bytes, at least {n} expected", pdu.len()));
    }
    Ok(())
}

/// `quantity` is 1..=`max` and the byte count is the one it needs.
fn counts_agree(what: &str, quantity: usize, max: usize, count: usize, needed: usize) -> Result<(), String> {
    if !(1..=max).contains(&quantity) || count != needed {
        return Err(format!("quantity {quantity} {what} (1–{max}) with a byte count of {count}"));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    const READ: [u8; 12] = [0, 2, 0, 0, 0, 6, 1, 0x04, 0, 0, 0, 12];

    #[test]
    fn well_formed_requests_pass_whole_and_a_partial_one_waits() {
        let coils = [0, 3, 0, 0, 0, 9, 1, 0x0F, 0, 0, 0, 10, 2, 0xFF, 0x03];
        let regs = [0, 4, 0, 0, 0, 11, 1, 0x10, 0, 0, 0, 2, 4, 0, 1, 0, 2];
        let all: Vec<u8> = [&READ[..], &coils, &regs].concat();
        assert_eq!(scan(&all), Scan { passed: all.len(), refused: None });
        assert_eq!(scan(&all[..all.len() - 1]), Scan { passed: READ.len() + coils.len(), refused: None });
        assert_eq!(scan(&READ[..5]), Scan { passed: 0, refused: None });
    }

    /// The frame that panics tokio-modbus 0.15's decoder: function 0x0F, quantity 65 535,
    /// byte count 0. Refused with "illegal data value" for its transaction and unit.
    #[test]
    fn write_multiple_coils_with_more_coils_than_bytes_is_refused() {
        let bad = [0, 1, 0, 0, 0, 7, 1, 0x0F, 0, 0, 0xFF, 0xFF, 0];
        let both: Vec<u8> = [&READ[..], &bad].concat();
        let s = scan(&both);
        assert_eq!(s.passed, READ.len(), "the good read before it passes");
        let r = s.refused.expect("refused");
        assert_eq!(r.reply, [0, 1, 0, 0, 0, 3, 1, 0x8F, 0x03]);
        assert!(r.why.contains("0x0F") && r.why.contains("65535"), "{}", r.why);
        // Counts that disagree in other ways.
        for pdu in [
            &[0x0F, 0, 0, 0, 9, 1, 0xFF][..],
            &[0x0F, 0, 0, 0, 8, 1, 0xFF, 0],
            &[0x10, 0, 0, 0, 2, 4, 0, 1, 0],
            &[0x17, 0, 0, 0, 1, 0, 0, 0, 1, 2, 0],
        ] {
            assert!(check_pdu(pdu).is_err(), "{pdu:?}");
        }
    }

    #[test]
    fn a_bad_header_is_refused_before_its_frame_is_whole() {
        let r = scan(&[0, 1, 0, 7, 0, 6, 1]).refused.expect("protocol 7");
        assert!(r.reply.is_empty() && r.why.contains("protocol 7"), "{r:?}");
        assert!(scan(&[0, 1, 0, 0, 0xFF, 0xFF, 1]).refused.is_some(), "a length of 65 535");
        assert!(scan(&[0, 1, 0, 0, 0, 1, 1]).refused.is_some(), "a length without a function code");
    }
}
