//! Time: FITS date strings → ns since the Unix epoch (UTC), TAI→UTC, ISO 8601 output.
//!
//! The civil-calendar arithmetic is written out here (proleptic Gregorian, days since
//! 1970-01-01) so that no date crate is needed. Times are `i64` nanoseconds, which covers
//! ±292 years around 1970 — every solar observation so far and for a while to come.

/// Nanoseconds per second.
pub const NS_PER_S: i64 = 1_000_000_000;
const NS_PER_DAY: i64 = 86_400 * NS_PER_S;

/// The time scale a date string was written in.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TimeScale {
    Utc,
    Tai,
}

/// TAI − UTC in seconds from each UTC date on (IERS Bulletin C; valid until the next leap
/// second is announced — none is scheduled as of 2025). Before 1972 UTC had fractional
/// offsets; those dates get the 1972 value of 10 s, and the 1 s accuracy holds only from
/// 1972 on.
const LEAP_SECONDS: [(i64, u32, u32, i64); 28] = [
    (1972, 1, 1, 10),
    (1972, 7, 1, 11),
    (1973, 1, 1, 12),
    (1974, 1, 1, 13),
    (1975, 1, 1, 14),
    (1976, 1, 1, 15),
    (1977, 1, 1, 16),
    (1978, 1, 1, 17),
    (1979, 1, 1, 18),
    (1980, 1, 1, 19),
    (1981, 7, 1, 20),
    (1982, 7, 1, 21),
    (1983, 7, 1, 22),
    (1985, 7, 1, 23),
    (1988, 1, 1, 24),
    (1990, 1, 1, 25),
    (1991, 1, 1, 26),
    (1992, 7, 1, 27),
    (1993, 7, 1, 28),
    (1994, 7, 1, 29),
    (1996, 1, 1, 30),
    (1997, 7, 1, 31),
    (1999, 1, 1, 32),
    (2006, 1, 1, 33),
    (2009, 1, 1, 34),
    (2012, 7, 1, 35),
    (2015, 7, 1, 36),
    (2017, 1, 1, 37),
];

/// Days since 1970-01-01 of a proleptic Gregorian date (H. Hinnant's `days_from_civil`).
pub fn days_from_civil(year: i64, month: u32, day: u32) -> i64 {
    let y = if month <= 2 { year - 1 } else { year };
    let era = y.div_euclid(400);
    let yoe = y - era * 400; // [0, 399]
    let m = month as i64;
    let doy = (153 * (if m > 2 { m - 3 } else { m + 9 }) + 2) / 5 + day as i64 - 1; // [0, 365]
    let doe = yoe * 365 + yoe / 4 - yoe / 100 + doy; // [0, 146096]
    era * 146_097 + doe - 719_468
}

/// The (year, month, day) of a day count since 1970-01-01 (inverse of [`days_from_civil`]).
pub fn civil_from_days(days: i64) -> (i64, u32, u32) {
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = (doy - (153 * mp + 2) / 5 + 1) as u32;
    let month = if mp < 10 { mp + 3 } else { mp - 9 } as u32;
    let year = yoe + era * 400 + i64::from(month <= 2);
    (year, month, day)
}

fn days_in_month(year: i64, month: u32) -> u32 {
    let leap = (year % 4 == 0 && year % 100 != 0) || year % 400 == 0;
    match month {
        1 | 3 | 5 | 7 | 8 | 10 | 12 => 31,
        4 | 6 | 9 | 11 => 30,
        _ if leap => 29,
        _ => 28,
    }
}

/// TAI − UTC (seconds) in force at a UTC instant.
pub fn tai_minus_utc_s(utc_ns: i64) -> i64 {
    let mut offset = LEAP_SECONDS[0].3;
    for &(y, m, d, dat) in &LEAP_SECONDS {
        if utc_ns >= days_from_civil(y, m, d) * NS_PER_DAY {
            offset = dat;
        }
    }
    offset
}

