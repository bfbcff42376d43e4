//! `report.json`: what a run did, per iteration and per trajectory.

use precimap_estimate::ResidualHistogram;
use serde::{Deserialize, Serialize};

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Report {
    pub campaign: String,
    pub manifest: String,
    /// Points in all input strips.
    pub points_total: u64,
    pub tiles: usize,
    pub strips: Vec<StripReport>,
    pub iterations: Vec<IterationReport>,
    pub converged: bool,
    pub trajectories: Vec<TrajectoryReport>,
    /// Signed distances of all modelled points to the latent map in the last iteration.
    pub residual_histogram: ResidualHistogram,
    /// How ground control fixes the map, and the offsets at control and check targets.
    #[serde(default)]
    pub control: crate::control_report::ControlReport,
    /// The scanners' mounting calibration, where the campaign estimates it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub calibration: Option<crate::calibration::CalibrationReport>,
    pub timings: Timings,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct StripReport {
    pub id: String,
    pub points: u64,
    pub points_with_normal: u64,
    pub points_emitted: u64,
    pub revolutions: u64,
    pub rows_per_revolution: u32,
    /// The strip had no scan angles; its scan image was built from reconstructed ones.
    #[serde(default)]
    pub scan_angles_reconstructed: bool,
    /// Points with a normal and a segment within `max_range_m` (what `min_usable_share` is
    /// measured on).
    #[serde(default)]
    pub points_usable: u64,
    /// Where the normals came from: `scan_image`, `ring_image` (a multi-beam head) or
    /// `neighbours` (3-D neighbours).
    #[serde(default)]
    pub normal_source: precimap_core::NormalSource,
    /// Why the scan image was not used, under `normals: auto`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scan_image_refused: Option<String>,
    pub tiles: usize,
}

impl StripReport {
    /// A strip's line of `report.json` from what its preparation measured.
    pub fn new(id: &str, stats: &precimap_estimate::PrepareStats, tiles: usize) -> Self {
        Self {
            id: id.to_string(),
            points: stats.points,
            points_with_normal: stats.points_with_normal,
            points_emitted: stats.points_emitted,
            revolutions: stats.revolutions,
            rows_per_revolution: stats.rows_per_revolution,
            scan_angles_reconstructed: stats.scan_angles_reconstructed,
            points_usable: stats.points_usable,
            normal_source: stats.normal_source,
            scan_image_refused: stats.scan_image_refused.clone(),
            tiles,
        }
    }
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct IterationReport {
    pub iteration: usize,
    /// Largest translation the common-mode field solved in this iteration applied to an anchor
    /// (0 in steps without it).
    #[serde(default)]
    pub common_mode_field_max_m: f64,
    /// The rotation of the whole campaign solved with the field in this iteration
    /// (`parameters.campaign_motion`; a rotation vector about the world frame's x, y and z axes,
    /// degrees): zero in steps without it.
    #[serde(default)]
    pub campaign_rotation_deg: [f64; 3],
    /// Largest heading the common-mode field solved in this iteration gave an anchor
    /// (`parameters.common_mode_heading`; degrees): zero in steps without it.
    #[serde(default)]
    pub common_mode_heading_max_deg: f64,
    /// Largest tilt (rotation about a horizontal axis) the common-mode field solved in this
    /// iteration gave an anchor (`parameters.common_mode_tilt`; degrees): zero in steps without it.
    #[serde(default)]
    pub common_mode_tilt_max_deg: f64,
    pub grid_m: f64,
    pub threshold_m: f64,
    /// Points in tile cores (each point once).
    pub points_in_tiles: u64,
    /// Points on latent-map pixels shared by two or more strip passes.
    pub points_modelled: u64,
    /// Observations: modelled points within the threshold.
    pub points_used: u64,
    pub residual_mean_m: f64,
    pub residual_std_m: f64,
    /// Mean over shared pixels of the standard deviation of the strips' heights.
    pub pixel_std_mean_m: f64,
    /// The largest anchor change since the previous iteration (the common-mode field's share
    /// included), as the displacement of a point at 10 m; the convergence test reads it.
    pub max_correction_change_m: f64,
    /// Median and 99th percentile of the anchors' changes (upper edges of 26 % wide bins): a
    /// campaign still drifting everywhere shows in the median, a few wandering anchors only in
    /// the maximum.
    #[serde(default)]
    pub median_correction_change_m: f64,
    #[serde(default)]
    pub p99_correction_change_m: f64,
    /// Where the largest change is: the place that keeps the campaign from converging.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_correction_change_at: Option<ChangeLocation>,
    /// Anderson acceleration's coefficients (oldest difference first) when this iteration started
    /// from their combination of the settling iterations before it (`parameters.anderson_depth`);
    /// absent when it started from the last iteration's result.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub anderson_coefficients: Vec<f64>,
    /// Wall-clock seconds, including the Anderson combination this iteration started from: the
    /// iterations' seconds add up to the estimation's.
    pub seconds: f64,
}

/// An anchor of a trajectory: its index and its distance along the trajectory (the anchor
/// spacing times the index), where the QC correction plots show it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ChangeLocation {
    pub trajectory: String,
    pub anchor: u32,
    pub along_m: f64,
}

impl ChangeLocation {
    /// The largest of several trajectories' changes `(trajectory id, change, anchor)` and where
    /// it is: the first one in trajectory order on ties; `(0, None)` for no trajectories. Both
    /// drivers take an iteration's `max_correction_change_m` and its place from here.
    pub fn largest<'a>(
        changes: impl IntoIterator<Item = (&'a str, f64, u32)>,
        anchor_spacing_m: f64,
    ) -> (f64, Option<Self>) {
        let mut best: Option<(&str, f64, u32)> = None;
        for c in changes {
            // A NaN change is never the largest while a number is there (as `f64::max`).
            if best.is_none_or(|b| c.1 > b.1 || b.1.is_nan()) {
                best = Some(c);
            }
        }
        let largest = best.map_or(0.0, |b| b.1.max(0.0));
        let at = best.map(|(trajectory, _, anchor)| Self {
            trajectory: trajectory.to_string(),
            anchor,
            along_m: anchor as f64 * anchor_spacing_m,
        });
        (largest, at)
    }
}

/// `v03 at 448 m`: the trajectory and the distance along it.
impl std::fmt::Display for ChangeLocation {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{} at {:.0} m", self.trajectory, self.along_m)
    }
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct TrajectoryReport {
    pub id: String,
    pub anchors: usize,
    pub anchors_observed: u32,
    pub observations: u64,
    pub position_correction_rms_m: f64,
    pub position_correction_max_m: f64,
    pub rotation_correction_rms_deg: f64,
    pub rotation_correction_max_deg: f64,
    /// Mean posterior standard deviation of the position corrections over observed anchors.
    pub position_sigma_mean_m: f64,
    pub rotation_sigma_mean_deg: f64,
    /// The trajectory's estimated curvature σ's (x, y, z in m, rotations about x, y, z in
    /// degrees), where the campaign estimates its process model (`parameters.process_model`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub curvature_sigma: Option<[f64; 6]>,
}

#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct Timings {
    /// Wall-clock seconds of each phase and in all.
    pub prepare_s: f64,
    pub estimate_s: f64,
    pub export_s: f64,
    pub total_s: f64,
    /// Through the job framework: every task's seconds summed (the executors' work, however many
    /// shared it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub task_s: Option<f64>,
}

#[cfg(test)]
mod tests {
    use super::ChangeLocation;

    #[test]
    fn the_largest_change_is_located_in_trajectory_order() {
        let changes = [("v01", 0.2e-3, 10), ("v02", 0.5e-3, 1235), ("v03", 0.5e-3, 7)];
        let (largest, at) = ChangeLocation::largest(changes, 0.5);
        let at = at.unwrap();
        assert_eq!(largest, 0.5e-3);
        assert_eq!(at, ChangeLocation { trajectory: "v02".into(), anchor: 1235, along_m: 617.5 });
        assert_eq!(at.to_string(), "v02 at 618 m");
        assert_eq!(ChangeLocation::largest([], 0.5), (0.0, None));
        // Nothing changed anywhere: the first trajectory's anchor, not a missing place.
        let (_, still) = ChangeLocation::largest([("v01", 0.0, 4), ("v02", 0.0, 9)], 0.5);
        let still = still.unwrap();
        assert_eq!((still.trajectory.as_str(), still.anchor), ("v01", 4));
    }
}
