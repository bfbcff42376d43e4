//! Rotations and small-angle algebra.
//!
//! Conventions (as in the manifest's formats): body frame x forward, y left, z up;
//! `R_world_body = Rz(yaw) · Ry(pitch) · Rx(roll)`, angles in degrees at the file boundary and
//! radians everywhere else.

pub type Vec3 = nalgebra::Vector3<f64>;
pub type Mat3 = nalgebra::Matrix3<f64>;

/// `Rz(yaw) · Ry(pitch) · Rx(roll)`, angles in radians.
pub fn rot_from_rpy(roll: f64, pitch: f64, yaw: f64) -> Mat3 {
    let (sr, cr) = roll.sin_cos();
    let (sp, cp) = pitch.sin_cos();
    let (sy, cy) = yaw.sin_cos();
    Mat3::new(
        cy * cp,
        cy * sp * sr - sy * cr,
        cy * sp * cr + sy * sr,
        sy * cp,
        sy * sp * sr + cy * cr,
        sy * sp * cr - cy * sr,
        -sp,
        cp * sr,
        cp * cr,
    )
}

/// Inverse of [`rot_from_rpy`]: `(roll, pitch, yaw)` in radians, yaw in (−π, π].
pub fn rpy_from_rot(r: &Mat3) -> (f64, f64, f64) {
    let pitch = (-r[(2, 0)]).clamp(-1.0, 1.0).asin();
    let roll = r[(2, 1)].atan2(r[(2, 2)]);
    let yaw = r[(1, 0)].atan2(r[(0, 0)]);
    (roll, pitch, yaw)
}

