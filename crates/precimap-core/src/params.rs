//! Estimation parameters. Every field has the paper's default (§5, §6.2, §7.1); a manifest's
//! `parameters` object overrides single fields and may not name unknown ones.

use serde::{Deserialize, Serialize};

/// One step of the iteration schedule: the latent map's pixel size and the outlier threshold.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct IterationStep {
    pub grid_m: f64,
    pub threshold_m: f64,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Parameters {
    /// Distance between anchors along the trajectory (paper: 0.5 m).
    pub anchor_spacing_m: f64,
    /// Edge of a square map tile (paper: 15 m).
    pub tile_size_m: f64,
    /// Points within this distance of a tile border are also emitted to the neighbour (paper: 0.3 m).
    pub tile_overlap_m: f64,
    /// Edge of a latent-map cell (voxel) holding local surface models.
    pub cell_size_m: f64,
    /// Points join a cell's surface model when their normals agree within this angle.
    pub normal_group_angle_deg: f64,
    /// σ of one point-to-surface distance (scanner precision).
    pub sigma_distance_m: f64,
    /// σ of the prior on the total position correction (GNSS/IMU position accuracy).
    pub sigma_prior_position_m: f64,
    /// σ of the prior on the total attitude correction.
    pub sigma_prior_rotation_deg: f64,
    /// σ of the change in position correction between neighbouring anchors.
    pub sigma_smooth_position_m: f64,
    /// σ of the change in attitude correction between neighbouring anchors.
    pub sigma_smooth_rotation_deg: f64,
    /// Iterations in order; estimation stops early once converged on the last step's settings.
    pub schedule: Vec<IterationStep>,
    /// Converged when no anchor moves a point at 10 m range by more than this between iterations.
    pub convergence_tolerance_m: f64,
}

impl Default for Parameters {
    fn default() -> Self {
        Self {
            anchor_spacing_m: 0.5,
            tile_size_m: 15.0,
            tile_overlap_m: 0.3,
            cell_size_m: 1.0,
            normal_group_angle_deg: 30.0,
            sigma_distance_m: 0.005,
            sigma_prior_position_m: 0.3,
            sigma_prior_rotation_deg: 0.05,
            sigma_smooth_position_m: 0.02,
            sigma_smooth_rotation_deg: 0.003,
            schedule: default_schedule(),
            convergence_tolerance_m: 1e-4,
        }
    }
}

/// The paper's schedule (§7.1): 18 iterations, grid 10 cm → 2 cm (most) → 1 cm, threshold
/// 0.3 m → 7 mm.
pub fn default_schedule() -> Vec<IterationStep> {
    let mut s = Vec::with_capacity(18);
    let mut push = |n: usize, grid_m: f64, threshold_m: f64| {
        for _ in 0..n {
            s.push(IterationStep { grid_m, threshold_m });
        }
    };
    push(2, 0.10, 0.30);
    push(1, 0.10, 0.15);
    push(1, 0.05, 0.08);
    push(1, 0.05, 0.05);
    push(2, 0.02, 0.03);
    push(5, 0.02, 0.02);
    push(1, 0.02, 0.015);
    push(1, 0.02, 0.012);
    push(2, 0.01, 0.01);
    push(2, 0.01, 0.007);
    s
}

/// A parameter that is out of its valid range: the field path and what is wrong.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("parameters.{field}: {problem}")]
pub struct ParameterProblem {
    pub field: String,
    pub problem: String,
}

impl Parameters {
    /// Every out-of-range value, each with its field name.
    pub fn problems(&self) -> Vec<ParameterProblem> {
        let mut out = Vec::new();
        let mut positive = |field: &str, v: f64| {
            if !(v.is_finite() && v > 0.0) {
                out.push(ParameterProblem {
                    field: field.into(),
                    problem: format!("must be a positive number, got {v}"),
                });
            }
        };
        positive("anchor_spacing_m", self.anchor_spacing_m);
        positive("tile_size_m", self.tile_size_m);
        positive("cell_size_m", self.cell_size_m);
        positive("normal_group_angle_deg", self.normal_group_angle_deg);
        positive("sigma_distance_m", self.sigma_distance_m);
        positive("sigma_prior_position_m", self.sigma_prior_position_m);
        positive("sigma_prior_rotation_deg", self.sigma_prior_rotation_deg);
        positive("sigma_smooth_position_m", self.sigma_smooth_position_m);
        positive("sigma_smooth_rotation_deg", self.sigma_smooth_rotation_deg);
        positive("convergence_tolerance_m", self.convergence_tolerance_m);
        for (i, step) in self.schedule.iter().enumerate() {
            positive(&format!("schedule[{i}].grid_m"), step.grid_m);
            positive(&format!("schedule[{i}].threshold_m"), step.threshold_m);
        }
        if !(self.tile_overlap_m.is_finite() && self.tile_overlap_m >= 0.0) {
            out.push(ParameterProblem { field: "tile_overlap_m".into(), problem: "must be zero or positive".into() });
        } else if self.tile_overlap_m * 2.0 >= self.tile_size_m {
            out.push(ParameterProblem {
                field: "tile_overlap_m".into(),
                problem: "must be less than half of tile_size_m".into(),
            });
        }
        if self.schedule.is_empty() {
            out.push(ParameterProblem { field: "schedule".into(), problem: "needs at least one iteration".into() });
        }
        if self.cell_size_m > 0.0 && self.tile_size_m > 0.0 {
            let cells = self.tile_size_m / self.cell_size_m;
            if (cells - cells.round()).abs() > 1e-9 {
                out.push(ParameterProblem {
                    field: "cell_size_m".into(),
                    problem: format!("must divide tile_size_m ({}) into whole cells", self.tile_size_m),
                });
            }
        }
        if self.normal_group_angle_deg >= 90.0 {
            out.push(ParameterProblem { field: "normal_group_angle_deg".into(), problem: "must be below 90".into() });
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_follow_the_paper() {
        let p = Parameters::default();
        assert_eq!(p.schedule.len(), 18);
        assert_eq!(p.schedule[0], IterationStep { grid_m: 0.10, threshold_m: 0.30 });
        assert_eq!(*p.schedule.last().unwrap(), IterationStep { grid_m: 0.01, threshold_m: 0.007 });
        assert!(p.problems().is_empty());
    }

    #[test]
    fn partial_override_and_unknown_fields() {
        let p: Parameters = serde_json::from_str(r#"{"anchor_spacing_m": 1.0}"#).unwrap();
        assert_eq!(p.anchor_spacing_m, 1.0);
        assert_eq!(p.tile_size_m, 15.0);
        assert!(serde_json::from_str::<Parameters>(r#"{"anchor_spacing": 1.0}"#).is_err());
        let bad = Parameters { cell_size_m: 0.7, tile_overlap_m: -1.0, ..Default::default() };
        let fields: Vec<_> = bad.problems().into_iter().map(|p| p.field).collect();
        assert_eq!(fields, vec!["tile_overlap_m", "cell_size_m"]);
    }
}
