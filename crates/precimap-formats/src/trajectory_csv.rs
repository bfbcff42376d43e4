//! Trajectory CSV: header `time,x,y,z,roll,pitch,yaw`, one pose per line, angles in
//! degrees. Writing uses Rust's shortest round-trip float formatting, so reading back what was
//! written gives the same bits.

use crate::atomic::PendingFile;
use crate::FormatError;
use precimap_core::{Trajectory, TrajectoryError, Vec3};
use std::io::Write;
use std::path::Path;

const COLUMNS: [&str; 7] = ["time", "x", "y", "z", "roll", "pitch", "yaw"];
const HEADER: &str = "time,x,y,z,roll,pitch,yaw";

/// Reads a trajectory CSV. Errors name the file and the 1-based line.
pub fn read_trajectory_csv(path: &Path) -> Result<Trajectory, FormatError> {
    let bytes = std::fs::read(path).map_err(|e| FormatError::io(path, "read trajectory", e))?;
    parse(path, &bytes)
}

fn line_error(path: &Path, line: usize, message: impl Into<String>) -> FormatError {
    FormatError::Line { path: path.to_path_buf(), line, message: message.into() }
}

/// Strips a trailing CR and surrounding blanks without allocating.
fn trim(line: &[u8]) -> &[u8] {
    line.trim_ascii()
}

fn parse(path: &Path, bytes: &[u8]) -> Result<Trajectory, FormatError> {
    // Spreadsheet exports often start with a UTF-8 byte-order mark; it is not part of the header.
    let bytes = bytes.strip_prefix(b"\xEF\xBB\xBF").unwrap_or(bytes);
    if let Some(problem) = crate::sniff::binary_problem(bytes, "CSV trajectory") {
        return Err(FormatError::file(path, problem));
    }
    let mut lines = bytes.split(|&b| b == b'\n');
    check_header(path, lines.next().unwrap_or_default())?;

    // ~60 bytes per line in practice; reserving avoids regrowth on hour-long trajectories.
    let estimate = bytes.len() / 48;
    let mut times = Vec::with_capacity(estimate);
    let mut positions = Vec::with_capacity(estimate);
    let mut rpy = Vec::with_capacity(estimate);
    let mut blank_line: Option<usize> = None;
    let mut values = [0f64; 7];

    for (k, raw) in lines.enumerate() {
        let line_no = k + 2;
        let line = trim(raw);
        if line.is_empty() {
            blank_line.get_or_insert(line_no);
            continue;
        }
        if let Some(b) = blank_line {
            return Err(line_error(path, b, "empty line between data lines; remove it"));
        }
        let mut n = 0;
        for field in line.split(|&b| b == b',') {
            if n < 7 {
                values[n] = parse_field(path, line_no, n, field)?;
            }
            n += 1;
        }
        if n != 7 {
            return Err(line_error(
                path,
                line_no,
                format!("expected 7 comma-separated values ({HEADER}), found {n}; fix the line or remove it"),
            ));
        }
        if let Some(&previous) = times.last() {
            if values[0] <= previous {
                return Err(line_error(
                    path,
                    line_no,
                    format!(
                        "time {} is not after the previous line's time {previous}; times must be strictly \
                         increasing: sort the file by time and remove duplicate samples",
                        values[0]
                    ),
                ));
            }
        }
        times.push(values[0]);
        positions.push(Vec3::new(values[1], values[2], values[3]));
        rpy.push([values[4], values[5], values[6]]);
    }
    if times.len() < 2 {
        return Err(FormatError::file(
            path,
            format!("has {} data line(s); a trajectory needs at least 2 samples to interpolate", times.len()),
        ));
    }
    // Everything Trajectory::new checks was checked above with line numbers; this mapping is a
    // safety net should core add checks. No blank lines precede data, so sample i is on line i+2.
    Trajectory::new(times, positions, rpy).map_err(|e| match e {
        TrajectoryError::NotIncreasing { index, .. } | TrajectoryError::NotFinite { index, .. } => {
            line_error(path, index + 2, e.to_string())
        }
        TrajectoryError::TooShort(_) => FormatError::file(path, e.to_string()),
    })
}

