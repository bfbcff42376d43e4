//! Applanix SBET trajectories and their SMRMSG accuracy files.
//!
//! An SBET is a headerless sequence of 136-byte records of 17 little-endian f64: GPS week seconds,
//! latitude, longitude (radians), ellipsoidal height (m), velocities x/y/z in the wander frame
//! (m/s), roll, pitch, platform heading, wander angle (radians), accelerations x/y/z (m/s²) and
//! angular rates x/y/z (rad/s). The true heading is the platform heading minus the wander angle.
//! Roll, pitch and heading are the aerospace `Rz(heading)·Ry(pitch)·Rx(roll)` from the body frame
//! (x forward, y right, z down) to the local-level north-east-down frame.
//!
//! An SMRMSG file has the same shape with 10 f64 per record: time, north/east/down position RMS
//! (m), north/east/down velocity RMS (m/s), roll/pitch/heading RMS (arc minutes).

use crate::navigation::{AttitudeConvention, NavSamples};
use crate::FormatError;
use std::path::Path;

pub const SBET_FIELDS: [&str; 17] = [
    "time",
    "latitude",
    "longitude",
    "altitude",
    "x velocity",
    "y velocity",
    "z velocity",
    "roll",
    "pitch",
    "platform heading",
    "wander angle",
    "x acceleration",
    "y acceleration",
    "z acceleration",
    "x angular rate",
    "y angular rate",
    "z angular rate",
];
const SBET_RECORD: usize = 17 * 8;
const SMRMSG_FIELDS: [&str; 10] = [
    "time",
    "north σ",
    "east σ",
    "down σ",
    "north velocity σ",
    "east velocity σ",
    "down velocity σ",
    "roll σ",
    "pitch σ",
    "heading σ",
];
const SMRMSG_RECORD: usize = 10 * 8;
/// Plausible position σ of an SMRMSG record (lowest, highest, unit): below a millimetre no
/// GNSS/IMU solution is that good, above 10 km it is no solution.
const SIGMA_POSITION_M: (f64, f64, &str) = (1e-3, 1e4, "m");
/// Plausible attitude σ (0.6 arc seconds to 180°).
const SIGMA_ATTITUDE_ARCMIN: (f64, f64, &str) = (0.01, 10_800.0, "arc minutes");

/// Splits a headerless binary file into records of `n` f64, checking length, finiteness and
/// increasing times (field 0). Errors name the record (0-based) and the field.
fn records(path: &Path, bytes: &[u8], names: &[&str], what: &str) -> Result<Vec<Vec<f64>>, FormatError> {
    let size = names.len() * 8;
    if !bytes.len().is_multiple_of(size) {
        let whole = bytes.len() / size;
        return Err(FormatError::file(
            path,
            format!(
                "truncated {what}: {} bytes is not a whole number of {size}-byte records (record {whole} is cut after \
                 {} bytes); the file was cut off in transfer or is not an {what}: copy or export it again",
                bytes.len(),
                bytes.len() % size
            ),
        ));
    }
    let n = bytes.len() / size;
    if n < 2 {
        return Err(FormatError::file(path, format!("has {n} record(s); a trajectory needs at least 2")));
    }
    let mut out = Vec::with_capacity(n);
    for (i, rec) in bytes.chunks_exact(size).enumerate() {
        let values: Vec<f64> =
            rec.chunks_exact(8).map(|b| f64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]])).collect();
        if let Some(k) = values.iter().position(|v| !v.is_finite()) {
            return Err(FormatError::file(
                path,
                format!(
                    "record {i} (byte {}): {} is {}, not a finite number; {what} is damaged",
                    i * size + k * 8,
                    names[k],
                    values[k]
                ),
            ));
        }
        if let Some(prev) = out.last().map(|p: &Vec<f64>| p[0]) {
            if values[0] <= prev {
                return Err(FormatError::file(
                    path,
                    format!(
                        "record {i}: time {} is not after the previous record's time {prev}; times must be strictly \
                         increasing (a file that spans a GPS week rollover must be split at the rollover)",
                        values[0]
                    ),
                ));
            }
        }
        out.push(values);
    }
    Ok(out)
}

