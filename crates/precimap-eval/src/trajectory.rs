//! Trajectory accuracy: an input or corrected trajectory against the true one, at its own time
//! stamps.

use precimap_core::geom::so3_log;
use precimap_core::{Trajectory, Vec3};

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
    /// Σ (c − c_true)·Δs over compared samples, Δs the true arc length since the previous
    /// sample (m²): the error weighted the way anchors (every 0.5 m of arc length) weigh it.
    pub position_sum_by_length: [f64; 3],
    /// Σ Δs over compared samples, m.
    pub length_m: f64,
}

impl TrajectoryErrors {
    pub fn merge(&mut self, other: &Self) {
        self.samples += other.samples;
        self.outside_truth += other.outside_truth;
        self.position_sum_sq += other.position_sum_sq;
        self.rotation_sum_sq_deg += other.rotation_sum_sq_deg;
        (0..3).for_each(|a| self.position_sum_by_length[a] += other.position_sum_by_length[a]);
        self.length_m += other.length_m;
    }

    /// Mean position error per arc length (x, y, z metres): the absolute datum error. For the
    /// input trajectories it is what no relative adjustment can observe (moving every pass and
    /// the map together changes no residual), so a result's mean stays there. NaN without length.
    pub fn mean_position_error_m(&self) -> [f64; 3] {
        self.position_sum_by_length.map(|v| v / self.length_m)
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

/// Position error `eval − truth_position` at time `t` (`eval` interpolated linearly); `None`
/// outside its time span.
pub fn position_error_at(eval: &Trajectory, truth_position: Vec3, t: f64) -> Option<[f64; 3]> {
    position_error_from(eval, truth_position, t, &mut 0)
}

/// [`position_error_at`] looking `t` up from segment `*hint` ([`Trajectory::locate_from`]).
pub fn position_error_from(eval: &Trajectory, truth_position: Vec3, t: f64, hint: &mut usize) -> Option<[f64; 3]> {
    let d = eval.position_at_from(t, hint)? - truth_position;
    Some([d.x, d.y, d.z])
}

/// Compares every sample of `eval` with `truth` interpolated at the same time.
pub fn trajectory_errors(eval: &Trajectory, truth: &Trajectory) -> TrajectoryErrors {
    let mut out = TrajectoryErrors::default();
    let mut last_true_position = None;
    for ((&t, c), r) in eval.times().iter().zip(eval.positions()).zip(eval.rotations()) {
        let Some(pose) = truth.pose_at(t) else {
            out.outside_truth += 1;
            continue;
        };
        out.samples += 1;
        let error = c - pose.position;
        out.position_sum_sq += error.norm_squared();
        if let Some(last) = last_true_position.replace(pose.position) {
            let step = (pose.position - last).norm();
            (0..3).for_each(|a| out.position_sum_by_length[a] += error[a] * step);
            out.length_m += step;
        }
        out.rotation_sum_sq_deg += so3_log(&(pose.rotation.transpose() * r)).norm().to_degrees().powi(2);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

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
        let at_truth = truth.position_at(100.3).unwrap();
        assert!((at_truth - truth.pose_at(100.3).unwrap().position).norm() < 1e-12);
        let at = position_error_at(&line(100.0, 200, Vec3::new(0.03, 0.0, 0.04), 0.0), at_truth, 100.3).unwrap();
        assert!((at[0] - 0.03).abs() < 1e-9 && at[1].abs() < 1e-9 && (at[2] - 0.04).abs() < 1e-9, "{at:?}");
        assert!(truth.position_at(99.0).is_none() && position_error_at(&truth, at_truth, 99.0).is_none());
        let mean = e.mean_position_error_m();
        assert!((mean[0] - 0.03).abs() < 1e-9 && mean[1].abs() < 1e-9 && (mean[2] - 0.04).abs() < 1e-9, "{mean:?}");
        assert!((e.length_m - 199.0 * 0.05).abs() < 1e-6, "{}", e.length_m);
    }

    #[test]
    fn the_mean_error_weighs_samples_by_arc_length_not_time() {
        // The truth drives 0.5 m per sample, then stands for 100 samples; the evaluated
        // trajectory is off by 0.1 m in x while driving and by 0.5 m while standing.
        let times: Vec<f64> = (0..200).map(|i| 100.0 + i as f64 * 0.005).collect();
        let along = |i: usize| 0.5 * i.min(100) as f64;
        let truth_positions = (0..200).map(|i| Vec3::new(549_800.0 + along(i), 5_803_400.0, 50.0)).collect();
        let eval_positions =
            (0..200).map(|i| Vec3::new(549_800.0 + along(i) + if i > 100 { 0.5 } else { 0.1 }, 5_803_400.0, 50.0));
        let rpy = vec![[0.0, 0.0, 0.0]; 200];
        let truth = Trajectory::new(times.clone(), truth_positions, rpy.clone()).unwrap();
        let eval = Trajectory::new(times, eval_positions.collect(), rpy).unwrap();
        let e = trajectory_errors(&eval, &truth);
        assert!((e.mean_position_error_m()[0] - 0.1).abs() < 1e-9, "{:?}", e.mean_position_error_m());
        assert!((e.length_m - 50.0).abs() < 1e-9);
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
