//! Configurable ASCII trajectories: the text exports of navigation software (one pose per line,
//! columns chosen by the manifest's `ascii` layout).

use crate::navigation::{AttitudeConvention, NavSamples};
use crate::FormatError;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Which column (0-based) holds what. `x`/`y` are easting/northing in a projected CRS or
/// longitude/latitude in degrees in a geographic one; `z` is the ellipsoidal height.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AsciiColumns {
    pub time: usize,
    pub x: usize,
    pub y: usize,
    pub z: usize,
    pub roll: usize,
    pub pitch: usize,
    pub heading: usize,
}

impl AsciiColumns {
    pub const NAMES: [&'static str; 7] = ["time", "x", "y", "z", "roll", "pitch", "heading"];

    fn indices(&self) -> [usize; 7] {
        [self.time, self.x, self.y, self.z, self.roll, self.pitch, self.heading]
    }
}

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AngleUnit {
    #[default]
    Deg,
    Rad,
}

/// How the angles are meant ([`crate::navigation::AttitudeConvention`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AsciiAttitude {
    /// Roll, pitch, true heading (clockwise from north) in north-east-down.
    #[default]
    Navigation,
    /// precimap's roll, pitch, yaw (counter-clockwise from grid east) about the grid axes.
    Grid,
}

/// What the time column counts.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AsciiTime {
    /// GPS seconds of the week.
    #[default]
    WeekSeconds,
    /// GPS seconds since the GPS epoch minus 10⁹ (as LAS files with the global-encoding bit).
    AdjustedStandard,
    /// GPS seconds since the GPS epoch (1980-01-06).
    GpsSeconds,
    /// UTC as Unix seconds; converted to GPS time with the leap-second table.
    UtcUnix,
}

fn comma() -> String {
    ",".to_string()
}

/// The manifest's `ascii` layout of a trajectory with `"format": "ascii"`.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AsciiLayout {
    /// One character, or `"whitespace"` for runs of blanks and tabs.
    #[serde(default = "comma")]
    pub delimiter: String,
    /// Lines to skip before the first pose.
    #[serde(default)]
    pub header_lines: usize,
    pub columns: AsciiColumns,
    /// Unit of roll, pitch and heading (geographic coordinates are always degrees).
    #[serde(default)]
    pub angle_unit: AngleUnit,
    #[serde(default)]
    pub attitude: AsciiAttitude,
    #[serde(default)]
    pub time: AsciiTime,
}

impl AsciiLayout {
    /// Problems with the layout itself, as (field, message).
    pub fn problems(&self) -> Vec<(&'static str, String)> {
        let mut out = Vec::new();
        if self.delimiter != "whitespace" && self.delimiter.chars().count() != 1 {
            out.push((
                "delimiter",
                format!("{:?} is not one character; use e.g. \",\", \";\", \"\\t\" or \"whitespace\"", self.delimiter),
            ));
        }
        let idx = self.columns.indices();
        for (i, a) in idx.iter().enumerate() {
            if *a > 1000 {
                out.push((
                    "columns",
                    format!("{} column {a} is beyond any export; columns count from 0", AsciiColumns::NAMES[i]),
                ));
            }
            if let Some(j) = idx[..i].iter().position(|b| b == a) {
                out.push((
                    "columns",
                    format!(
                        "{} and {} both name column {a}; every quantity needs its own column",
                        AsciiColumns::NAMES[j],
                        AsciiColumns::NAMES[i]
                    ),
                ));
            }
        }
        if self.header_lines > 10_000 {
            out.push(("header_lines", format!("{} header lines is implausible", self.header_lines)));
        }
        out
    }
}

fn line_error(path: &Path, line: usize, message: impl Into<String>) -> FormatError {
    FormatError::Line { path: path.to_path_buf(), line, message: message.into() }
}

