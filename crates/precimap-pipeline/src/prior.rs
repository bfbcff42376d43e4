//! Each anchor's prior from a trajectory's accuracy file (SMRMSG): the σ at the anchor's time,
//! turned into the processing frame's axes, at the level of the campaign's `sigma_prior_*`.
//!
//! The file gives the prior its shape (over time, e.g. a GNSS outage, and between axes); its
//! level stays the campaign's: a record with the file's median σ gets `sigma_prior_*`. A
//! per-anchor prior holds every anchor independently, so at the navigation's own σ it would
//! hold a stretch's mean far tighter than the navigation knows it (see
//! `Parameters::sigma_prior_position_m`).

use crate::campaign::TrajectoryEntry;
use crate::error::PipelineError;
use precimap_core::geom::{Mat3, Vec3};
use precimap_core::Parameters;

/// How far outside its records an accuracy file is held at its end values (seconds).
pub const ACCURACY_TOLERANCE_S: f64 = 1.0;

/// Rotation from north-east-down to east-north-up, for a campaign without a CRS (its frame is
/// taken as east-north-up).
const ENU_FROM_NED: Mat3 = Mat3::new(0.0, 1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, -1.0);

/// The prior weights (as `precimap_estimate::solve_trajectory` takes them) of
/// `trajectory`'s anchors `first..=last` from its accuracy file; `None` without one.
pub fn anchor_prior(
    trajectory: &TrajectoryEntry,
    params: &Parameters,
    (first, last): (u32, u32),
) -> Result<Option<Vec<[f64; 6]>>, PipelineError> {
    let Some(accuracy) = trajectory.accuracy.as_deref() else { return Ok(None) };
    let what = || format!("trajectory {} (accuracy file {})", trajectory.id, trajectory.accuracy_uri);
    let data = &trajectory.data;
    let (times, arcs, rotations) = (data.times(), data.arc_lengths(), data.rotations());
    let [median_position, median_tilt, median_heading] = accuracy.medians();
    let sp = params.sigma_prior_position_m;
    let [tilt_x, _, heading] = params.sigma_prior_rotation_axes_deg();
    let scale = [sp / median_position, tilt_x / median_tilt, heading / median_heading];
    let mut out = Vec::with_capacity((last.saturating_sub(first) + 1) as usize);
    let mut i = 0usize;
    let end = arcs.len().saturating_sub(1);
    for anchor in first..=last {
        let s = f64::from(anchor) * params.anchor_spacing_m;
        while i + 1 < end && arcs[i + 1] < s {
            i += 1;
        }
        let (t, position, rotation) = if end == 0 {
            (times[0], data.positions()[0], rotations[0])
        } else {
            let (a, b) = (arcs[i], arcs[i + 1]);
            let lambda = if b > a { ((s - a) / (b - a)).clamp(0.0, 1.0) } else { 0.0 };
            let p = data.positions()[i] + (data.positions()[i + 1] - data.positions()[i]) * lambda;
            (times[i] + lambda * (times[i + 1] - times[i]), p, rotations[if lambda < 0.5 { i } else { i + 1 }])
        };
        let Some((position_sigma, attitude_sigma)) = accuracy.at(t, ACCURACY_TOLERANCE_S) else {
            let (a, b) = (accuracy.times[0], accuracy.times[accuracy.times.len() - 1]);
            return Err(PipelineError::Input {
                what: what(),
                message: format!(
                    "anchor {anchor} lies at time {t:.3} s, outside the file's records ({a:.3}–{b:.3} s); supply the \
                     accuracy file of the same SBET, covering the whole trajectory"
                ),
            });
        };
        let local_from_ned = match &trajectory.georef {
            Some(g) => {
                let [lon, lat, _] = g.frame.geographic_from_local(&position);
                g.frame.local_from_ned(lon, lat)
            }
            None => ENU_FROM_NED,
        };
        out.push(weights(&local_from_ned, &rotation, position_sigma, attitude_sigma, scale));
    }
    Ok(Some(out))
}

/// One anchor's weights: the covariance of the scaled σ in the processing frame's axes, its
/// diagonal inverted. Roll acts about the body's forward axis, pitch about its lateral one,
/// heading about the vertical.
fn weights(
    local_from_ned: &Mat3,
    local_from_body: &Mat3,
    position_sigma_ned: [f64; 3],
    attitude_sigma_deg: [f64; 3],
    [position, tilt, heading]: [f64; 3],
) -> [f64; 6] {
    let variance = |axes: [(Vec3, f64); 3]| -> [f64; 3] {
        std::array::from_fn(|row| axes.iter().map(|(axis, sigma)| (axis[row] * sigma).powi(2)).sum())
    };
    let ned = |k: usize| local_from_ned.column(k).into_owned();
    let p = variance([
        (ned(0), position_sigma_ned[0] * position),
        (ned(1), position_sigma_ned[1] * position),
        (ned(2), position_sigma_ned[2] * position),
    ]);
    let [roll, pitch, yaw] = attitude_sigma_deg.map(f64::to_radians);
    let r = variance([
        (local_from_body.column(0).into_owned(), roll * tilt),
        (local_from_body.column(1).into_owned(), pitch * tilt),
        (ned(2), yaw * heading),
    ]);
    [1.0 / p[0], 1.0 / p[1], 1.0 / p[2], 1.0 / r[0], 1.0 / r[1], 1.0 / r[2]]
}

