//! The report's ground-control section: how the map's position is fixed, and its offset from
//! every control and check target, with RMSE per axis as the ASPRS positional accuracy standard
//! states them (horizontal `RMSE_r = √(RMSE_x² + RMSE_y²)`).

use precimap_core::control::{ControlOffset, ControlRole, ControlSums, ControlTarget};
use serde::{Deserialize, Serialize};
use std::collections::HashMap;

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ControlReport {
    /// Whether ground control fixes the map's position, in words.
    pub datum: String,
    /// Whether any control target was observed: without, the map sits where the GNSS/IMU
    /// trajectories put it on average.
    pub datum_observed: bool,
    /// RMSE at the control targets (how well the adjustment fits them).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub control: Option<AccuracyFigures>,
    /// RMSE at the check targets (independent: they are not in the adjustment).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub check: Option<AccuracyFigures>,
    pub targets: Vec<TargetReport>,
}

/// Root-mean-square offsets over the targets of one role, per axis of the processing frame,
/// each over the targets whose surroundings observe that axis.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct AccuracyFigures {
    /// Targets of the role the strips observed at all.
    pub targets_observed: usize,
    pub targets_listed: usize,
    pub rmse_x_m: Option<f64>,
    pub rmse_y_m: Option<f64>,
    pub rmse_z_m: Option<f64>,
    /// `√(RMSE_x² + RMSE_y²)`, with both axes observed somewhere.
    pub rmse_horizontal_m: Option<f64>,
    /// Mean offset per axis: a shift of the whole map shows here.
    pub mean_m: [Option<f64>; 3],
    /// Targets per axis the figures are over.
    pub observed_per_axis: [usize; 3],
}

/// One target's line: the map's offset from it (map minus target, metres) where observed.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TargetReport {
    pub id: String,
    pub role: ControlRole,
    pub sigma_m: [f64; 3],
    /// Strip passes and points that observed it in the last iteration (0: none did).
    pub passes: u32,
    pub points: u64,
    pub offset_m: ControlOffset,
}

impl ControlReport {
    /// The section for `targets` from what the last iteration measured at them (`sums`, any
    /// order; targets without sums were not observed).
    pub fn new(targets: &[ControlTarget], sums: &[ControlSums]) -> Self {
        let by_id: HashMap<&str, &ControlSums> = sums.iter().map(|s| (s.id.as_str(), s)).collect();
        let lines: Vec<TargetReport> = targets
            .iter()
            .map(|t| {
                let s = by_id.get(t.id.as_str()).copied();
                TargetReport {
                    id: t.id.clone(),
                    role: t.role,
                    sigma_m: t.sigma_m,
                    passes: s.map_or(0, |s| s.passes),
                    points: s.map_or(0, |s| s.points),
                    offset_m: s.map(ControlSums::offset).unwrap_or_default(),
                }
            })
            .collect();
        let control = AccuracyFigures::of(&lines, ControlRole::Control);
        let check = AccuracyFigures::of(&lines, ControlRole::Check);
        let listed = control.as_ref().map_or(0, |c| c.targets_listed);
        let observed = control.as_ref().map_or(0, |c| c.targets_observed);
        let datum = match (listed, observed) {
            (0, _) => "not observed: the manifest lists no control targets, so the map's position is the \
                       GNSS/IMU trajectories' on average (add $.control to tie it to the ground)"
                .to_string(),
            (n, 0) => format!(
                "not observed: none of the {n} control targets lies on a surface the strips see within \
                 parameters.control_radius_m; check their coordinates and CRS"
            ),
            (n, k) => {
                let axes = control.as_ref().map_or([0; 3], |c| c.observed_per_axis);
                format!("fixed by {k} of {n} control targets ({} observe x, {} y, {} z)", axes[0], axes[1], axes[2])
            }
        };
        Self { datum, datum_observed: observed > 0, control, check, targets: lines }
    }
}

