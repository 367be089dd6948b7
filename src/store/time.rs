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

/// Whether `s` is a time as [`format_millis`] writes it: that exact shape, and a real instant
/// (month 01–12, a day the month has, 00:00:00.000–23:59:59.999).
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
        && in_calendar(b)
}

/// The date and time fields of a string of [`is_timestamp`]'s shape are in range.
fn in_calendar(b: &[u8]) -> bool {
    let num =
        |r: std::ops::Range<usize>| b[r].iter().fold(0u32, |n, &c| n * 10 + u32::from(c - b'0'));
    let (y, m, d) = (num(0..4), num(5..7), num(8..10));
    let leap = (y % 4 == 0 && y % 100 != 0) || y % 400 == 0;
    let days = match m {
        1 | 3 | 5 | 7 | 8 | 10 | 12 => 31,
        4 | 6 | 9 | 11 => 30,
        2 if leap => 29,
        2 => 28,
        _ => return false,
    };
    (1..=days).contains(&d) && num(11..13) < 24 && num(14..16) < 60 && num(17..19) < 60
}

/// A time filter as a client may write it — RFC 3339 UTC, `YYYY-MM-DDTHH:MM:SSZ` or with 1 to 3
/// fraction digits (`…:SS.1Z`, `…:SS.123Z`) — in the stored form (`.mmm`), so that it compares
/// with stored times as a string. `None` for anything else, including impossible dates and times
/// (`2026-99-99T99:99:99Z`, February 30th, a leap second, which stored times never have).
pub fn normalize_timestamp(s: &str) -> Option<String> {
    let body = s.strip_suffix('Z')?;
    let (head, frac) = match body.split_once('.') {
        Some((head, frac)) if !frac.is_empty() => (head, frac),
        Some(_) => return None,
        None => (body, ""),
    };
    if head.len() != 19 || frac.len() > 3 || !frac.bytes().all(|c| c.is_ascii_digit()) {
        return None;
    }
    let t = format!("{head}.{frac:0<3}Z");
    is_timestamp(&t).then_some(t)
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
        assert!(!is_timestamp("2026-99-99T99:99:99.000Z"));
    }

    #[test]
    fn filters_are_checked_against_the_calendar() {
        for (given, stored) in [
            ("2026-12-01T16:09:21Z", "2026-12-01T16:09:21.000Z"),
            ("2026-12-01T16:09:21.1Z", "2026-12-01T16:09:21.100Z"),
            ("2026-12-01T16:09:21.123Z", "2026-12-01T16:09:21.123Z"),
            ("2024-02-29T23:59:59Z", "2024-02-29T23:59:59.000Z"),
            ("2000-02-29T00:00:00Z", "2000-02-29T00:00:00.000Z"),
        ] {
            assert_eq!(
                normalize_timestamp(given).as_deref(),
                Some(stored),
                "{given}"
            );
        }
        for bad in [
            "2026-99-99T99:99:99Z",
            "2026-13-01T00:00:00Z",
            "2026-00-01T00:00:00Z",
            "2026-04-31T00:00:00Z",
            "2026-02-29T00:00:00Z",
            "1900-02-29T00:00:00Z",
            "2026-12-00T00:00:00Z",
            "2026-12-01T24:00:00Z",
            "2026-12-01T23:60:00Z",
            "2026-12-31T23:59:60Z",
            "2026-12-01T16:09:21.1234Z",
            "2026-12-01T16:09:21.Z",
            "2026-12-01T16:09:21",
            "2026-12-01",
            "2026-12-01T16:09:21+01:00",
            "+2026-12-01T16:09:21Z",
            "yesterday",
            "",
        ] {
            assert_eq!(normalize_timestamp(bad), None, "{bad}");
        }
        assert!(now() < after(Duration::from_millis(5)));
    }
}