/// Reads an SBET file: positions as (longitude, latitude in radians, ellipsoidal height), attitude
/// as (roll, pitch, true heading) in radians, times in GPS week seconds.
pub fn read_sbet(path: &Path) -> Result<NavSamples, FormatError> {
    let bytes = std::fs::read(path).map_err(|e| FormatError::io(path, "read SBET trajectory", e))?;
    parse_sbet(path, &bytes)
}

pub(crate) fn parse_sbet(path: &Path, bytes: &[u8]) -> Result<NavSamples, FormatError> {
    debug_assert_eq!(SBET_RECORD, SBET_FIELDS.len() * 8);
    let recs = records(path, bytes, &SBET_FIELDS, "SBET")?;
    let mut s = NavSamples::with_capacity(recs.len(), AttitudeConvention::Navigation);
    for (i, r) in recs.iter().enumerate() {
        let (lat, lon) = (r[1], r[2]);
        if lat.abs() > std::f64::consts::FRAC_PI_2 || lon.abs() > 2.0 * std::f64::consts::PI {
            return Err(FormatError::file(
                path,
                format!(
                    "record {i}: latitude {lat} / longitude {lon} are not radians; an SBET stores them in radians \
                     (this file may be another format: use \"format\": \"ascii\" for text exports)"
                ),
            ));
        }
        s.times.push(r[0]);
        s.coordinates.push([lon, lat, r[3]]);
        s.attitude.push([r[7], r[8], r[9] - r[10]]);
    }
    Ok(s)
}

/// Writes an SBET file (velocities, accelerations and rates zero). `wander` is the wander angle
/// per sample; the platform heading written is the true heading plus it.
pub fn write_sbet(path: &Path, samples: &NavSamples, wander: &[f64]) -> Result<(), FormatError> {
    if samples.convention != AttitudeConvention::Navigation
        || wander.len() != samples.len()
        || samples.coordinates.len() != samples.len()
        || samples.attitude.len() != samples.len()
    {
        return Err(FormatError::file(
            path,
            "cannot write SBET: needs one position, navigation attitude and wander angle per time",
        ));
    }
    let mut bytes = Vec::with_capacity(samples.len() * SBET_RECORD);
    for i in 0..samples.len() {
        let [lon, lat, h] = samples.coordinates[i];
        let [roll, pitch, heading] = samples.attitude[i];
        let mut rec = [0f64; 17];
        rec[..4].copy_from_slice(&[samples.times[i], lat, lon, h]);
        rec[7..11].copy_from_slice(&[roll, pitch, heading + wander[i], wander[i]]);
        for v in rec {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
    }
    crate::atomic::write_bytes(path, &bytes)
}

/// Per-epoch accuracy of a trajectory (an SMRMSG file).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct NavAccuracy {
    pub times: Vec<f64>,
    /// North, east, down position σ, metres.
    pub position_sigma_m: Vec<[f64; 3]>,
    /// Roll, pitch, heading σ, degrees.
    pub attitude_sigma_deg: Vec<[f64; 3]>,
}

impl NavAccuracy {
    /// Position σ (north, east, down, m) and attitude σ (roll, pitch, heading, degrees) at time
    /// `t`, linear between records; `None` when `t` lies more than `tolerance_s` outside them
    /// (held at the end record within it).
    pub fn at(&self, t: f64, tolerance_s: f64) -> Option<([f64; 3], [f64; 3])> {
        let (first, last) = (*self.times.first()?, *self.times.last()?);
        if t < first - tolerance_s || t > last + tolerance_s {
            return None;
        }
        let i = self.times.partition_point(|&x| x <= t);
        if i == 0 {
            return Some((self.position_sigma_m[0], self.attitude_sigma_deg[0]));
        }
        if i == self.times.len() {
            return Some((self.position_sigma_m[i - 1], self.attitude_sigma_deg[i - 1]));
        }
        let lambda = (t - self.times[i - 1]) / (self.times[i] - self.times[i - 1]);
        let lerp = |a: &[f64; 3], b: &[f64; 3]| std::array::from_fn(|k| a[k] + lambda * (b[k] - a[k]));
        Some((
            lerp(&self.position_sigma_m[i - 1], &self.position_sigma_m[i]),
            lerp(&self.attitude_sigma_deg[i - 1], &self.attitude_sigma_deg[i]),
        ))
    }

