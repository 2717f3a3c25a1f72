//! Modbus register codec: a configured value (type, word order, scale, offset) to and from
//! its 16-bit registers.
//!
//! Bytes of a 32-bit value are named A (most significant) .. D (least significant). A Modbus
//! register carries two bytes, sent high byte first. The word orders place them as:
//!
//! | order | register n | register n+1 |
//! | --- | --- | --- |
//! | `ABCD` (big) | A B | C D |
//! | `CDAB` (little) | C D | A B |
//! | `BADC` | B A | D C |
//! | `DCBA` | D C | B A |
//!
//! 16-bit types are one register, high byte first, and ignore the word order.

use crate::utm::config::{RegisterConfig, ValueType, WordOrder};

/// Error turning registers into a value.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DecodeError {
    /// The reply did not carry as many registers as the type spans.
    #[error("register {register}: {value_type:?} needs {expected} register(s), got {got}")]
    WrongLength {
        /// First register of the value (0-based).
        register: u16,
        /// Configured type.
        value_type: ValueType,
        /// Registers the type spans.
        expected: usize,
        /// Registers received.
        got: usize,
    },
    /// The raw float is NaN or infinite (a device fault value, or a wrong word order).
    #[error("register {register}: raw f32 {raw} (registers {words:04X?}) is not a finite number; check the type and word order")]
    NotFinite {
        /// First register of the value (0-based).
        register: u16,
        /// The decoded raw value.
        raw: f32,
        /// The registers as received.
        words: Vec<u16>,
    },
}

/// Error turning a value into registers (the simulated UTM).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum EncodeError {
    /// The value, once offset and scale are undone, does not fit the register type.
    #[error("register {register}: value {value} gives raw {raw}, outside the range of {value_type:?}")]
    OutOfRange {
        /// First register of the value (0-based).
        register: u16,
        /// Configured type.
        value_type: ValueType,
        /// The engineering value asked for.
        value: f64,
        /// `(value - offset) / scale`.
        raw: f64,
    },
}

/// Decodes `words` (the registers starting at `reg.register`, at least as many as the type
/// spans; extra words are ignored) into `raw * scale + offset`.
pub fn decode(reg: &RegisterConfig, words: &[u16]) -> Result<f64, DecodeError> {
    let n = reg.value_type.registers() as usize;
    if words.len() < n {
        return Err(DecodeError::WrongLength { register: reg.register, value_type: reg.value_type, expected: n, got: words.len() });
    }
    let raw = match reg.value_type {
        ValueType::I16 => words[0] as i16 as f64,
        ValueType::U16 => words[0] as f64,
        ValueType::I32 => i32::from_be_bytes(to_abcd(reg.word_order, words[0], words[1])) as f64,
        ValueType::U32 => u32::from_be_bytes(to_abcd(reg.word_order, words[0], words[1])) as f64,
        ValueType::F32 => {
            let f = f32::from_be_bytes(to_abcd(reg.word_order, words[0], words[1]));
            if !f.is_finite() {
                return Err(DecodeError::NotFinite { register: reg.register, raw: f, words: words[..n].to_vec() });
            }
            f as f64
        }
    };
    Ok(raw * reg.scale + reg.offset)
}

/// Encodes `value` as the registers `decode` reads back: `raw = (value - offset) / scale`,
/// rounded to the nearest integer for integer types (out of range is an error).
pub fn encode(reg: &RegisterConfig, value: f64) -> Result<Vec<u16>, EncodeError> {
    let raw = (value - reg.offset) / reg.scale;
    let out_of_range = || EncodeError::OutOfRange { register: reg.register, value_type: reg.value_type, value, raw };
    let int_in = |lo: f64, hi: f64| -> Result<f64, EncodeError> {
        let r = raw.round();
        if r.is_finite() && r >= lo && r <= hi {
            Ok(r)
        } else {
            Err(out_of_range())
        }
    };
    Ok(match reg.value_type {
        ValueType::I16 => vec![int_in(i16::MIN as f64, i16::MAX as f64)? as i16 as u16],
        ValueType::U16 => vec![int_in(0.0, u16::MAX as f64)? as u16],
        ValueType::I32 => from_abcd(reg.word_order, (int_in(i32::MIN as f64, i32::MAX as f64)? as i32).to_be_bytes()),
        ValueType::U32 => from_abcd(reg.word_order, (int_in(0.0, u32::MAX as f64)? as u32).to_be_bytes()),
        ValueType::F32 => {
            let f = raw as f32;
            if !f.is_finite() {
                return Err(out_of_range());
            }
            from_abcd(reg.word_order, f.to_be_bytes())
        }
    })
}

