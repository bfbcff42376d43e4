//! Trajectory accuracy: an input or corrected trajectory against the true one, at its own time
//! stamps.

use precimap_core::geom::so3_log;
use precimap_core::{Mat3, Trajectory, Vec3};

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
    /// The same errors in the true trajectory's own frame, weighted by Δs like the datum.
    pub frame: FrameSums,
    /// The vertical error over the true horizontal position, weighted by Δs.
    pub tilt: TiltSums,
    /// The attitude error as a rotation vector in the world frame (degrees), in the true
    /// vehicle's axes ([`ATTITUDE_COMPONENTS`]), weighted by Δs like the position's frame.
    pub attitude: FrameSums,
    /// Σ ω·Δs over compared samples (deg·m), ω the attitude error in the world frame: with
    /// `length_m`, the campaign's mean attitude error.
    pub rotation_sum_by_length: [f64; 3],
}

/// An attitude error's components about the true vehicle's axes (body x forward,
/// y left, z up), in this order. Relative data see them differently: a heading error moves a
/// façade at range r along the track by r·δ, a roll error tilts the road across it.
pub const ATTITUDE_COMPONENTS: [&str; 3] = ["roll", "pitch", "heading"];

/// Length-weighted sums for the least-squares plane `e_z ≈ c₀ + c₁ Δx + c₂ Δy` through the
/// vertical position error over the true horizontal position (Δ from the first sample added).
/// Tilting a whole campaign, every pass and the map together, changes no residual, so the
/// strips' agreement cannot fix it (the GNSS/IMU prior should, as it places the datum); the
/// vertical error about this plane is what the agreement decides.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct TiltSums {
    origin: Option<[f64; 2]>,
    normal: [[f64; 3]; 3],
    rhs: [f64; 3],
    square: f64,
}

impl TiltSums {
    fn add(&mut self, position: Vec3, vertical_error: f64, weight: f64) {
        let origin = *self.origin.get_or_insert([position.x, position.y]);
        let v = [1.0, position.x - origin[0], position.y - origin[1]];
        for r in 0..3 {
            self.rhs[r] += weight * v[r] * vertical_error;
            for c in 0..3 {
                self.normal[r][c] += weight * v[r] * v[c];
            }
        }
        self.square += weight * vertical_error * vertical_error;
    }

    /// The same sums about `origin`: `v' = T v` with `T` adding the origins' difference.
    fn about(&self, origin: [f64; 2]) -> Self {
        let Some(mine) = self.origin else { return *self };
        let (dx, dy) = (mine[0] - origin[0], mine[1] - origin[1]);
        let t = nalgebra::Matrix3::new(1.0, 0.0, 0.0, dx, 1.0, 0.0, dy, 0.0, 1.0);
        let normal = t * nalgebra::Matrix3::from_fn(|r, c| self.normal[r][c]) * t.transpose();
        let rhs = t * nalgebra::Vector3::from(self.rhs);
        Self {
            origin: Some(origin),
            normal: std::array::from_fn(|r| std::array::from_fn(|c| normal[(r, c)])),
            rhs: rhs.into(),
            ..*self
        }
    }

    pub fn merge(&mut self, other: &Self) {
        let Some(mine) = self.origin else {
            *self = *other;
            return;
        };
        let other = other.about(mine);
        for r in 0..3 {
            self.rhs[r] += other.rhs[r];
            for c in 0..3 {
                self.normal[r][c] += other.normal[r][c];
            }
        }
        self.square += other.square;
    }

    /// The plane's tilt (degrees) and the RMS of the vertical error about it (metres); `None`
    /// where the samples cannot fix a plane (one straight line, or none).
    pub fn plane(&self) -> Option<(f64, f64)> {
        let normal = nalgebra::Matrix3::from_fn(|r, c| self.normal[r][c]);
        let rhs = nalgebra::Vector3::from(self.rhs);
        // A straight drive leaves the normal equations singular up to rounding (relative to the
        // diagonal, whose entries differ in units).
        let diagonal = normal.diagonal().product();
        if diagonal.is_nan() || normal.determinant().abs() <= 1e-9 * diagonal {
            return None;
        }
        let c = normal.cholesky()?.solve(&rhs);
        // normal[0][0] = Σ Δs, the weight of the samples.
        let residual = (self.square - rhs.dot(&c)).max(0.0) / self.normal[0][0];
        Some((c[1].hypot(c[2]).atan().to_degrees(), residual.sqrt()))
    }
}