/// Reads an ASCII trajectory. Times are converted to GPS week seconds or adjusted standard GPS
/// time ([`AsciiLayout::time`] says which is returned alongside: `true` for adjusted standard).
/// Geographic coordinates come back in radians when `geographic`.
pub fn read_trajectory_ascii(path: &Path, layout: &AsciiLayout, geographic: bool) -> Result<NavSamples, FormatError> {
    let text = std::fs::read(path).map_err(|e| FormatError::io(path, "read trajectory", e))?;
    parse(path, &text, layout, geographic)
}

pub(crate) fn parse(
    path: &Path,
    bytes: &[u8],
    layout: &AsciiLayout,
    geographic: bool,
) -> Result<NavSamples, FormatError> {
    let bytes = bytes.strip_prefix(b"\xEF\xBB\xBF").unwrap_or(bytes);
    let text = std::str::from_utf8(bytes).map_err(|e| {
        FormatError::file(
            path,
            format!(
                "is not text (UTF-8 error at byte {}); is this a binary SBET? use \"format\": \"sbet\"",
                e.valid_up_to()
            ),
        )
    })?;
    let convention = match layout.attitude {
        AsciiAttitude::Navigation => AttitudeConvention::Navigation,
        AsciiAttitude::Grid => AttitudeConvention::Grid,
    };
    let idx = layout.columns.indices();
    let needed = idx.iter().max().map_or(0, |m| m + 1);
    let delimiter = layout.delimiter.chars().next().filter(|_| layout.delimiter != "whitespace");
    let mut out = NavSamples::with_capacity(text.len() / 80, convention);
    let angle = |v: f64| if layout.angle_unit == AngleUnit::Deg { v.to_radians() } else { v };
    for (k, raw) in text.lines().enumerate().skip(layout.header_lines) {
        let line_no = k + 1;
        let line = raw.trim();
        if line.is_empty() {
            continue;
        }
        let fields: Vec<&str> = match delimiter {
            Some(d) => line.split(d).map(str::trim).collect(),
            None => line.split_whitespace().collect(),
        };
        if fields.len() < needed {
            return Err(line_error(
                path,
                line_no,
                format!(
                    "has {} columns but the layout reads column {}; check \"delimiter\" ({:?}) and \"header_lines\" ({})",
                    fields.len(),
                    needed - 1,
                    layout.delimiter,
                    layout.header_lines
                ),
            ));
        }
        let mut v = [0f64; 7];
        for (j, &c) in idx.iter().enumerate() {
            let name = AsciiColumns::NAMES[j];
            v[j] = match fields[c].parse::<f64>() {
                Ok(x) if x.is_finite() => x,
                Ok(x) => return Err(line_error(path, line_no, format!("{name} (column {c}) is {x}, not a finite number"))),
                Err(_) => {
                    return Err(line_error(
                        path,
                        line_no,
                        format!("{name} (column {c}): cannot parse {:?} as a number; check the column mapping and \"header_lines\"", fields[c]),
                    ))
                }
            };
        }
        let t = match layout.time {
            AsciiTime::UtcUnix => crate::gps_time::gps_from_unix_utc(v[0]),
            _ => v[0],
        };
        if let Some(&prev) = out.times.last() {
            if t <= prev {
                return Err(line_error(
                    path,
                    line_no,
                    format!(
                        "time {} is not after the previous line's time {prev}; times must be strictly increasing",
                        v[0]
                    ),
                ));
            }
        }
        let coordinates = if geographic {
            if v[2].abs() > 90.0 || v[1].abs() > 360.0 {
                return Err(line_error(
                    path,
                    line_no,
                    format!(
                        "longitude {} / latitude {} are not degrees; x is the longitude and y the latitude",
                        v[1], v[2]
                    ),
                ));
            }
            [v[1].to_radians(), v[2].to_radians(), v[3]]
        } else {
            [v[1], v[2], v[3]]
        };
        out.times.push(t);
        out.coordinates.push(coordinates);
        out.attitude.push([angle(v[4]), angle(v[5]), angle(v[6])]);
    }
    if out.len() < 2 {
        return Err(FormatError::file(
            path,
            format!(
                "has {} pose(s) after {} header line(s); a trajectory needs at least 2",
                out.len(),
                layout.header_lines
            ),
        ));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn layout(json: &str) -> AsciiLayout {
        serde_json::from_str(json).unwrap()
    }

    const COLUMNS: &str = r#""columns": {"time": 0, "y": 1, "x": 2, "z": 3, "roll": 4, "pitch": 5, "heading": 6}"#;

    #[test]
    fn whitespace_degrees_and_header() {
        let l = layout(&format!(r#"{{"delimiter": "whitespace", "header_lines": 2, {COLUMNS}}}"#));
        assert!(l.problems().is_empty());
        let text = "# exported\ntime lat lon h r p h\n100.0  52.5\t9.5 80.0 1.0 -2.0 90.0\n\n100.5 52.5 9.5 80.0 1.0 -2.0 91.0\n";
        let s = parse(Path::new("t.txt"), text.as_bytes(), &l, true).unwrap();
        assert_eq!(s.times, vec![100.0, 100.5]);
        assert_eq!(s.coordinates[0], [9.5f64.to_radians(), 52.5f64.to_radians(), 80.0]);
        assert_eq!(s.attitude[1], [1f64.to_radians(), -2f64.to_radians(), 91f64.to_radians()]);
        assert_eq!(s.convention, AttitudeConvention::Navigation);
    }

    #[test]
    fn semicolons_radians_grid_and_utc() {
        let l = layout(&format!(
            r#"{{"delimiter": ";", {COLUMNS}, "angle_unit": "rad", "attitude": "grid", "time": "utc_unix"}}"#
        ));
        let text = "1483228800;5803400;549800;55;0.1;0.2;0.3\n1483228801;5803401;549800;55;0.1;0.2;0.3\n";
        let s = parse(Path::new("t.txt"), text.as_bytes(), &l, false).unwrap();
        assert_eq!(s.times[0], 1_483_228_800.0 - 315_964_800.0 + 18.0);
        assert_eq!(s.coordinates[0], [549_800.0, 5_803_400.0, 55.0]);
        assert_eq!(s.attitude[0], [0.1, 0.2, 0.3]);
        assert_eq!(s.convention, AttitudeConvention::Grid);
    }

    #[test]
    fn bad_lines_name_line_and_column() {
        let l = layout(&format!(r#"{{{COLUMNS}}}"#));
        let err = |text: &str| parse(Path::new("t.txt"), text.as_bytes(), &l, true).unwrap_err().to_string();
        let m = err("1,52,9,80,0,0,0\n2,52,9,80,0,nan,0\n");
        assert!(m.contains("t.txt:2:") && m.contains("pitch (column 5) is NaN"), "{m}");
        let m = err("1,52,9,80,0,0,0\n2,52,9,80,0,0\n");
        assert!(m.contains("t.txt:2:") && m.contains("has 6 columns"), "{m}");
        let m = err("1,52,9,80,0,0,0\n1,52,9,80,0,0,0\n");
        assert!(m.contains("t.txt:2:") && m.contains("strictly increasing"), "{m}");
        let m = err("1,5803400,549800,80,0,0,0\n2,52,9,80,0,0,0\n");
        assert!(m.contains("t.txt:1:") && m.contains("not degrees"), "{m}");
        let m = err("1,52,9,80,0,0,x\n");
        assert!(m.contains("heading (column 6)") && m.contains("\"x\""), "{m}");
        assert!(err("1,52,9,80,0,0,0\n").contains("at least 2"));
        let bad = layout(
            r#"{"delimiter": "::", "columns": {"time": 0, "x": 1, "y": 1, "z": 3, "roll": 4, "pitch": 5, "heading": 6}}"#,
        );
        let p = bad.problems();
        assert!(p.iter().any(|(f, m)| *f == "delimiter" && m.contains("one character")), "{p:?}");
        assert!(p.iter().any(|(f, m)| *f == "columns" && m.contains("x and y both name column 1")), "{p:?}");
    }
}