fn check_header(path: &Path, first: &[u8]) -> Result<(), FormatError> {
    let line = trim(first);
    let ok = line.split(|&b| b == b',').map(trim).eq(COLUMNS.iter().map(|c| c.as_bytes()));
    if ok {
        return Ok(());
    }
    let shown = String::from_utf8_lossy(&line[..line.len().min(120)]);
    let message = if line.is_empty() {
        format!("missing header; the first line must be exactly `{HEADER}`")
    } else {
        format!("header is `{shown}`; it must be exactly `{HEADER}` (time in GPS seconds, x/y/z in metres, angles in degrees)")
    };
    Err(line_error(path, 1, message))
}

fn parse_field(path: &Path, line: usize, column: usize, field: &[u8]) -> Result<f64, FormatError> {
    let name = COLUMNS[column];
    let text = trim(field);
    if text.is_empty() {
        return Err(line_error(path, line, format!("column {name} is empty; every line needs 7 numbers")));
    }
    let parsed = std::str::from_utf8(text).ok().and_then(|s| s.parse::<f64>().ok());
    let shown = || String::from_utf8_lossy(&text[..text.len().min(40)]).into_owned();
    match parsed {
        Some(v) if v.is_finite() => Ok(v),
        Some(_) => Err(line_error(
            path,
            line,
            format!("column {name}: {} is not a finite number; replace it with a real value or drop the line", shown()),
        )),
        None => Err(line_error(
            path,
            line,
            format!("column {name}: cannot parse {:?} as a number (use a decimal point, no units)", shown()),
        )),
    }
}