/// A position error's components in the true trajectory's own frame, in this order: along the
/// direction of travel, across it (horizontal, to the left) and vertical. Strip adjustment
/// observes them differently: across-track and vertical through every surface a pass sees,
/// along-track only through surfaces that change along the street (poles, façade relief, cars),
/// so a weakly observed stretch shows up in one component and is lost in a 3D RMS.
pub const FRAME_COMPONENTS: [&str; 3] = ["along-track", "across-track", "vertical"];

/// Length-weighted sums from which each frame component's RMS of `e − d` follows for any datum
/// `d` (the mean error of every trajectory together, known only once all are compared): per
/// component `i` with unit vector `bᵢ`, Σ Δs (bᵢ·e)², Σ Δs (bᵢ·e) bᵢ and Σ Δs bᵢ bᵢᵀ. The
/// position error uses the travel frame ([`FRAME_COMPONENTS`]), the attitude error the true
/// vehicle's axes ([`ATTITUDE_COMPONENTS`]).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct FrameSums {
    square: [f64; 3],
    cross: [[f64; 3]; 3],
    outer: [[[f64; 3]; 3]; 3],
}

impl FrameSums {
    fn add(&mut self, basis: &[Vec3; 3], error: Vec3, weight: f64) {
        for (i, b) in basis.iter().enumerate() {
            let along = b.dot(&error);
            self.square[i] += weight * along * along;
            for r in 0..3 {
                self.cross[i][r] += weight * along * b[r];
                for c in 0..3 {
                    self.outer[i][r][c] += weight * b[r] * b[c];
                }
            }
        }
    }

    pub fn merge(&mut self, other: &Self) {
        for i in 0..3 {
            self.square[i] += other.square[i];
            for r in 0..3 {
                self.cross[i][r] += other.cross[i][r];
                for c in 0..3 {
                    self.outer[i][r][c] += other.outer[i][r][c];
                }
            }
        }
    }

    /// Per component of the basis the sums were filled in, the RMS of `e − datum` weighted by
    /// arc length over `length_m`; NaN without length.
    pub fn rms_without(&self, datum: [f64; 3], length_m: f64) -> [f64; 3] {
        std::array::from_fn(|i| {
            let mut sum = self.square[i];
            for r in 0..3 {
                sum -= 2.0 * datum[r] * self.cross[i][r];
                for c in 0..3 {
                    sum += datum[r] * self.outer[i][r][c] * datum[c];
                }
            }
            // Cancellation can leave a tiny negative sum where the error is the datum alone.
            (sum.max(0.0) / length_m).sqrt()
        })
    }
}

/// The frame (`FRAME_COMPONENTS`) of a true step `step`; `None` where the vehicle does not move
/// horizontally (below 0.1 mm per sample: standing, and such samples weigh nothing anyway).
fn travel_frame(step: Vec3) -> Option<[Vec3; 3]> {
    let horizontal = Vec3::new(step.x, step.y, 0.0);
    let length = horizontal.norm();
    (length > 1e-4).then(|| {
        let along = horizontal / length;
        [along, Vec3::new(-along.y, along.x, 0.0), Vec3::new(0.0, 0.0, 1.0)]
    })
}

/// Where a trajectory's frame component of `e − datum` is largest in magnitude.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct LargestError {
    /// Signed, metres.
    pub error_m: f64,
    /// GPS time of the sample.
    pub time_s: f64,
    /// True arc length from the trajectory's first compared sample, metres.
    pub arc_m: f64,
}

/// The largest error of each frame component (`FRAME_COMPONENTS`) of `eval` against `truth` once
/// `datum` is removed, over the samples with GPS times in `within` (first, last); `None` where
/// the trajectory never moves there inside the truth's time span.
pub fn largest_frame_errors(
    eval: &Trajectory,
    truth: &Trajectory,
    datum: [f64; 3],
    within: (f64, f64),
) -> [Option<LargestError>; 3] {
    let datum = Vec3::from(datum);
    let mut largest: [Option<LargestError>; 3] = [None; 3];
    compared_samples(eval, truth, |sample| {
        let Some(basis) = sample.frame.filter(|_| (within.0..=within.1).contains(&sample.time)) else { return };
        for (slot, b) in largest.iter_mut().zip(&basis) {
            let error_m = b.dot(&(sample.error - datum));
            if slot.is_none_or(|l| error_m.abs() > l.error_m.abs()) {
                *slot = Some(LargestError { error_m, time_s: sample.time, arc_m: sample.arc_m });
            }
        }
    });
    largest
}

