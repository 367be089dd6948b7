//! Watermark messages: L bits written as hexadecimal (most significant bit of the first digit
//! first), and fresh random messages.

/// A message string that does not fit.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum MessageError {
    /// The message itself is a secret: the error names only where the first character that is
    /// not a hex digit is (counted in characters, from 1), never the message.
    #[error("message is not hexadecimal (digits 0-9, a-f): character {0} is not a hex digit")]
    NotHex(usize),
    #[error("message is empty")]
    Empty,
    #[error("message has {got} bits ({digits} hex digits), {want} bits need {} hex digits", want / 4)]
    Length {
        got: usize,
        digits: usize,
        want: usize,
    },
    #[error("message lengths must be a positive multiple of 4 bits, got {0}")]
    BadBits(usize),
}

/// Parses `hex` (an optional `0x` prefix, case-insensitive) into exactly `bits` bits.
pub fn parse_hex(hex: &str, bits: usize) -> Result<Vec<bool>, MessageError> {
    if bits == 0 || !bits.is_multiple_of(4) {
        return Err(MessageError::BadBits(bits));
    }
    let trimmed = hex.trim();
    let s = trimmed
        .strip_prefix("0x")
        .or_else(|| trimmed.strip_prefix("0X"))
        .unwrap_or(trimmed);
    // Characters before the digits: leading white space and the prefix.
    let skipped = hex.chars().take_while(|c| c.is_whitespace()).count() + (trimmed.len() - s.len());
    let digits: Vec<u32> = s
        .chars()
        .enumerate()
        .map(|(k, c)| c.to_digit(16).ok_or(MessageError::NotHex(skipped + k + 1)))
        .collect::<Result<_, _>>()?;
    if digits.is_empty() {
        return Err(MessageError::Empty);
    }
    if digits.len() * 4 != bits {
        return Err(MessageError::Length {
            got: digits.len() * 4,
            digits: digits.len(),
            want: bits,
        });
    }
    Ok(digits
        .iter()
        .flat_map(|d| (0..4).rev().map(move |k| (d >> k) & 1 == 1))
        .collect())
}

/// Lower-case hex of `bits` (length a multiple of 4).
pub fn to_hex(bits: &[bool]) -> String {
    bits.chunks(4)
        .map(|c| {
            let v = c.iter().fold(0u32, |a, &b| (a << 1) | u32::from(b));
            let v = v << (4 - c.len());
            char::from_digit(v, 16).expect("nibble")
        })
        .collect()
}

/// `bits` bits from the operating system's random source (the random bits of v4 UUIDs, which
/// come from `getrandom`; the six fixed version/variant bits of each UUID are skipped).
pub fn random_message(bits: usize) -> Vec<bool> {
    let mut out = Vec::with_capacity(bits);
    while out.len() < bits {
        let b = uuid::Uuid::new_v4().into_bytes();
        for (i, byte) in b.iter().enumerate() {
            for k in (0..8).rev() {
                // Version: high nibble of byte 6; variant: top two bits of byte 8.
                let fixed = (i == 6 && k >= 4) || (i == 8 && k >= 6);
                if !fixed && out.len() < bits {
                    out.push((byte >> k) & 1 == 1);
                }
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hex_round_trips_msb_first() {
        let m = parse_hex("0xA5", 8).unwrap();
        assert_eq!(m, [true, false, true, false, false, true, false, true]);
        assert_eq!(to_hex(&m), "a5");
        let h = "deadbeef0123456789abcdef";
        assert_eq!(to_hex(&parse_hex(h, 96).unwrap()), h);
        assert_eq!(to_hex(&parse_hex("DEADBEEF", 32).unwrap()), "deadbeef");
    }

    #[test]
    fn bad_messages_are_typed_errors() {
        assert_eq!(parse_hex("xyz", 12), Err(MessageError::NotHex(1)));
        assert_eq!(parse_hex(" 0xdeadbeeg", 32), Err(MessageError::NotHex(11)));
        assert_eq!(parse_hex("", 4), Err(MessageError::Empty));
        assert_eq!(parse_hex(" 0x ", 4), Err(MessageError::Empty));
        // The message is a secret: an error never repeats it.
        let e = parse_hex("c0ffee5ecre7", 48).unwrap_err().to_string();
        assert!(!e.contains("c0ffee5ec"), "{e}");
        assert!(e.contains("character 10"), "{e}");
        assert_eq!(
            parse_hex("abc", 32),
            Err(MessageError::Length {
                got: 12,
                digits: 3,
                want: 32
            })
        );
        assert_eq!(parse_hex("a", 3), Err(MessageError::BadBits(3)));
    }

    #[test]
    fn random_messages_differ_and_are_balanced() {
        let a = random_message(64);
        let b = random_message(64);
        assert_eq!(a.len(), 64);
        assert_ne!(a, b);
        let ones: usize = (0..50)
            .map(|_| random_message(64).iter().filter(|&&x| x).count())
            .sum();
        // 3200 fair bits: mean 1600, std 28; fixed UUID bits would bias it by ~150.
        assert!((1480..=1720).contains(&ones), "{ones}");
    }
}
