//! A manifest's trajectory in any of its formats, read into the processing frame with its times
//! on one GPS time scale.

use crate::crs::{Crs, LocalFrame};
use crate::gps_time::{self, TimeConvention};
use crate::manifest::{TrajectoryFormat, TrajectoryRef};
use crate::navigation::{to_trajectory, AttitudeConvention, NavSamples};
use crate::sbet::{read_sbet, read_smrmsg, NavAccuracy};
use crate::trajectory_ascii::{read_trajectory_ascii, AsciiTime};
use crate::{read_trajectory_csv, FormatError};
use precimap_core::Trajectory;
use std::path::Path;

/// The geographic CRS an SBET is read in when the manifest names none (WGS 84, 3D).
pub const SBET_DEFAULT_CRS: u32 = 4979;

/// A trajectory ready for estimation.
#[derive(Clone, Debug)]
pub struct LoadedTrajectory {
    pub trajectory: Trajectory,
    /// What its times count; `None` for a trajectory CSV without a CRS, whose times are taken to
    /// be on the strips' own scale.
    pub time: Option<TimeConvention>,
    /// The GPS week of its times (given or derived), when known.
    pub week: Option<u32>,
    /// The SBET's per-epoch accuracy (SMRMSG), when the manifest names one.
    pub accuracy: Option<NavAccuracy>,
}

fn crs_of(path: &Path, code: u32) -> Result<Crs, FormatError> {
    Crs::from_epsg(code)
        .map_err(|e| FormatError::file(path, format!("{e}; fix the trajectory's \"crs\" in the manifest")))
}

/// Reads the trajectory `spec` from `path` (and its accuracy file from `accuracy_path`) into the
/// processing frame `frame`. Week seconds become adjusted standard GPS time when `gps_week` is
/// given.
pub fn load_trajectory(
    path: &Path,
    spec: &TrajectoryRef,
    accuracy_path: Option<&Path>,
    frame: Option<&LocalFrame>,
    gps_week: Option<u32>,
) -> Result<LoadedTrajectory, FormatError> {
    let (samples, source, time) = match spec.format {
        TrajectoryFormat::Csv => {
            let csv = read_trajectory_csv(path)?;
            let Some(code) = spec.crs else {
                return Ok(LoadedTrajectory { trajectory: csv, time: None, week: None, accuracy: None });
            };
            let mut s = NavSamples::with_capacity(csv.len(), AttitudeConvention::Grid);
            s.times = csv.times().to_vec();
            s.coordinates = csv.positions().iter().map(|p| [p.x, p.y, p.z]).collect();
            s.attitude = csv.rpy_deg().iter().map(|a| a.map(f64::to_radians)).collect();
            (s, Some(crs_of(path, code)?), None)
        }
        TrajectoryFormat::Sbet => {
            let s = read_sbet(path)?;
            (s, Some(crs_of(path, spec.crs.unwrap_or(SBET_DEFAULT_CRS))?), Some(TimeConvention::WeekSeconds))
        }
        TrajectoryFormat::Ascii => {
            let layout = spec.ascii.as_ref().ok_or_else(|| {
                FormatError::file(path, "an ASCII trajectory needs its \"ascii\" layout in the manifest")
            })?;
            let source = match (spec.crs, frame) {
                (Some(code), _) => Some(crs_of(path, code)?),
                (None, Some(f)) => Some(f.crs().clone()),
                (None, None) => None,
            };
            let geographic = source.as_ref().is_some_and(Crs::is_geographic);
            let mut s = read_trajectory_ascii(path, layout, geographic)?;
            let time = match layout.time {
                AsciiTime::WeekSeconds => Some(TimeConvention::WeekSeconds),
                AsciiTime::AdjustedStandard => Some(TimeConvention::AdjustedStandard),
                AsciiTime::GpsSeconds | AsciiTime::UtcUnix => {
                    s.times.iter_mut().for_each(|t| *t -= gps_time::ADJUSTED_STANDARD_OFFSET_S);
                    Some(TimeConvention::AdjustedStandard)
                }
            };
            (s, source, time)
        }
    };
    let offset = match (time, gps_week) {
        (Some(TimeConvention::WeekSeconds), Some(w)) => {
            gps_time::offset(TimeConvention::WeekSeconds, TimeConvention::AdjustedStandard, w)
        }
        _ => 0.0,
    };
    let trajectory = to_trajectory(path, &samples, source.as_ref(), frame, offset)?;
    let clock = trajectory_clock(spec, gps_week, trajectory.times()[0]);
    let accuracy = accuracy_path.map(|p| load_accuracy(p, spec, gps_week)).transpose()?;
    Ok(LoadedTrajectory { trajectory, time: clock.time, week: clock.week, accuracy })
}

