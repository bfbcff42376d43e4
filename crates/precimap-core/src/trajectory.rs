//! A GNSS/IMU trajectory: poses at (typically 200 Hz) time stamps, interpolated in between, with
//! the cumulative arc length that places anchors.

use crate::geom::{rot_from_rpy, so3_exp, so3_log, Mat3, Vec3};

/// One pose of the body frame in the world (projected CRS) frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Pose {
    pub position: Vec3,
    pub rotation: Mat3,
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum TrajectoryError {
    #[error("trajectory has {0} samples; at least 2 are needed to interpolate")]
    TooShort(usize),
    #[error("sample {index}: time {time} is not after the previous time {previous}; samples must be strictly increasing in time")]
    NotIncreasing { index: usize, time: f64, previous: f64 },
    #[error("sample {index}: {field} is not a finite number")]
    NotFinite { index: usize, field: &'static str },
}

/// Poses at strictly increasing times.
#[derive(Clone, Debug)]
pub struct Trajectory {
    times: Vec<f64>,
    positions: Vec<Vec3>,
    /// roll, pitch, yaw in degrees, exactly as read (kept for lossless round trips).
    rpy_deg: Vec<[f64; 3]>,
    rotations: Vec<Mat3>,
    /// Rotation vector from sample i to i+1 in the body frame: `R_{i+1} = R_i · Exp(ω_i)`.
    segment_rotations: Vec<Vec3>,
    /// Cumulative arc length of the positions, metres.
    arc: Vec<f64>,
}

impl Trajectory {
    pub fn new(times: Vec<f64>, positions: Vec<Vec3>, rpy_deg: Vec<[f64; 3]>) -> Result<Self, TrajectoryError> {
        let n = times.len();
        assert!(positions.len() == n && rpy_deg.len() == n, "trajectory columns differ in length");
        if n < 2 {
            return Err(TrajectoryError::TooShort(n));
        }
        for i in 0..n {
            let t = times[i];
            if !t.is_finite() {
                return Err(TrajectoryError::NotFinite { index: i, field: "time" });
            }
            for (k, name) in ["x", "y", "z"].iter().enumerate() {
                if !positions[i][k].is_finite() {
                    return Err(TrajectoryError::NotFinite { index: i, field: name });
                }
            }
            for (k, name) in ["roll", "pitch", "yaw"].iter().enumerate() {
                if !rpy_deg[i][k].is_finite() {
                    return Err(TrajectoryError::NotFinite { index: i, field: name });
                }
            }
            if i > 0 && t <= times[i - 1] {
                return Err(TrajectoryError::NotIncreasing { index: i, time: t, previous: times[i - 1] });
            }
        }
        let rotations: Vec<Mat3> =
            rpy_deg.iter().map(|a| rot_from_rpy(a[0].to_radians(), a[1].to_radians(), a[2].to_radians())).collect();
        let segment_rotations = rotations.windows(2).map(|w| so3_log(&(w[0].transpose() * w[1]))).collect();
        let mut arc = Vec::with_capacity(n);
        let mut s = 0.0;
        arc.push(0.0);
        for w in positions.windows(2) {
            s += (w[1] - w[0]).norm();
            arc.push(s);
        }
        Ok(Self { times, positions, rpy_deg, rotations, segment_rotations, arc })
    }

    pub fn len(&self) -> usize {
        self.times.len()
    }

    pub fn is_empty(&self) -> bool {
        self.times.is_empty()
    }

    pub fn times(&self) -> &[f64] {
        &self.times
    }

    pub fn positions(&self) -> &[Vec3] {
        &self.positions
    }

    pub fn rpy_deg(&self) -> &[[f64; 3]] {
        &self.rpy_deg
    }

    pub fn rotations(&self) -> &[Mat3] {
        &self.rotations
    }

    /// Per segment i (samples i, i+1), the body-frame rotation vector ω_i with
    /// `R_{i+1} = R_i · Exp(ω_i)`; [`Self::pose_in_segment`] rotates by `Exp(λ·ω_i)`.
    pub fn segment_rotations(&self) -> &[Vec3] {
        &self.segment_rotations
    }

    /// First and last time stamp.
    pub fn time_span(&self) -> (f64, f64) {
        (self.times[0], self.times[self.times.len() - 1])
    }

    /// True when `t` lies within the sampled time span.
    pub fn covers(&self, t: f64) -> bool {
        let (a, b) = self.time_span();
        t >= a && t <= b
    }

    /// Total arc length in metres.
    pub fn length_m(&self) -> f64 {
        self.arc[self.arc.len() - 1]
    }

    /// Segment index `i` and fraction `λ` with `times[i] ≤ t ≤ times[i+1]`; `None` outside the span.
    pub fn locate(&self, t: f64) -> Option<(usize, f64)> {
        if !self.covers(t) {
            return None;
        }
        let i = match self.times.binary_search_by(|x| x.total_cmp(&t)) {
            Ok(i) => i.min(self.times.len() - 2),
            Err(i) => i - 1,
        };
        Some(self.in_segment(i, t))
    }

    /// Segment `i` and the fraction of it at `t`.
    #[inline]
    fn in_segment(&self, i: usize, t: f64) -> (usize, f64) {
        let (t0, t1) = (self.times[i], self.times[i + 1]);
        (i, ((t - t0) / (t1 - t0)).clamp(0.0, 1.0))
    }

    /// [`Self::locate`] trying segment `*hint` first, and leaving the found segment there: O(1)
    /// for the slowly rising times of a strip's points (thousands per segment at 200 Hz), with
    /// the same result as [`Self::locate`] (times rise strictly, so `times[i] ≤ t < times[i+1]`
    /// holds for one segment only, the one its binary search finds).
    #[inline]
    pub fn locate_from(&self, t: f64, hint: &mut usize) -> Option<(usize, f64)> {
        let i = *hint;
        if i + 1 < self.times.len() && self.times[i] <= t && t < self.times[i + 1] {
            return Some(self.in_segment(i, t));
        }
        let found = self.locate(t)?;
        *hint = found.0;
        Some(found)
    }

    /// [`Self::position_at`] through [`Self::locate_from`].
    #[inline]
    pub fn position_at_from(&self, t: f64, hint: &mut usize) -> Option<Vec3> {
        let (i, lambda) = self.locate_from(t, hint)?;
        Some(self.position_in_segment(i, lambda))
    }

    /// Interpolated pose: positions linearly, rotations along the geodesic between samples.
    pub fn pose_at(&self, t: f64) -> Option<Pose> {
        let (i, lambda) = self.locate(t)?;
        Some(self.pose_in_segment(i, lambda))
    }

    /// Interpolated position alone (no rotation): what [`Self::pose_at`] gives as its position.
    pub fn position_at(&self, t: f64) -> Option<Vec3> {
        let (i, lambda) = self.locate(t)?;
        Some(self.position_in_segment(i, lambda))
    }

    fn position_in_segment(&self, i: usize, lambda: f64) -> Vec3 {
        self.positions[i] + (self.positions[i + 1] - self.positions[i]) * lambda
    }

    pub fn pose_in_segment(&self, i: usize, lambda: f64) -> Pose {
        let position = self.position_in_segment(i, lambda);
        let rotation = self.rotations[i] * so3_exp(&(self.segment_rotations[i] * lambda));
        Pose { position, rotation }
    }

    /// Arc length at time `t`, linearly interpolated (metres since the first sample).
    pub fn arc_length_at(&self, t: f64) -> Option<f64> {
        let (i, lambda) = self.locate(t)?;
        Some(self.arc[i] + (self.arc[i + 1] - self.arc[i]) * lambda)
    }

    /// Arc length at every sample (metres since the first sample).
    pub fn arc_lengths(&self) -> &[f64] {
        &self.arc
    }

    /// The segment and the share along it of each of the arc lengths `first·spacing,
    /// (first+1)·spacing, …` (`count` of them; where anchors sit), clamped to the ends. A
    /// trajectory has at least two samples, so there is always a segment.
    fn segments_along(&self, spacing: f64, first: u32, count: usize) -> impl Iterator<Item = (usize, f64)> + '_ {
        let last = self.arc.len() - 1;
        let mut i = 0usize;
        (0..count).map(move |k| {
            let s = (first as f64 + k as f64) * spacing;
            while i + 1 < last && self.arc[i + 1] < s {
                i += 1;
            }
            let (a, b) = (self.arc[i], self.arc[i + 1]);
            (i, if b > a { ((s - a) / (b - a)).clamp(0.0, 1.0) } else { 0.0 })
        })
    }

    /// Position at each of the arc lengths `first·spacing, (first+1)·spacing, …` (`count` of
    /// them; where anchors sit), linearly interpolated and clamped to the ends.
    pub fn positions_along(&self, spacing: f64, first: u32, count: usize) -> Vec<[f64; 3]> {
        self.segments_along(spacing, first, count)
            .map(|(i, lambda)| {
                let p = self.positions[i] + (self.positions[i + 1] - self.positions[i]) * lambda;
                [p.x, p.y, p.z]
            })
            .collect()
    }

    /// The body attitude (a rotation vector, `R = Exp(θ)`) at each of the arc lengths
    /// `first·spacing, (first+1)·spacing, …` (`count` of them; where anchors sit), along the
    /// geodesic between samples as [`Self::pose_in_segment`] interpolates, clamped to the ends;
    /// in the segments [`Self::positions_along`] chooses.
    pub fn attitudes_along(&self, spacing: f64, first: u32, count: usize) -> Vec<[f64; 3]> {
        self.segments_along(spacing, first, count)
            .map(|(i, lambda)| {
                let theta = so3_log(&self.pose_in_segment(i, lambda).rotation);
                [theta.x, theta.y, theta.z]
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn straight() -> Trajectory {
        let times: Vec<f64> = (0..11).map(|i| 100.0 + i as f64 * 0.5).collect();
        let positions = times.iter().map(|t| Vec3::new((t - 100.0) * 10.0, 0.0, 0.0)).collect();
        let rpy = times.iter().map(|t| [0.0, 0.0, (t - 100.0) * 2.0]).collect();
        Trajectory::new(times, positions, rpy).unwrap()
    }

    #[test]
    fn interpolates_position_rotation_and_arc() {
        let tr = straight();
        let p = tr.pose_at(101.25).unwrap();
        assert!((p.position.x - 12.5).abs() < 1e-12);
        let (_, _, yaw) = crate::geom::rpy_from_rot(&p.rotation);
        assert!((yaw.to_degrees() - 2.5).abs() < 1e-9);
        assert!((tr.arc_length_at(101.25).unwrap() - 12.5).abs() < 1e-12);
        assert!(tr.pose_at(99.0).is_none());
        assert!(tr.pose_at(105.0).is_some());
        assert_eq!(tr.length_m(), 50.0);
    }

    /// At an anchor's arc length, the attitude of the pose at the time the trajectory reaches it
    /// (10 m/s, yaw 2°/s: anchor `k` at 0.5 m is at 0.05·k s and 0.1·k°), clamped at the end.
    #[test]
    fn attitudes_along_follow_the_arc_length() {
        let tr = straight();
        let attitudes = tr.attitudes_along(0.5, 7, 100);
        for (i, theta) in attitudes.iter().enumerate() {
            let t = (100.0 + (7 + i) as f64 * 0.05).min(105.0);
            let expected = so3_log(&tr.pose_at(t).unwrap().rotation);
            for a in 0..3 {
                assert!((theta[a] - expected[a]).abs() < 1e-12, "anchor {}: {theta:?}", 7 + i);
            }
        }
        assert!((attitudes[3][2] - 1.0f64.to_radians()).abs() < 1e-12);
    }

    /// From any hint, at sample times, between them, at both ends and outside the span: the
    /// hinted look-up finds what the binary search finds, and leaves its segment as the hint.
    #[test]
    fn locate_from_any_hint_equals_locate() {
        let tr = straight();
        let mut times: Vec<f64> = (0..=44).map(|i| 99.9 + i as f64 * 0.125).collect();
        times.extend(tr.times().to_vec());
        times.extend([104.999_999, 105.0, 105.000_001]);
        for &t in &times {
            for start in [0, 3, 9, 10, 11, 1000] {
                let mut hint = start;
                let found = tr.locate_from(t, &mut hint);
                assert_eq!(found, tr.locate(t), "t {t} from hint {start}");
                assert_eq!(tr.position_at_from(t, &mut hint.clone()), tr.position_at(t), "t {t}");
                if let Some((i, _)) = found {
                    assert_eq!(tr.locate_from(t, &mut hint), found);
                    assert!(hint == i || hint == start, "t {t}: hint {hint}, segment {i}");
                }
            }
        }
    }

    #[test]
    fn rejects_bad_samples() {
        let e = Trajectory::new(vec![0.0, 0.0], vec![Vec3::zeros(); 2], vec![[0.0; 3]; 2]).unwrap_err();
        assert!(matches!(e, TrajectoryError::NotIncreasing { index: 1, .. }));
        let e = Trajectory::new(vec![0.0, 1.0], vec![Vec3::zeros(), Vec3::new(f64::NAN, 0.0, 0.0)], vec![[0.0; 3]; 2])
            .unwrap_err();
        assert_eq!(e, TrajectoryError::NotFinite { index: 1, field: "x" });
        assert_eq!(
            Trajectory::new(vec![0.0], vec![Vec3::zeros()], vec![[0.0; 3]]).unwrap_err(),
            TrajectoryError::TooShort(1)
        );
    }
}
