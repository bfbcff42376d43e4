//! Trajectories as navigation systems deliver them, and their conversion into precimap's
//! processing frame ([`crate::crs::LocalFrame`]).
//!
//! Attitude conventions (angles in radians here, body frame of precimap x forward, y left, z up):
//! - [`AttitudeConvention::Navigation`]: roll, pitch and true heading of the navigation body frame
//!   (x forward, y right, z down) in the local-level north-east-down frame at the sample's
//!   position, `R_ned_nav = Rz(heading)·Ry(pitch)·Rx(roll)`; SBET and most INS exports.
//! - [`AttitudeConvention::Grid`]: precimap's own `R = Rz(yaw)·Ry(pitch)·Rx(roll)` about the axes
//!   of the coordinates' frame: for a projected CRS, grid east, grid north and up at the sample
//!   (yaw counter-clockwise from grid east); the trajectory CSV without a CRS.

use crate::crs::{Crs, CrsError, LocalFrame};
use crate::FormatError;
use precimap_core::geom::{rot_from_rpy, rpy_from_rot};
use precimap_core::{Mat3, Trajectory, TrajectoryError, Vec3};
use std::path::Path;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum AttitudeConvention {
    Navigation,
    Grid,
}

/// Trajectory samples as read from a file: coordinates in the file's CRS (geographic: longitude,
/// latitude in radians, ellipsoidal height), attitude in radians, times as the file states them.
#[derive(Clone, Debug, PartialEq)]
pub struct NavSamples {
    pub times: Vec<f64>,
    pub coordinates: Vec<[f64; 3]>,
    pub attitude: Vec<[f64; 3]>,
    pub convention: AttitudeConvention,
}

impl NavSamples {
    pub fn with_capacity(n: usize, convention: AttitudeConvention) -> Self {
        Self {
            times: Vec::with_capacity(n),
            coordinates: Vec::with_capacity(n),
            attitude: Vec::with_capacity(n),
            convention,
        }
    }

    pub fn len(&self) -> usize {
        self.times.len()
    }

    pub fn is_empty(&self) -> bool {
        self.times.is_empty()
    }
}

fn crs_error(path: &Path, index: usize, e: CrsError) -> FormatError {
    FormatError::file(path, format!("sample {index}: {e}; check the trajectory's CRS in the manifest"))
}

/// Rotation from precimap's body frame to east-north-up of an attitude given about a projected
/// CRS's grid axes at a point whose meridian convergence is `convergence` (radians): true azimuths
/// are grid azimuths plus the convergence, so yaw (counter-clockwise) loses it.
fn enu_from_grid_rotation(grid_from_body: &Mat3, convergence: f64) -> Mat3 {
    rot_from_rpy(0.0, 0.0, -convergence) * grid_from_body
}

/// Converts `samples` into a trajectory in the processing frame `frame`, with `time_offset` added
/// to every time (the step from the file's time convention to the campaign's). `source` is the
/// CRS of the coordinates; without a frame, coordinates and [`AttitudeConvention::Grid`] angles
/// are taken as they are.
pub fn to_trajectory(
    path: &Path,
    samples: &NavSamples,
    source: Option<&Crs>,
    frame: Option<&LocalFrame>,
    time_offset: f64,
) -> Result<Trajectory, FormatError> {
    let n = samples.len();
    let times: Vec<f64> = samples.times.iter().map(|t| t + time_offset).collect();
    let mut positions = Vec::with_capacity(n);
    let mut rpy = Vec::with_capacity(n);
    match frame {
        None => {
            if samples.convention == AttitudeConvention::Navigation || source.is_some() {
                return Err(FormatError::file(
                    path,
                    "this trajectory is in a geographic or navigation frame, which needs a processing CRS: add \
                     \"crs\": {\"processing\": EPSG code, \"origin_grid_m\": [easting, northing, height]} to the manifest",
                ));
            }
            for (c, a) in samples.coordinates.iter().zip(&samples.attitude) {
                positions.push(Vec3::from(*c));
                rpy.push([a[0].to_degrees(), a[1].to_degrees(), a[2].to_degrees()]);
            }
        }
        Some(frame) => {
            let source = source.unwrap_or(frame.crs());
            for (i, (c, a)) in samples.coordinates.iter().zip(&samples.attitude).enumerate() {
                let own = source.to_geographic(*c).map_err(|e| crs_error(path, i, e))?;
                let g = frame.crs().geographic_from(source, own).map_err(|e| crs_error(path, i, e))?;
                let r = match samples.convention {
                    AttitudeConvention::Navigation => frame.body_rotation_from_navigation(g[0], g[1], a[0], a[1], a[2]),
                    AttitudeConvention::Grid => {
                        let gamma = source.convergence(own).map_err(|e| crs_error(path, i, e))?;
                        let enu = enu_from_grid_rotation(&rot_from_rpy(a[0], a[1], a[2]), gamma);
                        frame.body_rotation_from_enu(g[0], g[1], &enu)
                    }
                };
                let (roll, pitch, yaw) = rpy_from_rot(&r);
                positions.push(frame.local_from_geographic(g));
                rpy.push([roll.to_degrees(), pitch.to_degrees(), yaw.to_degrees()]);
            }
        }
    }
    Trajectory::new(times, positions, rpy).map_err(|e| match e {
        TrajectoryError::NotIncreasing { index, .. } | TrajectoryError::NotFinite { index, .. } => {
            FormatError::file(path, format!("sample {index}: {e}"))
        }
        TrajectoryError::TooShort(_) => FormatError::file(path, e.to_string()),
    })
}