/// Reads the accuracy (SMRMSG) file of the trajectory `spec` with its times on the scale
/// [`load_trajectory`] puts the trajectory's on: it counts time as its SBET does.
pub fn load_accuracy(path: &Path, spec: &TrajectoryRef, gps_week: Option<u32>) -> Result<NavAccuracy, FormatError> {
    let mut accuracy = read_smrmsg(path)?;
    if let (TrajectoryFormat::Sbet, Some(w)) = (spec.format, gps_week) {
        let offset = gps_time::offset(TimeConvention::WeekSeconds, TimeConvention::AdjustedStandard, w);
        accuracy.times.iter_mut().for_each(|t| *t += offset);
    }
    Ok(accuracy)
}

/// The time scale [`load_trajectory`] puts `spec`'s times on, given the loaded trajectory's first
/// time: week seconds become adjusted standard GPS time when `gps_week` is given.
pub fn trajectory_clock(spec: &TrajectoryRef, gps_week: Option<u32>, first_time: f64) -> LoadedTrajectoryClock {
    let file = match spec.format {
        TrajectoryFormat::Csv => None,
        TrajectoryFormat::Sbet => Some(TimeConvention::WeekSeconds),
        TrajectoryFormat::Ascii => match spec.ascii.as_ref().map(|l| l.time) {
            Some(AsciiTime::WeekSeconds) | None => Some(TimeConvention::WeekSeconds),
            Some(_) => Some(TimeConvention::AdjustedStandard),
        },
    };
    match (file, gps_week) {
        (Some(TimeConvention::WeekSeconds), Some(w)) => {
            LoadedTrajectoryClock { time: Some(TimeConvention::AdjustedStandard), week: Some(w) }
        }
        (Some(TimeConvention::AdjustedStandard), _) => {
            LoadedTrajectoryClock { time: file, week: gps_week.or_else(|| gps_time::week_of_adjusted(first_time)) }
        }
        _ => LoadedTrajectoryClock { time: file, week: None },
    }
}

/// The processing frame's view of a strip's GPS times: the seconds to add to put them on its
/// trajectory's scale, and the GPS week involved (given, or derived from whichever side has
/// adjusted standard times).
pub fn strip_clock(
    strip: TimeConvention,
    strip_first_time: f64,
    trajectory: &LoadedTrajectoryClock,
) -> (f64, Option<u32>) {
    match trajectory.time {
        None => (0.0, trajectory.week),
        Some(t) if t == strip => (0.0, trajectory.week.or_else(|| week_of(strip, strip_first_time))),
        Some(TimeConvention::WeekSeconds) => match week_of(strip, strip_first_time) {
            Some(w) => (gps_time::offset(strip, TimeConvention::WeekSeconds, w), Some(w)),
            None => (0.0, None),
        },
        Some(TimeConvention::AdjustedStandard) => match trajectory.week {
            Some(w) => (gps_time::offset(strip, TimeConvention::AdjustedStandard, w), Some(w)),
            None => (0.0, None),
        },
    }
}

fn week_of(convention: TimeConvention, t: f64) -> Option<u32> {
    (convention == TimeConvention::AdjustedStandard).then(|| gps_time::week_of_adjusted(t)).flatten()
}

/// What [`strip_clock`] needs of a trajectory (small, so task inputs can carry it).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct LoadedTrajectoryClock {
    pub time: Option<TimeConvention>,
    pub week: Option<u32>,
}

impl LoadedTrajectory {
    pub fn clock(&self) -> LoadedTrajectoryClock {
        LoadedTrajectoryClock { time: self.time, week: self.week }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gps_time::TimeConvention::{AdjustedStandard, WeekSeconds};

    #[test]
    fn strip_clocks_bridge_the_conventions() {
        let week = 2311u32;
        let start = f64::from(week) * 604_800.0 - 1e9;
        let adjusted = start + 345_600.0;
        let csv = LoadedTrajectoryClock::default();
        assert_eq!(strip_clock(AdjustedStandard, adjusted, &csv), (0.0, None));
        // SBET in week seconds, LAS in adjusted standard time: the week comes from the LAS.
        let sbet = LoadedTrajectoryClock { time: Some(WeekSeconds), week: None };
        let (offset, w) = strip_clock(AdjustedStandard, adjusted, &sbet);
        assert_eq!((adjusted + offset, w), (345_600.0, Some(week)));
        // SBET with the manifest's week (adjusted standard), LAS in week seconds.
        let given = LoadedTrajectoryClock { time: Some(AdjustedStandard), week: Some(week) };
        let (offset, w) = strip_clock(WeekSeconds, 345_600.0, &given);
        assert_eq!((345_600.0 + offset, w), (adjusted, Some(week)));
        assert_eq!(strip_clock(AdjustedStandard, adjusted, &given), (0.0, Some(week)));
        // Both in week seconds: nothing to bridge, the week stays unknown.
        assert_eq!(strip_clock(WeekSeconds, 345_600.0, &sbet), (0.0, None));
    }
}