/// Convert a TAI instant (counted like a UTC label, ns since 1970) to UTC.
pub fn tai_to_utc_ns(tai_ns: i64) -> i64 {
    // A leap takes effect when TAI reaches the UTC midnight label plus the new offset.
    let mut offset = LEAP_SECONDS[0].3;
    for &(y, m, d, dat) in &LEAP_SECONDS {
        if tai_ns >= days_from_civil(y, m, d) * NS_PER_DAY + dat * NS_PER_S {
            offset = dat;
        }
    }
    tai_ns.saturating_sub(offset * NS_PER_S)
}

/// Format ns since the epoch as ISO 8601 UTC with milliseconds: `YYYY-MM-DDTHH:MM:SS.sssZ`.
pub fn format_iso_utc(ns: i64) -> String {
    // Round to the millisecond first so 59.9996 s does not print as 60.000.
    let ms = ns.div_euclid(1_000_000) + i64::from(ns.rem_euclid(1_000_000) >= 500_000);
    let days = ms.div_euclid(86_400_000);
    let ms_of_day = ms.rem_euclid(86_400_000);
    let (y, mo, d) = civil_from_days(days);
    let (h, rest) = (ms_of_day / 3_600_000, ms_of_day % 3_600_000);
    let (mi, rest) = (rest / 60_000, rest % 60_000);
    let (s, milli) = (rest / 1000, rest % 1000);
    format!("{y:04}-{mo:02}-{d:02}T{h:02}:{mi:02}:{s:02}.{milli:03}Z")
}

/// Parse a FITS date/time and return UTC ns since the epoch.
///
/// Accepts the forms met in solar archives:
/// `2011-02-15T00:00:01.34Z`, `2011-02-15T00:00:00.34`, `2011-02-15 00:00:00`,
/// `2014.03.01_00:01:25_TAI` (JSOC), `2011-02-15` (date only), `19/05/98` (old FITS dd/mm/yy).
/// A `TAI` suffix (or `default_scale` = TAI when there is none) converts TAI→UTC.
pub fn parse_fits_time(text: &str, default_scale: TimeScale) -> Result<i64, String> {
    let (labelled_ns, scale) = parse_labelled(text)?;
    match scale.unwrap_or(default_scale) {
        TimeScale::Utc => Ok(labelled_ns),
        TimeScale::Tai => Ok(tai_to_utc_ns(labelled_ns)),
    }
}

/// Combine a date-only string (`DATE-OBS = '2004-03-01'` or `'01/03/04'`) with a separate
/// time-of-day string (`TIME-OBS = '00:00:10'`) into UTC ns.
pub fn parse_date_and_time(date: &str, time: &str, scale: TimeScale) -> Result<i64, String> {
    let day_ns = parse_fits_time(date.trim(), scale)?;
    let tod_ns = parse_time_of_day(time.trim())?;
    day_ns
        .checked_add(tod_ns)
        .ok_or_else(|| out_of_range(&format!("{date} {time}")))
}

/// Parse without applying the time scale: (ns of the calendar label, explicit scale if any).
fn parse_labelled(text: &str) -> Result<(i64, Option<TimeScale>), String> {
    let bad = || format!("unrecognised date/time {text:?}");
    let (body, scale) = split_scale_suffix(text.trim());
    if body.is_empty() {
        return Err(bad());
    }
    // The date part ends at the first 'T', ' ' or '_' (JSOC uses '_').
    let split_at = body.find(['T', ' ', '_']);
    let (date_part, time_part) = match split_at {
        Some(i) => (&body[..i], body[i + 1..].trim()),
        None => (body, ""),
    };
    let days = parse_date(date_part).ok_or_else(bad)?;
    let tod_ns = if time_part.is_empty() {
        0
    } else {
        parse_time_of_day(time_part).map_err(|_| bad())?
    };
    let ns = days
        .checked_mul(NS_PER_DAY)
        .and_then(|d| d.checked_add(tod_ns))
        .ok_or_else(|| out_of_range(text))?;
    Ok((ns, scale))
}

/// A date a 64-bit count of ns since 1970 cannot hold (before 1677 or after 2262).
fn out_of_range(text: &str) -> String {
    format!("date/time {text:?} is outside the years 1678–2261 that sunjitter represents")
}