/// Every trajectory's anchor prior over its anchor range (see [`anchor_prior`]).
pub fn anchor_priors(
    trajectories: &[TrajectoryEntry],
    params: &Parameters,
    ranges: &[(u32, u32)],
) -> Result<Vec<Option<Vec<[f64; 6]>>>, PipelineError> {
    trajectories.iter().zip(ranges).map(|(t, &range)| anchor_prior(t, params, range)).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use precimap_core::Trajectory;
    use precimap_formats::sbet::NavAccuracy;
    use std::sync::Arc;

    fn entry(accuracy: NavAccuracy, yaw_deg: f64) -> TrajectoryEntry {
        let times: Vec<f64> = (0..=100).map(f64::from).collect();
        let (c, s) = (yaw_deg.to_radians().cos(), yaw_deg.to_radians().sin());
        let positions = times.iter().map(|t| Vec3::new(c * t, s * t, 0.0)).collect();
        let rpy = vec![[0.0, 0.0, yaw_deg]; times.len()];
        TrajectoryEntry {
            id: "p01".into(),
            path: "p01.sbet".into(),
            data: Arc::new(Trajectory::new(times, positions, rpy).unwrap()),
            mean_lever_arm: Vec3::zeros(),
            clock: Default::default(),
            georef: None,
            accuracy: Some(Arc::new(accuracy)),
            accuracy_uri: "p01.smrmsg".into(),
        }
    }

    fn accuracy(times: Vec<f64>, horizontal: f64) -> NavAccuracy {
        let n = times.len();
        let mut a = NavAccuracy {
            times,
            position_sigma_m: vec![[0.02, 0.02, 0.04]; n],
            attitude_sigma_deg: vec![[0.01, 0.02, 0.05]; n],
        };
        a.position_sigma_m[n / 2 + 1] = [horizontal, 2.0 * horizontal, 0.04];
        a
    }

    /// The median record gets the campaign's σ; a worse record a looser prior by the ratio of
    /// its σ, on the processing frame's axes: north/east on y/x, roll and pitch on the axes of
    /// the vehicle's heading.
    #[test]
    fn the_file_shapes_the_campaign_prior() {
        let params = Parameters::default();
        let times: Vec<f64> = (0..=10).map(|k| f64::from(k) * 10.0).collect();
        let t = entry(accuracy(times, 0.08), 0.0);
        let w = anchor_prior(&t, &params, (0, 200)).unwrap().unwrap();
        // Anchor 0: the file's median everywhere but at 60 s.
        let [median_position, ..] = t.accuracy.as_deref().unwrap().medians();
        let sp = params.sigma_prior_position_m;
        let expect = |sigma: f64| 1.0 / (sigma * sp / median_position).powi(2);
        let close = |a: f64, b: f64| (a / b - 1.0).abs() < 1e-9;
        assert!(close(w[0][0], expect(0.02)) && close(w[0][2], expect(0.04)), "{:?}", w[0]);
        // Anchor 120 (60 m, 60 s): north 0.08 on y, east 0.16 on x.
        assert!(close(w[120][1], expect(0.08)) && close(w[120][0], expect(0.16)), "{:?}", w[120]);
        // Half-way to the next record: interpolated.
        assert!(close(w[130][1], expect(0.05)), "{:?}", w[130]);
        // Driving east, roll is about x and pitch about y; the heading gets the campaign's σ.
        let [tilt, _, heading] = params.sigma_prior_rotation_axes_deg().map(f64::to_radians);
        let median_tilt = (0.0005f64 / 2.0).sqrt().to_radians();
        let roll = 1.0 / (0.01f64.to_radians() * tilt / median_tilt).powi(2);
        let pitch = 1.0 / (0.02f64.to_radians() * tilt / median_tilt).powi(2);
        assert!(
            close(w[0][3], roll) && close(w[0][4], pitch) && close(w[0][5], 1.0 / (heading * heading)),
            "{:?}",
            w[0]
        );
        // Driving north they swap.
        let north = anchor_prior(
            &entry(accuracy((0..=10).map(|k| f64::from(k) * 10.0).collect(), 0.08), 90.0),
            &params,
            (0, 4),
        )
        .unwrap()
        .unwrap();
        assert!(close(north[0][3], pitch) && close(north[0][4], roll), "{:?}", north[0]);
    }

    #[test]
    fn anchors_outside_the_file_are_an_error_naming_it() {
        let t = entry(accuracy((0..=5).map(|k| f64::from(k) * 10.0).collect(), 0.08), 0.0);
        let e = anchor_prior(&t, &Parameters::default(), (0, 200)).unwrap_err().to_string();
        assert!(
            e.contains("trajectory p01 (accuracy file p01.smrmsg)") && e.contains("outside the file's records"),
            "{e}"
        );
    }
}
