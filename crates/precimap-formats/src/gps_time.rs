//! GPS time in one place: the conventions files use, the GPS week, and leap seconds.
//!
//! - **GPS week seconds**: seconds since the start of the GPS week (Sunday 00:00 GPS time); what
//!   SBET files and LAS files without the global-encoding bit carry. The week itself is not in
//!   the file: the manifest's `gps_week` names it, or it is derived from a file that has it.
//! - **Adjusted standard GPS time**: seconds since the GPS epoch (1980-01-06 00:00 UTC) minus
//!   10⁹; LAS files with global-encoding bit 0 set.
//! - **UTC** (Unix seconds) only for ASCII exports that use it; GPS time does not have leap
//!   seconds, UTC does, and [`LEAP_SECONDS`] is the one table of them.

use std::fmt;

pub const SECONDS_PER_WEEK: f64 = 604_800.0;
/// Adjusted standard GPS time = GPS time − this.
pub const ADJUSTED_STANDARD_OFFSET_S: f64 = 1e9;
/// The GPS epoch, 1980-01-06 00:00:00 UTC, in Unix seconds.
pub const GPS_EPOCH_UNIX_S: i64 = 315_964_800;

/// UTC dates (year, month; the leap second is inserted just before the 1st, 00:00 UTC) from which
/// GPS − UTC is the given number of seconds (IERS Bulletin C). Append here when the IERS announces
/// one.
pub const LEAP_SECONDS: [(i32, u32, i32); 18] = [
    (1981, 7, 1),
    (1982, 7, 2),
    (1983, 7, 3),
    (1985, 7, 4),
    (1988, 1, 5),
    (1990, 1, 6),
    (1991, 1, 7),
    (1992, 7, 8),
    (1993, 7, 9),
    (1994, 7, 10),
    (1996, 1, 11),
    (1997, 7, 12),
    (1999, 1, 13),
    (2006, 1, 14),
    (2009, 1, 15),
    (2012, 7, 16),
    (2015, 7, 17),
    (2017, 1, 18),
];

/// Days from 1970-01-01 to the first of `month` in `year` (proleptic Gregorian).
fn days_from_civil(year: i32, month: u32) -> i64 {
    let y = i64::from(year) - i64::from(month <= 2);
    let era = y.div_euclid(400);
    let yoe = y - era * 400;
    let m = i64::from(month);
    let doy = (153 * (if m > 2 { m - 3 } else { m + 9 }) + 2) / 5;
    let doe = yoe * 365 + yoe / 4 - yoe / 100 + doy;
    era * 146_097 + doe - 719_468
}

/// GPS − UTC in seconds at Unix time `unix_s` (UTC).
pub fn gps_minus_utc_at_unix(unix_s: f64) -> i32 {
    LEAP_SECONDS
        .iter()
        .take_while(|(y, m, _)| unix_s >= (days_from_civil(*y, *m) * 86_400) as f64)
        .last()
        .map_or(0, |l| l.2)
}

/// GPS seconds since the GPS epoch of a UTC instant in Unix seconds.
pub fn gps_from_unix_utc(unix_s: f64) -> f64 {
    unix_s - GPS_EPOCH_UNIX_S as f64 + f64::from(gps_minus_utc_at_unix(unix_s))
}

/// Inverse of [`gps_from_unix_utc`] (outside the leap second itself).
pub fn unix_utc_from_gps(gps_s: f64) -> f64 {
    let approx = gps_s + GPS_EPOCH_UNIX_S as f64;
    let guess = approx - f64::from(gps_minus_utc_at_unix(approx));
    approx - f64::from(gps_minus_utc_at_unix(guess))
}

/// How a file states GPS time.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TimeConvention {
    WeekSeconds,
    AdjustedStandard,
}

impl fmt::Display for TimeConvention {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Self::WeekSeconds => "GPS week seconds",
            Self::AdjustedStandard => "adjusted standard GPS time",
        })
    }
}

/// The GPS week of an adjusted standard GPS time.
pub fn week_of_adjusted(t: f64) -> Option<u32> {
    let w = ((t + ADJUSTED_STANDARD_OFFSET_S) / SECONDS_PER_WEEK).floor();
    (w.is_finite() && (0.0..=f64::from(u16::MAX)).contains(&w)).then_some(w as u32)
}