    /// Medians over the records: the position's RMS σ over its three axes (m), the tilt's RMS
    /// over roll and pitch, and the heading's (degrees).
    pub fn medians(&self) -> [f64; 3] {
        let median = |mut v: Vec<f64>| {
            v.sort_by(f64::total_cmp);
            v.get(v.len() / 2).copied().unwrap_or(0.0)
        };
        let rms = |s: &[f64]| (s.iter().map(|v| v * v).sum::<f64>() / s.len() as f64).sqrt();
        [
            median(self.position_sigma_m.iter().map(|s| rms(s)).collect()),
            median(self.attitude_sigma_deg.iter().map(|s| rms(&s[..2])).collect()),
            median(self.attitude_sigma_deg.iter().map(|s| s[2]).collect()),
        ]
    }

    /// Median and largest horizontal position σ (root of the north and east variances), metres,
    /// and median and largest heading σ, degrees.
    pub fn summary(&self) -> [f64; 4] {
        let stat = |mut v: Vec<f64>| {
            v.sort_by(f64::total_cmp);
            [v[v.len() / 2], v[v.len() - 1]]
        };
        let horizontal = stat(self.position_sigma_m.iter().map(|s| s[0].hypot(s[1])).collect());
        let heading = stat(self.attitude_sigma_deg.iter().map(|s| s[2]).collect());
        [horizontal[0], horizontal[1], heading[0], heading[1]]
    }
}

/// Reads an SMRMSG accuracy file.
pub fn read_smrmsg(path: &Path) -> Result<NavAccuracy, FormatError> {
    let bytes = std::fs::read(path).map_err(|e| FormatError::io(path, "read SMRMSG accuracy file", e))?;
    debug_assert_eq!(SMRMSG_RECORD, SMRMSG_FIELDS.len() * 8);
    let recs = records(path, &bytes, &SMRMSG_FIELDS, "SMRMSG file")?;
    let mut out = NavAccuracy::default();
    for (i, r) in recs.iter().enumerate() {
        if let Some(k) = r[1..].iter().position(|v| *v < 0.0) {
            return Err(FormatError::file(
                path,
                format!("record {i}: {} is negative ({})", SMRMSG_FIELDS[k + 1], r[k + 1]),
            ));
        }
        // Position and attitude σ become the estimator's prior: a zero or implausible value
        // would pin or free an anchor outright.
        for (k, (lowest, highest, unit)) in [(1, SIGMA_POSITION_M), (7, SIGMA_ATTITUDE_ARCMIN)]
            .into_iter()
            .flat_map(|(first, range)| (first..first + 3).map(move |k| (k, range)))
        {
            if !(lowest..=highest).contains(&r[k]) {
                return Err(FormatError::file(
                    path,
                    format!(
                        "record {i} (time {}): {} is {} {unit}, outside the plausible {lowest}–{highest} {unit} of a \
                         GNSS/IMU accuracy; the file is damaged or is not the SMRMSG of this SBET (remove \
                         \"accuracy_uri\" to use the campaign's sigma_prior_* instead)",
                        r[0], SMRMSG_FIELDS[k], r[k]
                    ),
                ));
            }
        }
        out.times.push(r[0]);
        out.position_sigma_m.push([r[1], r[2], r[3]]);
        out.attitude_sigma_deg.push([r[7] / 60.0, r[8] / 60.0, r[9] / 60.0]);
    }
    Ok(out)
}

