//! The precision `precimap run` states (the posterior standard deviations of its corrections
//! tables, `OUT/corrections/{trajectory}.csv`) held against the errors the simulator's truth
//! shows: how far a user can trust the stated figures.

use serde::Serialize;
use std::path::{Path, PathBuf};

/// Three values per component of the trajectory's travel frame (the position's).
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct FrameValues {
    pub along_track: f64,
    pub across_track: f64,
    pub vertical: f64,
}

impl FrameValues {
    fn new(v: [f64; 3]) -> Self {
        Self { along_track: v[0], across_track: v[1], vertical: v[2] }
    }

    pub fn components(&self) -> [f64; 3] {
        [self.along_track, self.across_track, self.vertical]
    }
}

/// Three values per axis of the vehicle (the attitude's).
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct AxisValues {
    pub roll: f64,
    pub pitch: f64,
    pub heading: f64,
}

impl AxisValues {
    fn new(v: [f64; 3]) -> Self {
        Self { roll: v[0], pitch: v[1], heading: v[2] }
    }

    pub fn components(&self) -> [f64; 3] {
        [self.roll, self.pitch, self.heading]
    }
}

/// The stated precision of the result's trajectories and the actual error over it.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct StatedPrecision {
    /// Estimated anchors with a standard deviation, over all trajectories.
    pub anchors: u64,
    /// RMS over those anchors of the stated standard deviation of the position correction.
    pub position_sigma_rms_m: FrameValues,
    /// The same for the attitude correction, per axis of the vehicle.
    pub attitude_sigma_rms_deg: AxisValues,
    /// `trajectory_error_without_datum_rms_m` (after) over the stated σ: 1 where the stated
    /// precision is honest, above 1 where it promises more than the result holds.
    pub position_error_over_sigma: FrameValues,
    /// `trajectory_attitude_error_without_mean_rms_deg` (after) over the stated σ.
    pub attitude_error_over_sigma: AxisValues,
}

/// Sums of squared standard deviations read from corrections tables.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SigmaSums {
    pub anchors: u64,
    pub position: [f64; 3],
    pub attitude: [f64; 3],
}

impl SigmaSums {
    /// Held against the actual errors (position m, attitude degrees, per component); `None`
    /// without an anchor.
    pub fn stated(&self, position_error_m: [f64; 3], attitude_error_deg: [f64; 3]) -> Option<StatedPrecision> {
        if self.anchors == 0 {
            return None;
        }
        let n = self.anchors as f64;
        let position: [f64; 3] = self.position.map(|s| (s / n).sqrt());
        let attitude: [f64; 3] = self.attitude.map(|s| (s / n).sqrt());
        let over = |e: [f64; 3], s: [f64; 3]| std::array::from_fn(|k| e[k] / s[k]);
        Some(StatedPrecision {
            anchors: self.anchors,
            position_sigma_rms_m: FrameValues::new(position),
            attitude_sigma_rms_deg: AxisValues::new(attitude),
            position_error_over_sigma: FrameValues::new(over(position_error_m, position)),
            attitude_error_over_sigma: AxisValues::new(over(attitude_error_deg, attitude)),
        })
    }
}

#[derive(Debug, thiserror::Error, PartialEq)]
#[error("{}, line {line}: {message}; the corrections table is damaged: write it again with `precimap run`", path.display())]
pub struct TableError {
    pub path: PathBuf,
    pub line: usize,
    pub message: String,
}

/// The columns read, by their header names.
const SIGMA_COLUMNS: [&str; 6] =
    ["sigma_along_m", "sigma_across_m", "sigma_vertical_m", "sigma_roll_deg", "sigma_pitch_deg", "sigma_heading_deg"];