impl AccuracyFigures {
    fn of(lines: &[TargetReport], role: ControlRole) -> Option<Self> {
        let of_role: Vec<&TargetReport> = lines.iter().filter(|l| l.role == role).collect();
        if of_role.is_empty() {
            return None;
        }
        let mut squares = [0.0; 3];
        let mut sums = [0.0; 3];
        let mut counts = [0usize; 3];
        for l in &of_role {
            for (a, v) in [l.offset_m.x, l.offset_m.y, l.offset_m.z].into_iter().enumerate() {
                if let Some(v) = v {
                    squares[a] += v * v;
                    sums[a] += v;
                    counts[a] += 1;
                }
            }
        }
        let rmse = |a: usize| (counts[a] > 0).then(|| (squares[a] / counts[a] as f64).sqrt());
        let (x, y) = (rmse(0), rmse(1));
        Some(Self {
            targets_observed: of_role.iter().filter(|l| l.points > 0).count(),
            targets_listed: of_role.len(),
            rmse_x_m: x,
            rmse_y_m: y,
            rmse_z_m: rmse(2),
            rmse_horizontal_m: x.zip(y).map(|(x, y)| x.hypot(y)),
            mean_m: [0, 1, 2].map(|a| (counts[a] > 0).then(|| sums[a] / counts[a] as f64)),
            observed_per_axis: counts,
        })
    }
}

/// The targets as CSV (`qc/control.csv`): one line per target, empty cells where an axis is not
/// observed.
pub fn control_csv(report: &ControlReport) -> String {
    let mut out =
        String::from("id,role,sigma_x_m,sigma_y_m,sigma_z_m,passes,points,offset_x_m,offset_y_m,offset_z_m\n");
    let cell = |v: Option<f64>| v.map_or(String::new(), |v| format!("{v:.4}"));
    for t in &report.targets {
        let role = match t.role {
            ControlRole::Control => "control",
            ControlRole::Check => "check",
        };
        out.push_str(&format!(
            "{},{role},{},{},{},{},{},{},{},{}\n",
            t.id,
            t.sigma_m[0],
            t.sigma_m[1],
            t.sigma_m[2],
            t.passes,
            t.points,
            cell(t.offset_m.x),
            cell(t.offset_m.y),
            cell(t.offset_m.z)
        ));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn target(id: &str, role: ControlRole) -> ControlTarget {
        ControlTarget { id: id.into(), position: [0.0; 3], sigma_m: [0.005; 3], role, plane: None }
    }

    fn sums(id: &str, w: [f64; 3], e: f64) -> ControlSums {
        let mut s = ControlSums::new(id);
        s.add(w, e, 1.0);
        s.passes = 2;
        s
    }

    #[test]
    fn without_control_the_datum_is_not_observed() {
        let r = ControlReport::new(&[], &[]);
        assert!(!r.datum_observed);
        assert!(r.datum.starts_with("not observed"), "{}", r.datum);
        assert_eq!((&r.control, &r.check), (&None, &None));
    }

    #[test]
    fn check_rmse_is_per_axis_over_the_targets_that_observe_it() {
        let targets = [
            target("g1", ControlRole::Control),
            target("k1", ControlRole::Check),
            target("k2", ControlRole::Check),
            target("k3", ControlRole::Check),
        ];
        let measured = [
            sums("g1", [0.0, 0.0, 1.0], 0.001),
            sums("k1", [0.0, 0.0, 1.0], 0.003),
            sums("k2", [0.0, 0.0, 1.0], -0.004),
            sums("k2", [1.0, 0.0, 0.0], 0.006),
        ];
        // k2's two surfaces arrive as two tiles' sums.
        let mut k2 = measured[2].clone();
        k2.merge(&measured[3]);
        let r = ControlReport::new(&targets, &[measured[0].clone(), measured[1].clone(), k2]);
        assert!(r.datum_observed && r.datum.starts_with("fixed by 1 of 1"), "{}", r.datum);
        let check = r.check.clone().unwrap();
        assert_eq!((check.targets_listed, check.targets_observed), (3, 2));
        assert_eq!(check.observed_per_axis, [1, 0, 2]);
        assert!((check.rmse_z_m.unwrap() - (12.5e-6f64).sqrt()).abs() < 1e-12);
        assert!((check.rmse_x_m.unwrap() - 0.006).abs() < 1e-12);
        assert_eq!(check.rmse_horizontal_m, None, "y is observed nowhere");
        let csv = control_csv(&r);
        assert!(csv.contains("\nk3,check,0.005,0.005,0.005,0,0,,,\n"), "{csv}");
    }
}