/// Strip a trailing time-scale marker (`Z`, `_TAI`, ` UTC`…) and report the scale.
fn split_scale_suffix(text: &str) -> (&str, Option<TimeScale>) {
    let upper = text.to_ascii_uppercase();
    for (suffix, scale) in [
        ("TAI", TimeScale::Tai),
        ("UTC", TimeScale::Utc),
        ("UT", TimeScale::Utc),
    ] {
        if upper.ends_with(suffix) {
            let body = text[..text.len() - suffix.len()].trim_end_matches(['_', ' ']);
            return (body, Some(scale));
        }
    }
    if upper.ends_with('Z') {
        return (&text[..text.len() - 1], Some(TimeScale::Utc));
    }
    (text, None)
}

/// Days since the epoch of `YYYY-MM-DD`, `YYYY.MM.DD`, `YYYY/MM/DD` or old-style `DD/MM/YY`.
fn parse_date(text: &str) -> Option<i64> {
    let parts: Vec<&str> = text.split(['-', '.', '/']).collect();
    if parts.len() != 3
        || parts
            .iter()
            .any(|p| p.is_empty() || !p.bytes().all(|b| b.is_ascii_digit()))
    {
        return None;
    }
    let (year, month, day) = if parts[0].len() == 4 {
        (
            parts[0].parse().ok()?,
            parts[1].parse().ok()?,
            parts[2].parse().ok()?,
        )
    } else if text.contains('/') && parts[2].len() == 2 {
        // Pre-2000 FITS form 'DD/MM/YY', defined for 1900–1999 only.
        (
            1900 + parts[2].parse::<i64>().ok()?,
            parts[1].parse().ok()?,
            parts[0].parse().ok()?,
        )
    } else {
        return None;
    };
    if !(1..=12).contains(&month) || day < 1 || day > days_in_month(year, month) {
        return None;
    }
    Some(days_from_civil(year, month, day))
}

/// `HH:MM[:SS[.fff…]]` → ns into the day (a leap second 60 is accepted and rolls over).
fn parse_time_of_day(text: &str) -> Result<i64, String> {
    let bad = || format!("unrecognised time of day {text:?}");
    let fields: Vec<&str> = text.split(':').collect();
    if fields.len() < 2 || fields.len() > 3 {
        return Err(bad());
    }
    let hour: i64 = parse_digits(fields[0]).ok_or_else(bad)?;
    let minute: i64 = parse_digits(fields[1]).ok_or_else(bad)?;
    let sec_ns = match fields.get(2) {
        Some(s) => parse_seconds_ns(s).ok_or_else(bad)?,
        None => 0,
    };
    if hour > 24 || minute > 59 || sec_ns >= 61 * NS_PER_S {
        return Err(bad());
    }
    Ok((hour * 60 + minute) * 60 * NS_PER_S + sec_ns)
}

fn parse_digits(text: &str) -> Option<i64> {
    if text.is_empty() || text.len() > 4 || !text.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    text.parse().ok()
}