/// Adds the standard deviations of a corrections table's estimated anchors (`text`, read from
/// `path`, which errors name) to `sums`. Anchors continued past the estimated range
/// (`estimated` 0) and rows without a standard deviation are skipped.
pub fn add_table(sums: &mut SigmaSums, text: &str, path: &Path) -> Result<(), TableError> {
    let error = |line: usize, message: String| TableError { path: path.to_path_buf(), line, message };
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().ok_or_else(|| error(1, "the file is empty".into()))?.split(',').collect();
    let column = |name: &str| {
        header.iter().position(|h| h.trim() == name).ok_or_else(|| error(1, format!("no column {name:?}")))
    };
    let sigma: Vec<usize> = SIGMA_COLUMNS.iter().map(|c| column(c)).collect::<Result<_, _>>()?;
    let estimated = column("estimated")?;
    for (k, line) in lines.enumerate() {
        let number = k + 2;
        if line.trim().is_empty() {
            continue;
        }
        let fields: Vec<&str> = line.split(',').collect();
        if fields.len() != header.len() {
            return Err(error(number, format!("{} fields where the header has {}", fields.len(), header.len())));
        }
        if fields[estimated].trim() != "1" || fields[sigma[0]].trim().is_empty() {
            continue;
        }
        let mut values = [0.0; 6];
        for (v, &c) in values.iter_mut().zip(&sigma) {
            *v =
                fields[c].trim().parse::<f64>().ok().filter(|v| v.is_finite() && *v >= 0.0).ok_or_else(|| {
                    error(number, format!("{} is {:?}, not a standard deviation", header[c], fields[c]))
                })?;
        }
        sums.anchors += 1;
        for a in 0..3 {
            sums.position[a] += values[a] * values[a];
            sums.attitude[a] += values[3 + a] * values[3 + a];
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    const HEADER: &str = "anchor,arc_m,time,x,y,z,along_m,across_m,vertical_m,roll_deg,pitch_deg,heading_deg,\
        sigma_along_m,sigma_across_m,sigma_vertical_m,sigma_roll_deg,sigma_pitch_deg,sigma_heading_deg,estimated";

    #[test]
    fn stated_sigma_is_the_rms_over_estimated_anchors() {
        let text = format!(
            "{HEADER}\n\
             0,0.0,1.0,0,0,0,0,0,0,0,0,0,,,,,,,0\n\
             1,0.5,1.1,0,0,0,0,0,0,0,0,0,0.003,0.001,0.002,0.004,0.002,0.006,1\n\
             2,1.0,1.2,0,0,0,0,0,0,0,0,0,0.004,0.001,0.002,0.004,0.002,0.008,1\n\
             3,1.5,1.3,0,0,0,0,0,0,0,0,0,0.9,0.9,0.9,0.9,0.9,0.9,0\n"
        );
        let mut sums = SigmaSums::default();
        add_table(&mut sums, &text, Path::new("c.csv")).unwrap();
        assert_eq!(sums.anchors, 2);
        // Actual errors twice the stated σ along the track, equal across.
        let stated = sums.stated([0.0025f64.hypot(0.0025) * 2.0, 0.001, 0.001], [0.004, 0.002, 0.007]).unwrap();
        let sigma = stated.position_sigma_rms_m.components();
        assert!((sigma[0] - (12.5e-6f64).sqrt()).abs() < 1e-12, "{sigma:?}");
        assert!((sigma[1] - 0.001).abs() < 1e-12 && (sigma[2] - 0.002).abs() < 1e-12);
        let over = stated.position_error_over_sigma.components();
        assert!((over[0] - 2.0).abs() < 1e-9 && (over[1] - 1.0).abs() < 1e-9 && (over[2] - 0.5).abs() < 1e-9);
        let attitude = stated.attitude_sigma_rms_deg.components();
        assert!((attitude[2] - (50e-6f64).sqrt()).abs() < 1e-12, "{attitude:?}");
        assert!((stated.attitude_error_over_sigma.roll - 1.0).abs() < 1e-9);
        assert!(SigmaSums::default().stated([1.0; 3], [1.0; 3]).is_none());
    }

    #[test]
    fn a_damaged_table_is_named_with_its_line() {
        let mut sums = SigmaSums::default();
        let short = format!("{HEADER}\n1,0.5,1.1,0,0,0\n");
        let e = add_table(&mut sums, &short, Path::new("out/corrections/v01.csv")).unwrap_err();
        assert_eq!(e.line, 2);
        assert!(e.to_string().contains("out/corrections/v01.csv, line 2: 6 fields"), "{e}");
        let negative = format!("{HEADER}\n1,0.5,1.1,0,0,0,0,0,0,0,0,0,-0.003,0.001,0.002,0.004,0.002,0.006,1\n");
        let e = add_table(&mut sums, &negative, Path::new("c.csv")).unwrap_err();
        assert!(e.message.contains("sigma_along_m is \"-0.003\""), "{e}");
        let e = add_table(&mut sums, "anchor,estimated\n", Path::new("c.csv")).unwrap_err();
        assert!(e.message.contains("no column \"sigma_along_m\""), "{e}");
        assert_eq!(sums, SigmaSums::default());
    }
}
