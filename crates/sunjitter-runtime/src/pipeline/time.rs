//! Times as the output contract writes them: ISO 8601 UTC.

/// ISO 8601 UTC with milliseconds, e.g. `2014-03-29T14:09:38.680Z` (the contract's `obs_time`).
pub fn iso8601_utc(ns: i64) -> String {
    sunjitter_core::time::format_iso_utc(ns)
}

/// Parse an ISO 8601 UTC time back to ns since the epoch.
pub fn parse_iso8601_utc(s: &str) -> Option<i64> {
    sunjitter_core::time::parse_fits_time(s, sunjitter_core::time::TimeScale::Utc).ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn iso_times_match_python_datetime() {
        // python: datetime.fromisoformat(s).replace(tzinfo=timezone.utc).timestamp()
        for (s, ns) in [
            ("2014-03-29T14:09:38.680Z", 1_396_102_178_680_000_000i64),
            ("1998-05-19T22:21:43.000Z", 895_616_503_000_000_000),
            ("2000-02-29T00:00:00.000Z", 951_782_400_000_000_000),
            ("1969-12-31T23:59:59.500Z", -500_000_000),
        ] {
            assert_eq!(iso8601_utc(ns), s);
            assert_eq!(parse_iso8601_utc(s), Some(ns));
        }
    }
}