/// Reorders two registers into big-endian bytes `[A, B, C, D]`.
fn to_abcd(order: WordOrder, w0: u16, w1: u16) -> [u8; 4] {
    let [p, q] = w0.to_be_bytes();
    let [r, s] = w1.to_be_bytes();
    match order {
        WordOrder::Abcd => [p, q, r, s],
        WordOrder::Cdab => [r, s, p, q],
        WordOrder::Badc => [q, p, s, r],
        WordOrder::Dcba => [s, r, q, p],
    }
}

/// Inverse of [`to_abcd`]: big-endian bytes `[A, B, C, D]` to two registers.
fn from_abcd(order: WordOrder, [a, b, c, d]: [u8; 4]) -> Vec<u16> {
    let (w0, w1) = match order {
        WordOrder::Abcd => ([a, b], [c, d]),
        WordOrder::Cdab => ([c, d], [a, b]),
        WordOrder::Badc => ([b, a], [d, c]),
        WordOrder::Dcba => ([d, c], [b, a]),
    };
    vec![u16::from_be_bytes(w0), u16::from_be_bytes(w1)]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::utm::config::RegisterKind;

    fn reg(value_type: ValueType, word_order: WordOrder) -> RegisterConfig {
        RegisterConfig { register: 7, kind: RegisterKind::Input, value_type, word_order, scale: 1.0, offset: 0.0 }
    }

    const ORDERS: [WordOrder; 4] = [WordOrder::Abcd, WordOrder::Cdab, WordOrder::Badc, WordOrder::Dcba];

    /// The registers of bytes 0xAA 0xBB 0xCC 0xDD (A..D) in each order, as on the wire.
    fn pattern(order: WordOrder, abcd: u32) -> [u16; 2] {
        let [a, b, c, d] = abcd.to_be_bytes();
        let w = |x: u8, y: u8| u16::from_be_bytes([x, y]);
        match order {
            WordOrder::Abcd => [w(a, b), w(c, d)],
            WordOrder::Cdab => [w(c, d), w(a, b)],
            WordOrder::Badc => [w(b, a), w(d, c)],
            WordOrder::Dcba => [w(d, c), w(b, a)],
        }
    }

    #[test]
    fn f32_in_every_word_order() {
        // 12.5f32 = 0x41480000, -3.25f32 = 0xC0500000, 1.0e-3f32 = 0x3A83126F.
        for (bits, value) in [(0x4148_0000u32, 12.5f64), (0xC050_0000, -3.25), (0x3A83_126F, 1.0e-3f32 as f64)] {
            for order in ORDERS {
                let words = pattern(order, bits);
                let got = decode(&reg(ValueType::F32, order), &words).unwrap();
                assert_eq!(got, value, "{order:?} {words:04X?}");
            }
        }
        // Literal wire patterns, written out by hand.
        assert_eq!(decode(&reg(ValueType::F32, WordOrder::Abcd), &[0x4148, 0x0000]).unwrap(), 12.5);
        assert_eq!(decode(&reg(ValueType::F32, WordOrder::Cdab), &[0x0000, 0x4148]).unwrap(), 12.5);
        assert_eq!(decode(&reg(ValueType::F32, WordOrder::Badc), &[0x4841, 0x0000]).unwrap(), 12.5);
        assert_eq!(decode(&reg(ValueType::F32, WordOrder::Dcba), &[0x0000, 0x4841]).unwrap(), 12.5);
        assert_eq!(decode(&reg(ValueType::F32, WordOrder::Badc), &[0x833A, 0x6F12]).unwrap(), 1.0e-3f32 as f64);
        assert_eq!(decode(&reg(ValueType::F32, WordOrder::Dcba), &[0x6F12, 0x833A]).unwrap(), 1.0e-3f32 as f64);
    }

    #[test]
    fn i32_and_u32_in_every_word_order() {
        // -25000 = 0xFFFF9E58; 3_000_000_000 = 0xB2D05E00; 0x01020304 = 16909060.
        for order in ORDERS {
            let r = reg(ValueType::I32, order);
            assert_eq!(decode(&r, &pattern(order, 0xFFFF_9E58)).unwrap(), -25000.0);
            assert_eq!(decode(&r, &pattern(order, 0x0102_0304)).unwrap(), 16_909_060.0);
            assert_eq!(decode(&r, &pattern(order, 0x8000_0000)).unwrap(), i32::MIN as f64);
            let r = reg(ValueType::U32, order);
            assert_eq!(decode(&r, &pattern(order, 0xB2D0_5E00)).unwrap(), 3_000_000_000.0);
            assert_eq!(decode(&r, &pattern(order, 0xFFFF_FFFF)).unwrap(), u32::MAX as f64);
        }
        assert_eq!(decode(&reg(ValueType::I32, WordOrder::Abcd), &[0x0102, 0x0304]).unwrap(), 16_909_060.0);
        assert_eq!(decode(&reg(ValueType::I32, WordOrder::Cdab), &[0x0304, 0x0102]).unwrap(), 16_909_060.0);
        assert_eq!(decode(&reg(ValueType::I32, WordOrder::Badc), &[0x0201, 0x0403]).unwrap(), 16_909_060.0);
        assert_eq!(decode(&reg(ValueType::I32, WordOrder::Dcba), &[0x0403, 0x0201]).unwrap(), 16_909_060.0);
        assert_eq!(decode(&reg(ValueType::U32, WordOrder::Badc), &[0xD0B2, 0x005E]).unwrap(), 3_000_000_000.0);
    }

    #[test]
    fn sixteen_bit_types_ignore_word_order() {
        for order in ORDERS {
            assert_eq!(decode(&reg(ValueType::I16, order), &[0xFB2E]).unwrap(), -1234.0);
            assert_eq!(decode(&reg(ValueType::I16, order), &[0x7FFF]).unwrap(), 32767.0);
            assert_eq!(decode(&reg(ValueType::U16, order), &[0xD431]).unwrap(), 54321.0);
            assert_eq!(decode(&reg(ValueType::U16, order), &[0xFB2E, 0x1234]).unwrap(), 64302.0);
        }
    }

    #[test]
    fn scale_and_offset_apply_after_decoding() {
        let mut r = reg(ValueType::I32, WordOrder::Abcd);
        r.scale = 0.001;
        r.offset = 2.0;
        let got = decode(&r, &[0xFFFF, 0x9E58]).unwrap();
        assert!((got - (-25.0 + 2.0)).abs() < 1e-12, "{got}");
        let mut r = reg(ValueType::U16, WordOrder::Abcd);
        r.scale = 0.5;
        r.offset = -1.0;
        assert_eq!(decode(&r, &[100]).unwrap(), 49.0);
    }

    #[test]
    fn short_replies_and_non_finite_floats_are_errors_naming_the_register() {
        let e = decode(&reg(ValueType::F32, WordOrder::Abcd), &[0x4148]).unwrap_err();
        assert!(matches!(e, DecodeError::WrongLength { register: 7, expected: 2, got: 1, .. }));
        assert!(e.to_string().starts_with("register 7:"), "{e}");
        assert!(decode(&reg(ValueType::U16, WordOrder::Abcd), &[]).is_err());
        for bits in [0x7FC0_0000u32, 0x7F80_0000, 0xFF80_0000] {
            for order in ORDERS {
                let e = decode(&reg(ValueType::F32, order), &pattern(order, bits)).unwrap_err();
                assert!(matches!(e, DecodeError::NotFinite { register: 7, .. }), "{e}");
                assert!(e.to_string().contains("register 7"), "{e}");
            }
        }
    }

    #[test]
    fn encode_is_the_inverse_of_decode() {
        let types = [ValueType::F32, ValueType::I16, ValueType::U16, ValueType::I32, ValueType::U32];
        for vt in types {
            for order in ORDERS {
                let mut r = reg(vt, order);
                r.scale = 0.01;
                r.offset = 1.5;
                for value in [1.5, 12.34, 200.0, 301.25] {
                    let words = encode(&r, value).unwrap();
                    assert_eq!(words.len(), vt.registers() as usize);
                    let back = decode(&r, &words).unwrap();
                    // Integer types round to one count (0.01), f32 to ~1e-7 relative.
                    let tol = if vt == ValueType::F32 { 1e-4 } else { 0.005 + 1e-9 };
                    assert!((back - value).abs() <= tol, "{vt:?} {order:?}: {value} -> {words:04X?} -> {back}");
                }
            }
        }
        assert_eq!(encode(&reg(ValueType::F32, WordOrder::Cdab), 12.5).unwrap(), vec![0x0000, 0x4148]);
        assert_eq!(encode(&reg(ValueType::U32, WordOrder::Badc), 3e9).unwrap(), vec![0xD0B2, 0x005E]);
        assert_eq!(encode(&reg(ValueType::I16, WordOrder::Abcd), -1234.0).unwrap(), vec![0xFB2E]);
    }

    #[test]
    fn encode_rejects_values_outside_the_type() {
        assert!(encode(&reg(ValueType::I16, WordOrder::Abcd), 40000.0).is_err());
        assert!(encode(&reg(ValueType::U16, WordOrder::Abcd), -1.0).is_err());
        assert!(encode(&reg(ValueType::U32, WordOrder::Abcd), -0.6).is_err());
        assert!(encode(&reg(ValueType::I32, WordOrder::Abcd), 3e9).is_err());
        assert!(encode(&reg(ValueType::F32, WordOrder::Abcd), 1e39).is_err());
        assert!(encode(&reg(ValueType::F32, WordOrder::Abcd), f64::NAN).is_err());
    }
}