/// The frame sums ([`FrameSums`], weighted by true arc length) and that length over the samples
/// of `eval` outside `scanned` (first, last GPS time its strips' points span; `None`: no strip,
/// every sample): the run-up and run-out, whose corrections are predicted, not estimated.
pub fn unscanned_frame_sums(eval: &Trajectory, truth: &Trajectory, scanned: Option<(f64, f64)>) -> (FrameSums, f64) {
    let mut sums = FrameSums::default();
    let mut length_m = 0.0;
    compared_samples(eval, truth, |sample| {
        if scanned.is_some_and(|(first, last)| (first..=last).contains(&sample.time)) || sample.step_m <= 0.0 {
            return;
        }
        length_m += sample.step_m;
        if let Some(basis) = &sample.frame {
            sums.add(basis, sample.error, sample.step_m);
        }
    });
    (sums, length_m)
}

/// One sample of `eval` inside the truth's time span.
struct ComparedSample<'a> {
    time: f64,
    true_position: Vec3,
    error: Vec3,
    rotation: &'a Mat3,
    true_rotation: Mat3,
    /// True arc length since the previous compared sample (0 for the first).
    step_m: f64,
    arc_m: f64,
    /// The frame of the last true step that moved (`travel_frame`).
    frame: Option<[Vec3; 3]>,
}