/// Seconds to add to a time in `from` to express it in `to`, given the GPS week of the week
/// seconds involved.
pub fn offset(from: TimeConvention, to: TimeConvention, week: u32) -> f64 {
    let week_start_adjusted = f64::from(week) * SECONDS_PER_WEEK - ADJUSTED_STANDARD_OFFSET_S;
    match (from, to) {
        (TimeConvention::WeekSeconds, TimeConvention::AdjustedStandard) => week_start_adjusted,
        (TimeConvention::AdjustedStandard, TimeConvention::WeekSeconds) => -week_start_adjusted,
        _ => 0.0,
    }
}

/// A time range in both conventions, for messages: `345600.000–345700.000 s of GPS week 2311
/// (adjusted standard 397 …)`; without a week only the given convention.
pub fn describe_range(first: f64, last: f64, convention: TimeConvention, week: Option<u32>) -> String {
    let shown = format!("{first:.3}–{last:.3} s {convention}");
    let Some(week) = week else {
        return format!("{shown} (GPS week unknown)");
    };
    let other = match convention {
        TimeConvention::WeekSeconds => TimeConvention::AdjustedStandard,
        TimeConvention::AdjustedStandard => TimeConvention::WeekSeconds,
    };
    let d = offset(convention, other, week);
    let (first_o, last_o) = (first + d, last + d);
    match convention {
        TimeConvention::WeekSeconds => {
            format!("{first:.3}–{last:.3} s of GPS week {week} ({first_o:.3}–{last_o:.3} s {other})")
        }
        TimeConvention::AdjustedStandard => {
            format!("{shown} ({first_o:.3}–{last_o:.3} s of GPS week {week})")
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn leap_seconds_at_known_dates() {
        // 2017-01-01 00:00:00 UTC = Unix 1483228800; GPS−UTC became 18 s there.
        assert_eq!(days_from_civil(2017, 1) * 86_400, 1_483_228_800);
        assert_eq!(gps_minus_utc_at_unix(1_483_228_799.0), 17);
        assert_eq!(gps_minus_utc_at_unix(1_483_228_800.0), 18);
        assert_eq!(gps_minus_utc_at_unix(GPS_EPOCH_UNIX_S as f64), 0);
        assert_eq!(days_from_civil(1980, 1) * 86_400 + 5 * 86_400, GPS_EPOCH_UNIX_S);
        // GPS week 2000 began 2018-05-06 00:00:00 GPS = 2018-05-05 23:59:42 UTC.
        let unix = 1_525_564_782.0;
        assert_eq!(gps_from_unix_utc(unix), 2000.0 * SECONDS_PER_WEEK);
        assert_eq!(unix_utc_from_gps(2000.0 * SECONDS_PER_WEEK), unix);
    }

    #[test]
    fn week_seconds_and_adjusted_standard() {
        let week = 2311;
        let sow = 345_600.25;
        let adjusted = sow + offset(TimeConvention::WeekSeconds, TimeConvention::AdjustedStandard, week);
        assert_eq!(adjusted, 2311.0 * 604_800.0 + 345_600.25 - 1e9);
        assert_eq!(week_of_adjusted(adjusted), Some(week));
        assert_eq!(adjusted + offset(TimeConvention::AdjustedStandard, TimeConvention::WeekSeconds, week), sow);
        assert_eq!(offset(TimeConvention::WeekSeconds, TimeConvention::WeekSeconds, week), 0.0);
        assert_eq!(week_of_adjusted(f64::NAN), None);
        let shown = describe_range(sow, sow + 10.0, TimeConvention::WeekSeconds, Some(week));
        assert!(shown.contains("345600.250–345610.250 s of GPS week 2311"), "{shown}");
        assert!(shown.contains(&format!("{adjusted:.3}")) && shown.contains("adjusted standard"), "{shown}");
        let shown = describe_range(adjusted, adjusted + 1.0, TimeConvention::AdjustedStandard, Some(week));
        assert!(shown.contains("345600.250–345601.250 s of GPS week 2311"), "{shown}");
        assert!(describe_range(1.0, 2.0, TimeConvention::WeekSeconds, None).contains("week unknown"));
    }
}
