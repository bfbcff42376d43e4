//! Trajectory accuracy: an input or corrected trajectory against the true one, at its own time
//! stamps.

use precimap_core::geom::so3_log;
use precimap_core::Trajectory;

/// Sums of squared errors of one trajectory against the truth.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct TrajectoryErrors {
    /// Samples compared (inside the true trajectory's time span).
    pub samples: u64,
    /// Samples outside the true trajectory's time span, not compared.
    pub outside_truth: u64,
    /// Σ |c − c_true|², m².
    pub position_sum_sq: f64,
    /// Σ angle(R_trueᵀ R)², deg².
    pub rotation_sum_sq_deg: f64,
}

impl TrajectoryErrors {
    pub fn merge(&mut self, other: &Self) {
        self.samples += other.samples;
        self.outside_truth += other.outside_truth;
        self.position_sum_sq += other.position_sum_sq;
        self.rotation_sum_sq_deg += other.rotation_sum_sq_deg;
    }

    /// RMS of the 3D position error, metres; NaN without samples.
    pub fn position_rms_m(&self) -> f64 {
        (self.position_sum_sq / self.samples as f64).sqrt()
    }

    /// RMS of the attitude error angle, degrees; NaN without samples.
    pub fn rotation_rms_deg(&self) -> f64 {
        (self.rotation_sum_sq_deg / self.samples as f64).sqrt()
    }
}

/// Compares every sample of `eval` with `truth` interpolated at the same time.
pub fn trajectory_errors(eval: &Trajectory, truth: &Trajectory) -> TrajectoryErrors {
    let mut out = TrajectoryErrors::default();
    for ((&t, c), r) in eval.times().iter().zip(eval.positions()).zip(eval.rotations()) {
        let Some(pose) = truth.pose_at(t) else {
            out.outside_truth += 1;
            continue;
        };
        out.samples += 1;
        out.position_sum_sq += (c - pose.position).norm_squared();
        out.rotation_sum_sq_deg += so3_log(&(pose.rotation.transpose() * r)).norm().to_degrees().powi(2);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use precimap_core::Vec3;

    fn line(t0: f64, n: usize, shift: Vec3, yaw_offset_deg: f64) -> Trajectory {
        let times: Vec<f64> = (0..n).map(|i| t0 + i as f64 * 0.005).collect();
        let positions =
            times.iter().map(|t| Vec3::new(549_800.0 + (t - 100.0) * 10.0, 5_803_400.0, 50.0) + shift).collect();
        let rpy = times.iter().map(|t| [0.5, -1.0, 30.0 + (t - 100.0) + yaw_offset_deg]).collect();
        Trajectory::new(times, positions, rpy).unwrap()
    }

    #[test]
    fn constant_offsets_are_recovered() {
        let truth = line(100.0, 200, Vec3::zeros(), 0.0);
        let e = trajectory_errors(&line(100.0, 200, Vec3::new(0.03, 0.0, 0.04), 0.02), &truth);
        assert_eq!((e.samples, e.outside_truth), (200, 0));
        assert!((e.position_rms_m() - 0.05).abs() < 1e-9);
        assert!((e.rotation_rms_deg() - 0.02).abs() < 1e-6, "{}", e.rotation_rms_deg());
        let same = trajectory_errors(&truth, &truth);
        assert!(same.position_rms_m() < 1e-12 && same.rotation_rms_deg() < 1e-6);
    }

    #[test]
    fn samples_outside_the_truth_are_counted_not_compared() {
        let truth = line(100.0, 100, Vec3::zeros(), 0.0);
        // Starts 50 samples later: the last 50 lie beyond the truth's end.
        let e = trajectory_errors(&line(100.25, 100, Vec3::new(0.0, 0.0, 0.01), 0.0), &truth);
        assert_eq!((e.samples, e.outside_truth), (50, 50));
        assert!((e.position_rms_m() - 0.01).abs() < 1e-9);
        let mut total = TrajectoryErrors::default();
        total.merge(&e);
        total.merge(&trajectory_errors(&truth, &truth));
        assert_eq!(total.samples, 150);
        assert!((total.position_rms_m() - (50.0 * 1e-4 / 150.0f64).sqrt()).abs() < 1e-9);
    }
}
