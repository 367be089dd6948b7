//! Timestamps: RFC 3339 UTC text with milliseconds (`2026-12-01T16:09:21.123Z`), made in Rust
//! from the system clock so that every stored time has the same width and `since`/`until` filters
//! and lease comparisons work as plain string comparisons.

use std::time::{Duration, SystemTime, UNIX_EPOCH};

/// Now, formatted.
pub(crate) fn now() -> String {
    format_millis(now_millis())
}

/// Now plus `d`, formatted.
pub(crate) fn after(d: Duration) -> String {
    let ms = i64::try_from(d.as_millis()).unwrap_or(i64::MAX / 2);
    format_millis(now_millis().saturating_add(ms))
}

fn now_millis() -> i64 {
    match SystemTime::now().duration_since(UNIX_EPOCH) {
        Ok(d) => i64::try_from(d.as_millis()).unwrap_or(i64::MAX / 2),
        Err(e) => -i64::try_from(e.duration().as_millis()).unwrap_or(i64::MAX / 2),
    }
}

/// Formats milliseconds since the Unix epoch (proleptic Gregorian calendar, UTC).
pub(crate) fn format_millis(ms: i64) -> String {
    let days = ms.div_euclid(86_400_000);
    let in_day = ms.rem_euclid(86_400_000);
    let (y, m, d) = civil_from_days(days);
    let (h, rest) = (in_day / 3_600_000, in_day % 3_600_000);
    let (min, rest) = (rest / 60_000, rest % 60_000);
    let (s, milli) = (rest / 1000, rest % 1000);
    format!("{y:04}-{m:02}-{d:02}T{h:02}:{min:02}:{s:02}.{milli:03}Z")
}

/// Days since 1970-01-01 to (year, month, day) (H. Hinnant's `civil_from_days`).
fn civil_from_days(z: i64) -> (i64, u32, u32) {
    let z = z + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = (doy - (153 * mp + 2) / 5 + 1) as u32;
    let m = if mp < 10 { mp + 3 } else { mp - 9 } as u32;
    let y = yoe + era * 400 + i64::from(m <= 2);
    (y, m, d)
}

/// Whether `s` has exactly the shape [`format_millis`] produces (used to validate filters).
pub(crate) fn is_timestamp(s: &str) -> bool {
    let b = s.as_bytes();
    b.len() == 24
        && b.iter().enumerate().all(|(i, &c)| match i {
            4 | 7 => c == b'-',
            10 => c == b'T',
            13 | 16 => c == b':',
            19 => c == b'.',
            23 => c == b'Z',
            _ => c.is_ascii_digit(),
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn formats_known_instants() {
        assert_eq!(format_millis(0), "1970-01-01T00:00:00.000Z");
        assert_eq!(format_millis(951_782_400_000), "2000-02-29T00:00:00.000Z");
        assert_eq!(format_millis(1_798_761_599_999), "2026-12-31T23:59:59.999Z");
        assert!(is_timestamp(&now()));
        assert!(!is_timestamp("2026-12-31 23:59:59.999Z"));
        assert!(now() < after(Duration::from_millis(5)));
    }
}