/// Writes an SMRMSG file (velocity σ zero); attitude σ are given in degrees and stored in arc
/// minutes.
pub fn write_smrmsg(path: &Path, accuracy: &NavAccuracy) -> Result<(), FormatError> {
    let n = accuracy.times.len();
    if accuracy.position_sigma_m.len() != n || accuracy.attitude_sigma_deg.len() != n {
        return Err(FormatError::file(path, "cannot write SMRMSG: needs one position and attitude σ per time"));
    }
    let mut bytes = Vec::with_capacity(n * SMRMSG_RECORD);
    for i in 0..n {
        let [north, east, down] = accuracy.position_sigma_m[i];
        let [roll, pitch, heading] = accuracy.attitude_sigma_deg[i].map(|d| d * 60.0);
        for v in [accuracy.times[i], north, east, down, 0.0, 0.0, 0.0, roll, pitch, heading] {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
    }
    crate::atomic::write_bytes(path, &bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn record(values: [f64; 17]) -> Vec<u8> {
        values.iter().flat_map(|v| v.to_le_bytes()).collect()
    }

    fn sample(t: f64) -> [f64; 17] {
        let mut r = [0.0; 17];
        r[0] = t;
        r[1] = 52.37f64.to_radians();
        r[2] = 9.73f64.to_radians();
        r[3] = 102.5;
        r[7] = 0.01;
        r[8] = -0.02;
        r[9] = 1.0;
        r[10] = 0.25;
        r
    }

    fn err(bytes: &[u8]) -> String {
        parse_sbet(Path::new("p01.sbet"), bytes).unwrap_err().to_string()
    }

    #[test]
    fn reads_records_and_true_heading() {
        let bytes: Vec<u8> = [sample(100.0), sample(100.005)].iter().flat_map(|r| record(*r)).collect();
        let s = parse_sbet(Path::new("p01.sbet"), &bytes).unwrap();
        assert_eq!(s.times, vec![100.0, 100.005]);
        assert_eq!(s.coordinates[1], [9.73f64.to_radians(), 52.37f64.to_radians(), 102.5]);
        assert_eq!(s.attitude[0], [0.01, -0.02, 0.75]);
    }

    #[test]
    fn write_then_read() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("t.sbet");
        let mut s = NavSamples::with_capacity(3, AttitudeConvention::Navigation);
        for i in 0..3 {
            s.times.push(5.0 + i as f64);
            s.coordinates.push([0.17, 0.91, 50.0 + i as f64]);
            s.attitude.push([0.001, 0.002, 6.0]);
        }
        write_sbet(&p, &s, &[0.3, 0.4, -0.2]).unwrap();
        assert_eq!(std::fs::metadata(&p).unwrap().len(), 3 * 136);
        let back = read_sbet(&p).unwrap();
        assert_eq!(back.times, s.times);
        assert_eq!(back.coordinates, s.coordinates);
        for (a, b) in back.attitude.iter().zip(&s.attitude) {
            assert!((a[2] - b[2]).abs() < 1e-14 && a[0] == b[0] && a[1] == b[1]);
        }
    }

    #[test]
    fn truncated_nan_unordered_and_degrees_are_refused() {
        let good: Vec<u8> = [sample(1.0), sample(2.0)].iter().flat_map(|r| record(*r)).collect();
        let m = err(&good[..good.len() - 5]);
        assert!(m.contains("p01.sbet") && m.contains("truncated SBET") && m.contains("record 1 is cut"), "{m}");
        let mut nan = sample(2.0);
        nan[8] = f64::NAN;
        let m = err(&[record(sample(1.0)), record(nan)].concat());
        assert!(m.contains("record 1") && m.contains("pitch is NaN"), "{m}");
        let m = err(&[record(sample(2.0)), record(sample(2.0))].concat());
        assert!(m.contains("record 1: time 2 is not after") && m.contains("strictly increasing"), "{m}");
        let mut degrees = sample(2.0);
        degrees[1] = 52.37;
        let m = err(&[record(sample(1.0)), record(degrees)].concat());
        assert!(m.contains("not radians"), "{m}");
        assert!(err(&record(sample(1.0))).contains("at least 2"));
        assert!(err(&[]).contains("at least 2"));
    }

    #[test]
    fn smrmsg_in_metres_and_degrees() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("smrmsg.out");
        let rec = |t: f64, s: f64| -> Vec<u8> {
            [t, s, s, 2.0 * s, 0.0, 0.0, 0.0, 0.6, 0.6, 1.2].iter().flat_map(|v| v.to_le_bytes()).collect()
        };
        std::fs::write(&p, [rec(1.0, 0.02), rec(2.0, 0.03), rec(3.0, 0.5)].concat()).unwrap();
        let a = read_smrmsg(&p).unwrap();
        assert_eq!(a.attitude_sigma_deg[0], [0.01, 0.01, 0.02]);
        let s = a.summary();
        assert!((s[0] - 0.03 * 2f64.sqrt()).abs() < 1e-12 && (s[1] - 0.5 * 2f64.sqrt()).abs() < 1e-12, "{s:?}");
        std::fs::write(&p, [rec(1.0, 0.02), rec(2.0, -0.03)].concat()).unwrap();
        assert!(read_smrmsg(&p).unwrap_err().to_string().contains("north σ is negative"));
        std::fs::write(&p, &rec(1.0, 0.02)[..40]).unwrap();
        assert!(read_smrmsg(&p).unwrap_err().to_string().contains("truncated SMRMSG"));
    }

    #[test]
    fn zero_and_implausible_sigma_are_refused_with_the_record() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("p01.smrmsg");
        let rec = |t: f64, pos: f64, att_arcmin: f64| -> Vec<u8> {
            [t, pos, pos, pos, 0.0, 0.0, 0.0, att_arcmin, att_arcmin, att_arcmin]
                .iter()
                .flat_map(|v| v.to_le_bytes())
                .collect()
        };
        let cases = [
            (rec(2.0, 0.0, 0.6), "north σ is 0 m"),
            (rec(2.0, 1e-5, 0.6), "north σ is 0.00001 m"),
            (rec(2.0, 0.05, 0.0), "roll σ is 0 arc minutes"),
            (rec(2.0, 2e4, 0.6), "north σ is 20000 m"),
        ];
        for (bad, what) in cases {
            std::fs::write(&p, [rec(1.0, 0.02, 0.6), bad].concat()).unwrap();
            let m = read_smrmsg(&p).unwrap_err().to_string();
            assert!(m.contains("p01.smrmsg") && m.contains("record 1 (time 2)") && m.contains("accuracy_uri"), "{m}");
            assert!(m.contains(what), "{m}");
        }
        let mut nan = rec(2.0, 0.02, 0.6);
        nan[8..16].copy_from_slice(&f64::NAN.to_le_bytes());
        std::fs::write(&p, [rec(1.0, 0.02, 0.6), nan].concat()).unwrap();
        assert!(read_smrmsg(&p).unwrap_err().to_string().contains("record 1 (byte 88): north σ is NaN"));
    }

    #[test]
    fn smrmsg_round_trip_interpolation_and_medians() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.smrmsg");
        let a = NavAccuracy {
            times: vec![10.0, 11.0, 12.0],
            position_sigma_m: vec![[0.02, 0.02, 0.04], [0.04, 0.04, 0.08], [0.03, 0.03, 0.06]],
            attitude_sigma_deg: vec![[0.01, 0.01, 0.03], [0.02, 0.02, 0.05], [0.01, 0.01, 0.04]],
        };
        write_smrmsg(&p, &a).unwrap();
        let back = read_smrmsg(&p).unwrap();
        assert_eq!(back.times, a.times);
        assert_eq!(back.position_sigma_m, a.position_sigma_m);
        for (x, y) in back.attitude_sigma_deg.iter().zip(&a.attitude_sigma_deg) {
            assert!((0..3).all(|k| (x[k] - y[k]).abs() < 1e-15), "{x:?} {y:?}");
        }
        let (pos, att) = a.at(10.5, 0.0).unwrap();
        assert!((pos[0] - 0.03).abs() < 1e-15 && (att[2] - 0.04).abs() < 1e-15, "{pos:?} {att:?}");
        assert_eq!(a.at(12.5, 1.0).unwrap().0, [0.03, 0.03, 0.06]);
        assert_eq!(a.at(9.5, 1.0).unwrap().0, [0.02, 0.02, 0.04]);
        assert!(a.at(13.5, 1.0).is_none() && a.at(8.0, 1.0).is_none());
        let m = a.medians();
        let rms = (0.03f64.powi(2) * 2.0 + 0.06f64.powi(2)) / 3.0;
        assert!((m[0] - rms.sqrt()).abs() < 1e-15 && m[1] == 0.01 && m[2] == 0.04, "{m:?}");
    }
}