/// `SS` or `SS.fff…` → ns, exactly (no float rounding), digits beyond 1 ns ignored.
fn parse_seconds_ns(text: &str) -> Option<i64> {
    let (whole, frac) = text.split_once('.').unwrap_or((text, ""));
    let seconds = parse_digits(whole)?;
    if !frac.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    let mut frac_ns = 0i64;
    for (i, b) in frac.bytes().take(9).enumerate() {
        frac_ns += i64::from(b - b'0') * 10i64.pow(8 - i as u32);
    }
    Some(seconds * NS_PER_S + frac_ns)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn iso(text: &str) -> String {
        format_iso_utc(parse_fits_time(text, TimeScale::Utc).expect(text))
    }

    #[test]
    fn civil_round_trip_and_known_days() {
        // Known day numbers (Unix epoch, 2000-01-01 = 10957, 1900-03-01 = -25508).
        assert_eq!(days_from_civil(1970, 1, 1), 0);
        assert_eq!(days_from_civil(2000, 1, 1), 10_957);
        assert_eq!(days_from_civil(1900, 3, 1), -25_508);
        assert_eq!(days_from_civil(2024, 2, 29), 19_782);
        for d in (-200_000..200_000).step_by(997) {
            let (y, m, dd) = civil_from_days(d);
            assert_eq!(days_from_civil(y, m, dd), d);
        }
    }

    #[test]
    fn parses_the_archive_forms() {
        assert_eq!(iso("2011-02-15T00:00:01.34Z"), "2011-02-15T00:00:01.340Z");
        assert_eq!(iso("2011-02-15T00:00:00.34"), "2011-02-15T00:00:00.340Z");
        assert_eq!(iso("2004-03-01T00:00:10.515Z"), "2004-03-01T00:00:10.515Z");
        assert_eq!(iso("2004-03-01 00:00:10"), "2004-03-01T00:00:10.000Z");
        assert_eq!(iso("2004-03-01"), "2004-03-01T00:00:00.000Z");
        assert_eq!(iso("19/05/98"), "1998-05-19T00:00:00.000Z");
        assert_eq!(iso("2014.03.01_00:01:30_UTC"), "2014-03-01T00:01:30.000Z");
    }

    /// A year beyond 2262 overflows the ns count (a panic in debug builds, a wrapped time in
    /// release); fuzz/corpus/fits_header/crash-time-year-4028 is such a header.
    #[test]
    fn dates_beyond_the_ns_range_are_refused() {
        for text in [
            "4028-03-29T14:09:38.830",
            "2262-04-12",
            "1600-01-01T00:00:00_TAI",
        ] {
            let e = parse_fits_time(text, TimeScale::Utc).unwrap_err();
            assert!(e.contains("outside the years"), "{e}");
        }
        assert!(parse_date_and_time("2262-04-11", "23:59:59", TimeScale::Utc).is_err());
        // The ends of the range still work (2262-04-11T23:47:16.854775807Z is i64::MAX ns).
        assert_eq!(iso("2262-04-11T23:47:16"), "2262-04-11T23:47:16.000Z");
        assert_eq!(iso("1678-01-01"), "1678-01-01T00:00:00.000Z");
    }

    #[test]
    fn tai_to_utc_uses_the_leap_second_table() {
        // HMI T_OBS; astropy: Time('2014-03-01T00:01:25', scale='tai').utc -> 00:00:50.000.
        assert_eq!(iso("2014.03.01_00:01:25_TAI"), "2014-03-01T00:00:50.000Z");
        // Across the 2016-12-31 leap second: TAI 2017-01-01T00:00:36 = UTC 23:59:60 (not
        // representable), TAI 00:00:37 = UTC 2017-01-01T00:00:00 (astropy agrees).
        assert_eq!(iso("2017-01-01T00:00:37_TAI"), "2017-01-01T00:00:00.000Z");
        assert_eq!(iso("2017-01-01T00:00:35_TAI"), "2016-12-31T23:59:59.000Z");
        assert_eq!(
            tai_minus_utc_s(days_from_civil(1998, 5, 19) * NS_PER_DAY),
            31
        );
        // Default scale TAI applies only without an explicit suffix.
        let t = parse_fits_time("2014-03-01T00:01:25", TimeScale::Tai).unwrap();
        assert_eq!(format_iso_utc(t), "2014-03-01T00:00:50.000Z");
        let t = parse_fits_time("2014-03-01T00:01:25Z", TimeScale::Tai).unwrap();
        assert_eq!(format_iso_utc(t), "2014-03-01T00:01:25.000Z");
    }

    #[test]
    fn separate_date_and_time_cards() {
        let t = parse_date_and_time("2004-03-01", "00:00:10.5", TimeScale::Utc).unwrap();
        assert_eq!(format_iso_utc(t), "2004-03-01T00:00:10.500Z");
    }

    #[test]
    fn format_rounds_to_milliseconds_and_handles_pre_epoch() {
        assert_eq!(format_iso_utc(999_600_000), "1970-01-01T00:00:01.000Z");
        assert_eq!(format_iso_utc(-1), "1970-01-01T00:00:00.000Z");
        assert_eq!(format_iso_utc(-NS_PER_S), "1969-12-31T23:59:59.000Z");
    }

    #[test]
    fn rejects_garbage_without_panicking() {
        for bad in [
            "",
            "Z",
            "2011-13-01",
            "2011-02-30",
            "2011-02-15T25:00",
            "yesterday",
            "2011-02-15T00:00:xx",
            "98/05/19, 22:21:43.000",
        ] {
            assert!(parse_fits_time(bad, TimeScale::Utc).is_err(), "{bad}");
        }
    }
}