/// A pose of the processing frame as grid coordinates of its CRS and precimap angles (degrees)
/// about the grid axes at that point ([`AttitudeConvention::Grid`]): what trajectory outputs carry.
pub fn grid_pose(
    frame: &LocalFrame,
    position: &Vec3,
    local_from_body: &Mat3,
) -> Result<([f64; 3], [f64; 3]), CrsError> {
    let g = frame.geographic_from_local(position);
    let grid = frame.crs().from_geographic(g)?;
    let enu = frame.enu_from_body_rotation(g[0], g[1], local_from_body);
    let gamma = frame.crs().convergence(g)?;
    let (roll, pitch, yaw) = rpy_from_rot(&(rot_from_rpy(0.0, 0.0, gamma) * enu));
    Ok((grid, [roll.to_degrees(), pitch.to_degrees(), precimap_core::geom::wrap_deg(yaw.to_degrees())]))
}

/// A pose of the processing frame as geographic coordinates (longitude, latitude in radians,
/// height) and navigation angles (roll, pitch, true heading in radians): what an SBET carries.
pub fn navigation_pose(frame: &LocalFrame, position: &Vec3, local_from_body: &Mat3) -> ([f64; 3], [f64; 3]) {
    let g = frame.geographic_from_local(position);
    (g, frame.navigation_from_body_rotation(g[0], g[1], local_from_body))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame() -> LocalFrame {
        LocalFrame::new(Crs::from_epsg(32632).unwrap(), [549_800.0, 5_803_400.0, 55.0]).unwrap()
    }

    fn poses() -> Vec<(Vec3, Mat3)> {
        (0..5)
            .map(|i| {
                let p = Vec3::new(549_800.0 + 300.0 * i as f64, 5_803_400.0 - 170.0 * i as f64, 55.0 + i as f64);
                (p, rot_from_rpy(0.01 * i as f64, -0.02, 0.4 + 0.7 * i as f64))
            })
            .collect()
    }

    #[test]
    fn navigation_and_grid_poses_come_back_exactly() {
        let f = frame();
        let geographic = Crs::from_epsg(4979).unwrap();
        let mut nav = NavSamples::with_capacity(5, AttitudeConvention::Navigation);
        let mut grid = NavSamples::with_capacity(5, AttitudeConvention::Grid);
        for (i, (p, r)) in poses().iter().enumerate() {
            let (g, a) = navigation_pose(&f, p, r);
            nav.times.push(i as f64);
            nav.coordinates.push(g);
            nav.attitude.push(a);
            let (gp, ga) = grid_pose(&f, p, r).unwrap();
            grid.times.push(i as f64);
            grid.coordinates.push(gp);
            grid.attitude.push(ga.map(f64::to_radians));
        }
        let path = Path::new("t");
        for (samples, source) in [(&nav, Some(&geographic)), (&grid, None)] {
            let t = to_trajectory(path, samples, source, Some(&f), 10.0).unwrap();
            assert_eq!(t.times()[0], 10.0);
            for (i, (p, r)) in poses().iter().enumerate() {
                assert!(
                    (t.positions()[i] - p).norm() < 1e-7,
                    "{:?} {i}: {} vs {p}",
                    samples.convention,
                    t.positions()[i]
                );
                // The numerical convergence is good to ~1e-10 rad (10 nm at 100 m).
                let d = (t.rotations()[i] - r).norm();
                assert!(d < 1e-9, "{:?} {i}: {d}", samples.convention);
            }
        }
        // Grid coordinates at the origin are the origin, and the yaw about grid east is the local yaw there.
        let (gp, ga) = grid_pose(&f, &poses()[0].0, &poses()[0].1).unwrap();
        assert!((gp[0] - 549_800.0).abs() < 1e-8 && (gp[1] - 5_803_400.0).abs() < 1e-8);
        assert!((ga[2] - 0.4f64.to_degrees()).abs() < 1e-9, "{ga:?}");
    }

    #[test]
    fn without_a_frame_only_local_trajectories_pass() {
        let mut s = NavSamples::with_capacity(2, AttitudeConvention::Grid);
        s.times = vec![0.0, 1.0];
        s.coordinates = vec![[1.0, 2.0, 3.0], [2.0, 2.0, 3.0]];
        s.attitude = vec![[0.0, 0.0, std::f64::consts::FRAC_PI_2]; 2];
        let t = to_trajectory(Path::new("t"), &s, None, None, 0.0).unwrap();
        assert!((t.rpy_deg()[0][2] - 90.0).abs() < 1e-12);
        s.convention = AttitudeConvention::Navigation;
        let e = to_trajectory(Path::new("t.sbet"), &s, None, None, 0.0).unwrap_err().to_string();
        assert!(e.contains("t.sbet") && e.contains("needs a processing CRS"), "{e}");
        s.convention = AttitudeConvention::Grid;
        s.times = vec![1.0, 1.0];
        let e = to_trajectory(Path::new("t"), &s, None, None, 0.0).unwrap_err().to_string();
        assert!(e.contains("sample 1"), "{e}");
    }
}