/// Writes a trajectory CSV that [`read_trajectory_csv`] reads back bit-exactly. The samples must be
/// a valid trajectory (equal lengths, finite, strictly increasing times, at least 2), so that what
/// is written can always be read. The file appears atomically.
pub fn write_trajectory_csv(
    path: &Path,
    times: &[f64],
    positions: &[Vec3],
    rpy_deg: &[[f64; 3]],
) -> Result<(), FormatError> {
    let n = times.len();
    if positions.len() != n || rpy_deg.len() != n {
        return Err(FormatError::file(
            path,
            format!(
                "cannot write: {n} times, {} positions and {} attitudes; pass one of each per sample",
                positions.len(),
                rpy_deg.len()
            ),
        ));
    }
    if n < 2 {
        return Err(FormatError::file(path, format!("cannot write {n} sample(s); a trajectory needs at least 2")));
    }
    for i in 0..n {
        let p = &positions[i];
        let all = [times[i], p.x, p.y, p.z, rpy_deg[i][0], rpy_deg[i][1], rpy_deg[i][2]];
        if let Some(k) = all.iter().position(|v| !v.is_finite()) {
            return Err(FormatError::file(
                path,
                format!("cannot write sample {i}: {} is {}, not a finite number", COLUMNS[k], all[k]),
            ));
        }
        if i > 0 && times[i] <= times[i - 1] {
            return Err(FormatError::file(
                path,
                format!(
                    "cannot write sample {i}: time {} is not after the previous time {}; times must be strictly increasing",
                    times[i],
                    times[i - 1]
                ),
            ));
        }
    }

    let (pending, file) = PendingFile::create(path)?;
    let mut w = std::io::BufWriter::with_capacity(1 << 20, file);
    let io = |e| FormatError::io(path, "write trajectory", e);
    writeln!(w, "{HEADER}").map_err(io)?;
    for i in 0..n {
        let (p, a) = (&positions[i], &rpy_deg[i]);
        // `{}` on f64 is the shortest text that parses back to the same bits.
        writeln!(w, "{},{},{},{},{},{},{}", times[i], p.x, p.y, p.z, a[0], a[1], a[2]).map_err(io)?;
    }
    w.into_inner().map_err(|e| io(e.into_error()))?;
    pending.commit()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn write_text(dir: &Path, name: &str, text: &str) -> std::path::PathBuf {
        let p = dir.join(name);
        std::fs::write(&p, text).unwrap();
        p
    }

    fn err_of(text: &str) -> (String, FormatError) {
        let dir = tempfile::tempdir().unwrap();
        let p = write_text(dir.path(), "traj.csv", text);
        let e = read_trajectory_csv(&p).unwrap_err();
        (e.to_string(), e)
    }

    #[test]
    fn round_trip_is_bit_exact() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("t.csv");
        // Awkward values: thirds, tiny and huge magnitudes, negative zero, subnormal.
        let times: Vec<f64> = (0..500).map(|i| 345_600.123_456_789 + i as f64 / 3.0).collect();
        let positions: Vec<Vec3> = (0..500)
            .map(|i| {
                Vec3::new(549_800.0 + (i as f64).sqrt() / 7.0, 5_803_400.0 - i as f64 * 0.1, -0.0 + 1e-300 * i as f64)
            })
            .collect();
        let rpy: Vec<[f64; 3]> = (0..500)
            .map(|i| [0.1 * i as f64 / 3.0, -(i as f64).ln_1p(), 179.999_999_999_9 - i as f64 * 1e-7])
            .collect();
        let mut positions = positions;
        positions[3].z = -0.0;
        positions[4].z = f64::MIN_POSITIVE / 4.0;
        write_trajectory_csv(&p, &times, &positions, &rpy).unwrap();
        let t = read_trajectory_csv(&p).unwrap();
        assert_eq!(t.len(), 500);
        for i in 0..500 {
            assert_eq!(t.times()[i].to_bits(), times[i].to_bits());
            for k in 0..3 {
                assert_eq!(t.positions()[i][k].to_bits(), positions[i][k].to_bits(), "sample {i} axis {k}");
                assert_eq!(t.rpy_deg()[i][k].to_bits(), rpy[i][k].to_bits());
            }
        }
        // No temporary left behind.
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    #[test]
    fn tolerates_whitespace_crlf_bom_and_trailing_blank_lines() {
        let dir = tempfile::tempdir().unwrap();
        let p = write_text(
            dir.path(),
            "t.csv",
            "\u{feff} time, x,y,z,roll,pitch,yaw \r\n0,1,2,3,4,5,6\r\n1, 1 ,2,3,4,5,6\r\n\r\n\n",
        );
        let t = read_trajectory_csv(&p).unwrap();
        assert_eq!(t.times(), &[0.0, 1.0]);
    }

    #[test]
    fn wrong_header_shows_expected() {
        let (msg, e) = err_of("t,x,y,z,r,p,h\n0,1,2,3,4,5,6\n1,1,2,3,4,5,6\n");
        assert!(matches!(e, FormatError::Line { line: 1, .. }), "{e:?}");
        assert!(msg.contains("traj.csv:1:") && msg.contains("time,x,y,z,roll,pitch,yaw"), "{msg}");
        let (msg, _) = err_of("");
        assert!(msg.contains("traj.csv:1:") && msg.contains("missing header"), "{msg}");
        // A data line where the header should be.
        let (msg, _) = err_of("0,1,2,3,4,5,6\n1,1,2,3,4,5,6\n");
        assert!(msg.contains("traj.csv:1:") && msg.contains("must be exactly"), "{msg}");
    }

    #[test]
    fn wrong_column_count_names_line() {
        let (msg, e) = err_of("time,x,y,z,roll,pitch,yaw\n0,1,2,3,4,5,6\n1,1,2,3,4,5\n");
        assert!(matches!(e, FormatError::Line { line: 3, .. }), "{e:?}");
        assert!(msg.contains("traj.csv:3:") && msg.contains("found 6"), "{msg}");
        let (msg, _) = err_of("time,x,y,z,roll,pitch,yaw\n0,1,2,3,4,5,6,7\n1,1,2,3,4,5,6\n");
        assert!(msg.contains("traj.csv:2:") && msg.contains("found 8"), "{msg}");
    }

    #[test]
    fn unparsable_number_shows_text() {
        let (msg, e) = err_of("time,x,y,z,roll,pitch,yaw\n0,1,2,3,4,5,6\n1,1,2,3,4,5,6\n2,1,2m,3,4,5,6\n");
        assert!(matches!(e, FormatError::Line { line: 4, .. }), "{e:?}");
        assert!(msg.contains("traj.csv:4:") && msg.contains("column y") && msg.contains("\"2m\""), "{msg}");
        let (msg, _) = err_of("time,x,y,z,roll,pitch,yaw\n0,1,,3,4,5,6\n1,1,2,3,4,5,6\n");
        assert!(msg.contains("traj.csv:2:") && msg.contains("column y is empty"), "{msg}");
    }

    #[test]
    fn non_finite_names_column_and_line() {
        for bad in ["NaN", "inf", "-infinity"] {
            let (msg, e) = err_of(&format!("time,x,y,z,roll,pitch,yaw\n0,1,2,3,4,5,6\n1,1,2,3,4,{bad},6\n"));
            assert!(matches!(e, FormatError::Line { line: 3, .. }), "{e:?}");
            assert!(msg.contains("column pitch") && msg.contains("not a finite number"), "{msg}");
        }
    }

    #[test]
    fn times_not_increasing_show_both_times() {
        let (msg, e) = err_of("time,x,y,z,roll,pitch,yaw\n10.5,1,2,3,4,5,6\n10.25,1,2,3,4,5,6\n");
        assert!(matches!(e, FormatError::Line { line: 3, .. }), "{e:?}");
        assert!(msg.contains("10.25") && msg.contains("10.5") && msg.contains("strictly increasing"), "{msg}");
        let (msg, _) = err_of("time,x,y,z,roll,pitch,yaw\n1,1,2,3,4,5,6\n1,1,2,3,4,5,6\n");
        assert!(msg.contains("traj.csv:3:"), "{msg}");
    }

    #[test]
    fn fewer_than_two_samples() {
        let (msg, e) = err_of("time,x,y,z,roll,pitch,yaw\n0,1,2,3,4,5,6\n\n");
        assert!(matches!(e, FormatError::File { .. }), "{e:?}");
        assert!(msg.contains("traj.csv") && msg.contains("at least 2"), "{msg}");
    }

    #[test]
    fn blank_line_in_the_middle() {
        let (msg, _) = err_of("time,x,y,z,roll,pitch,yaw\n0,1,2,3,4,5,6\n\n1,1,2,3,4,5,6\n");
        assert!(msg.contains("traj.csv:3:") && msg.contains("empty line"), "{msg}");
    }

    #[test]
    fn missing_file_names_it() {
        let dir = tempfile::tempdir().unwrap();
        let e = read_trajectory_csv(&dir.path().join("nope.csv")).unwrap_err();
        assert!(matches!(e, FormatError::Io { .. }) && e.to_string().contains("nope.csv"), "{e}");
    }

    #[test]
    fn writer_rejects_what_the_reader_would_reject() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("w.csv");
        let pos = [Vec3::zeros(); 2];
        assert!(write_trajectory_csv(&p, &[0.0, 1.0], &pos[..1], &[[0.0; 3]; 2]).is_err());
        assert!(write_trajectory_csv(&p, &[1.0, 1.0], &pos, &[[0.0; 3]; 2]).is_err());
        let e = write_trajectory_csv(&p, &[0.0, 1.0], &pos, &[[0.0; 3], [0.0, f64::NAN, 0.0]]).unwrap_err();
        assert!(e.to_string().contains("pitch"), "{e}");
        assert!(!p.exists());
    }

    /// Parses an hour of 200 Hz (720k lines). Run with `--ignored --nocapture` in release mode.
    #[test]
    #[ignore]
    fn throughput_720k_lines() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("hour.csv");
        let n = 720_000;
        let times: Vec<f64> = (0..n).map(|i| 345_600.0 + i as f64 * 0.005).collect();
        let pos: Vec<Vec3> = (0..n)
            .map(|i| Vec3::new(549_800.0 + i as f64 * 0.0512, 5_803_400.0 + (i as f64 * 1e-3).sin(), 54.3))
            .collect();
        let rpy: Vec<[f64; 3]> = (0..n).map(|i| [0.01 * (i as f64).cos(), -0.2, (i as f64 * 1e-4) % 180.0]).collect();
        let t0 = std::time::Instant::now();
        write_trajectory_csv(&p, &times, &pos, &rpy).unwrap();
        let w = t0.elapsed();
        let t0 = std::time::Instant::now();
        let t = read_trajectory_csv(&p).unwrap();
        let r = t0.elapsed();
        assert_eq!(t.len(), n);
        eprintln!(
            "trajectory CSV, {n} lines, {} MB: write {:.3} s, read {:.3} s ({:.2} M lines/s)",
            std::fs::metadata(&p).unwrap().len() / 1_000_000,
            w.as_secs_f64(),
            r.as_secs_f64(),
            n as f64 / r.as_secs_f64() / 1e6
        );
    }
}