/// Calls `visit` for every sample of `eval` inside the truth's time span, in order; returns the
/// number of samples outside it.
fn compared_samples(eval: &Trajectory, truth: &Trajectory, mut visit: impl FnMut(ComparedSample<'_>)) -> u64 {
    let mut outside = 0;
    let mut last_true_position: Option<Vec3> = None;
    let mut frame = None;
    let mut arc_m = 0.0;
    for ((&t, c), r) in eval.times().iter().zip(eval.positions()).zip(eval.rotations()) {
        let Some(pose) = truth.pose_at(t) else {
            outside += 1;
            continue;
        };
        let step = last_true_position.replace(pose.position).map_or(Vec3::zeros(), |last| pose.position - last);
        frame = travel_frame(step).or(frame);
        let step_m = step.norm();
        arc_m += step_m;
        visit(ComparedSample {
            time: t,
            true_position: pose.position,
            error: c - pose.position,
            rotation: r,
            true_rotation: pose.rotation,
            step_m,
            arc_m,
            frame,
        });
    }
    outside
}

impl TrajectoryErrors {
    pub fn merge(&mut self, other: &Self) {
        self.samples += other.samples;
        self.outside_truth += other.outside_truth;
        self.position_sum_sq += other.position_sum_sq;
        self.rotation_sum_sq_deg += other.rotation_sum_sq_deg;
        (0..3).for_each(|a| self.position_sum_by_length[a] += other.position_sum_by_length[a]);
        self.length_m += other.length_m;
        self.frame.merge(&other.frame);
        self.tilt.merge(&other.tilt);
        self.attitude.merge(&other.attitude);
        (0..3).for_each(|a| self.rotation_sum_by_length[a] += other.rotation_sum_by_length[a]);
    }

    /// Mean attitude error per arc length (a rotation vector in the world frame, degrees): the
    /// campaign's rotation as a whole, which, like the datum, moves every pass and the map
    /// together. NaN without length.
    pub fn mean_rotation_error_deg(&self) -> [f64; 3] {
        self.rotation_sum_by_length.map(|v| v / self.length_m)
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
    out.outside_truth = compared_samples(eval, truth, |sample| {
        out.samples += 1;
        out.position_sum_sq += sample.error.norm_squared();
        // R = R_true·Exp(ω_body), so R·R_trueᵀ = Exp(R_true·ω_body): the error in the world
        // frame, whose components along the true body axes are ω_body's.
        let body = so3_log(&(sample.true_rotation.transpose() * sample.rotation)).map(f64::to_degrees);
        out.rotation_sum_sq_deg += body.norm_squared();
        // The sums weighted by arc length: a standstill weighs nothing.
        if sample.step_m > 0.0 {
            (0..3).for_each(|a| out.position_sum_by_length[a] += sample.error[a] * sample.step_m);
            out.length_m += sample.step_m;
            if let Some(basis) = &sample.frame {
                out.frame.add(basis, sample.error, sample.step_m);
            }
            out.tilt.add(sample.true_position, sample.error.z, sample.step_m);
            let world = sample.true_rotation * body;
            let axes = [0, 1, 2].map(|c| sample.true_rotation.column(c).into_owned());
            out.attitude.add(&axes, world, sample.step_m);
            (0..3).for_each(|a| out.rotation_sum_by_length[a] += world[a] * sample.step_m);
        }
    });
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

    /// Only the poses outside the scanned span count, in the frame of travel (+x here).
    #[test]
    fn unscanned_sums_hold_the_run_up_and_run_out_alone() {
        let truth = line(100.0, 1000, Vec3::zeros(), 0.0);
        // Off by 2 cm along the track in the first second (the run-up), exact after.
        let times: Vec<f64> = (0..1000).map(|i| 100.0 + i as f64 * 0.005).collect();
        let positions = times
            .iter()
            .map(|&t| Vec3::new(549_800.0 + (t - 100.0) * 10.0 + if t < 101.0 { 0.02 } else { 0.0 }, 5_803_400.0, 50.0))
            .collect();
        let rpy = times.iter().map(|t| [0.5, -1.0, 30.0 + (t - 100.0)]).collect();
        let eval = Trajectory::new(times, positions, rpy).unwrap();
        let (sums, length_m) = unscanned_frame_sums(&eval, &truth, Some((101.0, 104.0)));
        // Run-up 100.005–100.995 s and run-out 104.005–104.995 s, 0.05 m per sample.
        assert!((length_m - 2.0 * 199.0 * 0.05).abs() < 1e-6, "{length_m}");
        let rms = sums.rms_without([0.0; 3], length_m);
        assert!((rms[0] - 0.02 / 2f64.sqrt()).abs() < 1e-9 && rms[1] < 1e-9 && rms[2] < 1e-9, "{rms:?}");
        // Without strips every pose is unscanned.
        let (all, all_m) = unscanned_frame_sums(&eval, &truth, None);
        assert!((all_m - 999.0 * 0.05).abs() < 1e-6);
        assert!((all.rms_without([0.0; 3], all_m)[0] - 0.02 * (199.0f64 / 999.0).sqrt()).abs() < 1e-9);
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

    const ALL: (f64, f64) = (f64::NEG_INFINITY, f64::INFINITY);

    #[test]
    fn errors_split_into_the_travel_frame_without_a_datum() {
        let truth = line(100.0, 200, Vec3::zeros(), 0.0);
        // Drives along +x: +x is along-track, +y across (to the left), +z vertical.
        let e = trajectory_errors(&line(100.0, 200, Vec3::new(0.03, -0.02, 0.04), 0.0), &truth);
        let rms = e.frame.rms_without([0.0; 3], e.length_m);
        assert!(
            (rms[0] - 0.03).abs() < 1e-9 && (rms[1] - 0.02).abs() < 1e-9 && (rms[2] - 0.04).abs() < 1e-9,
            "{rms:?}"
        );
        // A constant error is all datum.
        let without = e.frame.rms_without(e.mean_position_error_m(), e.length_m);
        assert!(without.iter().all(|v| *v < 1e-7), "{without:?}");
        // Part of it: what is left per component.
        let partly = e.frame.rms_without([0.01, 0.0, 0.04], e.length_m);
        assert!((partly[0] - 0.02).abs() < 1e-9 && (partly[1] - 0.02).abs() < 1e-9 && partly[2] < 1e-7, "{partly:?}");
        // Driving along +y, an x error lies across the track, to the right.
        let north = |shift: Vec3| {
            let times: Vec<f64> = (0..100).map(|i| 100.0 + i as f64 * 0.005).collect();
            let positions = (0..100).map(|i| Vec3::new(549_800.0, 5_803_400.0 + 0.05 * i as f64, 50.0) + shift);
            Trajectory::new(times, positions.collect(), vec![[0.0, 0.0, 90.0]; 100]).unwrap()
        };
        let e = trajectory_errors(&north(Vec3::new(0.03, 0.0, 0.0)), &north(Vec3::zeros()));
        let largest = largest_frame_errors(&north(Vec3::new(0.03, 0.0, 0.0)), &north(Vec3::zeros()), [0.0; 3], ALL);
        let rms = e.frame.rms_without([0.0; 3], e.length_m);
        assert!(rms[0] < 1e-9 && (rms[1] - 0.03).abs() < 1e-9 && rms[2] < 1e-9, "{rms:?}");
        assert!((largest[1].unwrap().error_m + 0.03).abs() < 1e-9, "{largest:?}");
    }

    /// A drive of `n` samples at 10 m/s on `heading_deg`, each pose's attitude off by the
    /// body-frame rotation `error_deg(i)` (roll, pitch, heading about the vehicle's axes).
    fn drive(heading_deg: f64, n: usize, error_deg: impl Fn(usize) -> [f64; 3]) -> Trajectory {
        use precimap_core::geom::{rot_from_rpy, rpy_from_rot, so3_exp};
        let times: Vec<f64> = (0..n).map(|i| 100.0 + i as f64 * 0.005).collect();
        let (s, c) = heading_deg.to_radians().sin_cos();
        let positions =
            (0..n).map(|i| Vec3::new(549_800.0 + 0.05 * i as f64 * c, 5_803_400.0 + 0.05 * i as f64 * s, 50.0));
        let truth = rot_from_rpy(0.5f64.to_radians(), (-1.0f64).to_radians(), heading_deg.to_radians());
        let rpy = (0..n)
            .map(|i| {
                let r = truth * so3_exp(&Vec3::from(error_deg(i).map(f64::to_radians)));
                let (roll, pitch, yaw) = rpy_from_rot(&r);
                [roll, pitch, yaw].map(f64::to_degrees)
            })
            .collect();
        Trajectory::new(times, positions.collect(), rpy).unwrap()
    }

    #[test]
    fn attitude_errors_split_into_the_vehicles_axes_without_the_campaigns_rotation() {
        // Roll 0.01° and heading ±0.02° alternating every 50 samples, on two headings at right
        // angles (not the axes': a basis transposed by mistake would tell there).
        let error = |i: usize| [0.01, 0.0, if (i / 50).is_multiple_of(2) { 0.02 } else { -0.02 }];
        let mut e = trajectory_errors(&drive(30.0, 200, error), &drive(30.0, 200, |_| [0.0; 3]));
        e.merge(&trajectory_errors(&drive(120.0, 200, error), &drive(120.0, 200, |_| [0.0; 3])));
        let rms = e.attitude.rms_without([0.0; 3], e.length_m);
        assert!((rms[0] - 0.01).abs() < 1e-9 && rms[1] < 1e-9 && (rms[2] - 0.02).abs() < 1e-9, "{rms:?}");
        // The mean rotation in the world frame: the rolls about the two forward axes f₁, f₂
        // average to 0.005·(f₁ + f₂); the heading's ± over 4 × 50 samples per drive nearly cancels.
        let (s, c) = 30f64.to_radians().sin_cos();
        let mean = e.mean_rotation_error_deg();
        assert!((mean[0] - 0.005 * (c - s)).abs() < 1e-4 && (mean[1] - 0.005 * (s + c)).abs() < 1e-4, "{mean:?}");
        assert!(mean[2].abs() < 1e-3, "{mean:?}");
        // Without it each drive keeps its roll less that mean, ±0.005·(f₁ − f₂): 0.005° about
        // its forward axis (roll) and 0.005° about its left one (pitch).
        let without = e.attitude.rms_without(mean, e.length_m);
        assert!((without[0] - 0.005).abs() < 1e-4 && (without[1] - 0.005).abs() < 1e-4, "{without:?}");
        assert!((without[2] - 0.02).abs() < 1e-3, "{without:?}");
        // The per-sample angle agrees with the axes where the weights do (constant speed).
        assert!((e.rotation_rms_deg() - (0.01f64.powi(2) + 0.02f64.powi(2)).sqrt()).abs() < 1e-9);
    }

    #[test]
    fn the_largest_along_track_error_is_found_where_it_is() {
        // A bump of 70 mm along the track, centred 5 m into a 10 m drive (t = 100.5 s).
        let truth = line(100.0, 200, Vec3::zeros(), 0.0);
        let times: Vec<f64> = (0..200).map(|i| 100.0 + i as f64 * 0.005).collect();
        let bump = |t: f64| 0.07 * (-((t - 100.5) / 0.1).powi(2)).exp();
        let positions =
            times.iter().zip(truth.positions()).map(|(&t, p)| p + Vec3::new(bump(t) + 0.01, 0.002, 0.0)).collect();
        let eval = Trajectory::new(times, positions, vec![[0.0, 0.0, 0.0]; 200]).unwrap();
        let [along, across, vertical] = largest_frame_errors(&eval, &truth, [0.01, 0.0, 0.0], ALL);
        // Outside the scanned span it is not looked for.
        let before_it = largest_frame_errors(&eval, &truth, [0.01, 0.0, 0.0], (100.0, 100.4))[0].unwrap();
        assert!(before_it.time_s <= 100.4 && before_it.error_m < 0.07 * 0.5, "{before_it:?}");
        let along = along.unwrap();
        assert!((along.error_m - 0.07).abs() < 1e-9 && (along.time_s - 100.5).abs() < 1e-9, "{along:?}");
        assert!((along.arc_m - 5.0).abs() < 1e-6, "{along:?}");
        assert!((across.unwrap().error_m - 0.002).abs() < 1e-9 && vertical.unwrap().error_m.abs() < 1e-9);
        // A trajectory that never moves has no frame.
        let standing = Trajectory::new(vec![1.0, 2.0], vec![Vec3::zeros(); 2], vec![[0.0; 3]; 2]).unwrap();
        assert_eq!(largest_frame_errors(&standing, &standing, [0.0; 3], ALL), [None; 3]);
        let e = trajectory_errors(&standing, &standing);
        assert!(e.frame.rms_without([0.0; 3], e.length_m).iter().all(|v| v.is_nan()));
    }

    #[test]
    fn a_campaign_tilted_as_a_whole_is_found_across_trajectories() {
        // Two straight legs at right angles (each alone cannot fix a plane), with a vertical
        // error of 20 mm plus 1 mm per metre eastwards: a tilt of atan(0.001) = 57.3 mdeg.
        let leg = |t0: f64, start: Vec3, dir: Vec3, tilted: bool| {
            let times: Vec<f64> = (0..200).map(|i| t0 + i as f64 * 0.005).collect();
            let positions = (0..200)
                .map(|i| {
                    let p = start + dir * (0.05 * i as f64);
                    if tilted {
                        p + Vec3::new(0.0, 0.0, 0.02 + 0.001 * (p.x - 549_800.0))
                    } else {
                        p
                    }
                })
                .collect();
            Trajectory::new(times, positions, vec![[0.0; 3]; 200]).unwrap()
        };
        let east = Vec3::new(549_800.0, 5_803_400.0, 50.0);
        let north = Vec3::new(549_810.0, 5_803_400.0, 50.0);
        let (x, y) = (Vec3::new(1.0, 0.0, 0.0), Vec3::new(0.0, 1.0, 0.0));
        let first = trajectory_errors(&leg(100.0, east, x, true), &leg(100.0, east, x, false));
        let second = trajectory_errors(&leg(200.0, north, y, true), &leg(200.0, north, y, false));
        assert_eq!(first.tilt.plane(), None, "one straight leg fixes no plane");
        let mut both = TrajectoryErrors::default();
        both.merge(&first);
        both.merge(&second);
        let (tilt_deg, rms) = both.tilt.plane().unwrap();
        assert!((tilt_deg - 0.001f64.atan().to_degrees()).abs() < 1e-9, "{tilt_deg}");
        assert!(rms < 1e-6, "{rms}");
        // Without the tilt the vertical error is what lies off the plane: 10 mm on the second leg.
        let bumped = |t0: f64| {
            let l = leg(t0, north, y, true);
            let positions = l.positions().iter().map(|p| p + Vec3::new(0.0, 0.0, 0.01)).collect();
            Trajectory::new(l.times().to_vec(), positions, vec![[0.0; 3]; 200]).unwrap()
        };
        let mut off = TrajectoryErrors::default();
        off.merge(&first);
        off.merge(&trajectory_errors(&bumped(200.0), &leg(200.0, north, y, false)));
        let (_, rms) = off.tilt.plane().unwrap();
        assert!(rms > 0.001 && rms < 0.01, "{rms}");
    }
}