/// Skew-symmetric matrix `[v]×` with `[v]× w = v × w`.
pub fn skew(v: &Vec3) -> Mat3 {
    Mat3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

/// Rotation matrix `Exp(θ)` of a rotation vector (Rodrigues).
pub fn so3_exp(theta: &Vec3) -> Mat3 {
    let angle2 = theta.norm_squared();
    let k = skew(theta);
    if angle2 < 1e-12 {
        // Second-order series; exact to ~1e-18 here.
        return Mat3::identity() + k + 0.5 * k * k;
    }
    let angle = angle2.sqrt();
    let a = angle.sin() / angle;
    let b = (1.0 - angle.cos()) / angle2;
    Mat3::identity() + a * k + b * k * k
}

/// Rotation vector `Log(R)` (inverse of [`so3_exp`] for angles below π).
pub fn so3_log(r: &Mat3) -> Vec3 {
    let cos = ((r.trace() - 1.0) * 0.5).clamp(-1.0, 1.0);
    let angle = cos.acos();
    let w = Vec3::new(r[(2, 1)] - r[(1, 2)], r[(0, 2)] - r[(2, 0)], r[(1, 0)] - r[(0, 1)]);
    if angle < 1e-7 {
        return 0.5 * w;
    }
    w * (angle / (2.0 * angle.sin()))
}

/// `Exp(θ)·r` without forming the matrix. Below 0.01 rad (pose corrections, one trajectory
/// segment of a vehicle) by the series to the θ⁴ terms, whose remainder (θ⁶/5040) is under double
/// precision; larger angles use Rodrigues.
#[inline]
pub fn rotate_small(theta: [f64; 3], r: [f64; 3]) -> [f64; 3] {
    SmallRotation::new(theta).apply(r)
}

/// `Exp(θ)` ready to rotate several vectors ([`rotate_small`] for each, with the coefficients of
/// the series computed once).
#[derive(Clone, Copy, Debug)]
pub struct SmallRotation {
    theta: [f64; 3],
    a: f64,
    b: f64,
}

impl SmallRotation {
    #[inline]
    pub fn new(theta: [f64; 3]) -> Self {
        let [tx, ty, tz] = theta;
        let angle2 = tx * tx + ty * ty + tz * tz;
        let (a, b) = if angle2 < 1e-4 {
            (1.0 - angle2 / 6.0 * (1.0 - angle2 / 20.0), 0.5 - angle2 / 24.0 * (1.0 - angle2 / 30.0))
        } else {
            let angle = angle2.sqrt();
            (angle.sin() / angle, (1.0 - angle.cos()) / angle2)
        };
        Self { theta, a, b }
    }

    /// `Exp(θ)·r`.
    #[inline]
    pub fn apply(&self, r: [f64; 3]) -> [f64; 3] {
        let [tx, ty, tz] = self.theta;
        let (a, b) = (self.a, self.b);
        // θ × r and θ × (θ × r)
        let c1 = [ty * r[2] - tz * r[1], tz * r[0] - tx * r[2], tx * r[1] - ty * r[0]];
        let c2 = [ty * c1[2] - tz * c1[1], tz * c1[0] - tx * c1[2], tx * c1[1] - ty * c1[0]];
        [r[0] + a * c1[0] + b * c2[0], r[1] + a * c1[1] + b * c2[1], r[2] + a * c1[2] + b * c2[2]]
    }
}

/// `x.floor()`, inlined: on the baseline x86-64 target (no SSE4.1 `roundsd`) `f64::floor` is a
/// libm call, which shows in per-point loops. Equal to `x.floor()` for every finite `x`, and for
/// ±∞ and NaN after the saturating casts callers apply (`as i32`, `as u32`).
#[inline]
pub fn floor(x: f64) -> f64 {
    let t = x as i64 as f64;
    if t > x {
        t - 1.0
    } else {
        t
    }
}

/// `x.ceil()`, inlined like [`floor`] (same range; the sign of a zero result may differ, which
/// the integer casts callers apply do not see).
#[inline]
pub fn ceil(x: f64) -> f64 {
    -floor(-x)
}

/// Wraps an angle in degrees into (−180, 180].
pub fn wrap_deg(a: f64) -> f64 {
    let mut w = a % 360.0;
    if w <= -180.0 {
        w += 360.0;
    } else if w > 180.0 {
        w -= 360.0;
    }
    w
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn inlined_floor_matches_floor() {
        for x in [-2.5, -2.0, -1e-12, -0.0, 0.0, 1e-12, 0.5, 1.0, 3.999_999, 1e15 + 0.5, -1e15 - 0.5, 4.5e15, -7.0] {
            assert_eq!(floor(x), x.floor(), "{x}");
        }
        for x in [f64::INFINITY, f64::NEG_INFINITY, f64::NAN, 1e300, -1e300] {
            assert_eq!(floor(x) as i32, x.floor() as i32, "{x}");
            assert_eq!(floor(x) as u32, x.floor() as u32, "{x}");
        }
    }

    #[test]
    fn inlined_ceil_matches_ceil() {
        for x in [-2.5, -2.0, -1e-12, -0.0, 0.0, 1e-12, 0.5, 1.0, 3.000_001, 1e15 + 0.5, -1e15 - 0.5, 4.5e15, -7.0] {
            assert_eq!(ceil(x) as i64, x.ceil() as i64, "{x}");
            assert!(ceil(x) == x.ceil(), "{x}");
        }
        for x in [f64::INFINITY, f64::NEG_INFINITY, f64::NAN, 1e300, -1e300] {
            assert_eq!(ceil(x) as i32, x.ceil() as i32, "{x}");
            assert_eq!(ceil(x) as u32, x.ceil() as u32, "{x}");
        }
    }

    #[test]
    fn rpy_round_trip() {
        for &(r, p, y) in &[(0.1, -0.2, 2.9), (-1.0, 0.3, -3.0), (0.0, 0.0, 0.0), (0.01, 0.02, 1.5)] {
            let m = rot_from_rpy(r, p, y);
            let (r2, p2, y2) = rpy_from_rot(&m);
            assert!((r - r2).abs() < 1e-12 && (p - p2).abs() < 1e-12 && (y - y2).abs() < 1e-12);
            assert!((m.transpose() * m - Mat3::identity()).norm() < 1e-12);
        }
    }

    #[test]
    fn rpy_matches_axis_composition() {
        let m = rot_from_rpy(0.3, -0.4, 1.1);
        let rx = so3_exp(&Vec3::new(0.3, 0.0, 0.0));
        let ry = so3_exp(&Vec3::new(0.0, -0.4, 0.0));
        let rz = so3_exp(&Vec3::new(0.0, 0.0, 1.1));
        assert!((m - rz * ry * rx).norm() < 1e-12);
    }

    #[test]
    fn exp_log_round_trip_and_series() {
        for th in [Vec3::new(0.3, -0.2, 0.9), Vec3::new(1e-5, 2e-5, -3e-6), Vec3::new(0.0, 0.0, 0.0)] {
            let m = so3_exp(&th);
            assert!((so3_log(&m) - th).norm() < 1e-10);
            let r = Vec3::new(12.0, -3.0, 40.0);
            let a = m * r;
            let b = rotate_small([th.x, th.y, th.z], [r.x, r.y, r.z]);
            assert!((a - Vec3::from(b)).norm() < 1e-9, "{a} vs {b:?}");
        }
        let th = Vec3::new(4e-3, -3e-3, 5e-3);
        let r = Vec3::new(30.0, 10.0, -2.0);
        let exact = so3_exp(&th) * r;
        let series = Vec3::from(rotate_small([th.x, th.y, th.z], [r.x, r.y, r.z]));
        assert!((exact - series).norm() < 1e-9);
    }

    #[test]
    fn wrap() {
        assert_eq!(wrap_deg(190.0), -170.0);
        assert_eq!(wrap_deg(-180.0), 180.0);
        assert_eq!(wrap_deg(45.0), 45.0);
    }
}
