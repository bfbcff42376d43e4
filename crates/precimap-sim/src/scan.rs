//! The scan heads: one strip per head and pass, streamed measurement by measurement to its LAS/LAZ
//! file and its truth file.
//!
//! Measurement `k` of a strip happens at `t_k = t_start + k/(f·N)` with scan angle
//! `φ = −180° + (k mod N)·360°/N`; its body-frame direction is `sin φ·a − cos φ·z` (a = the
//! head's horizontal scan-plane direction), so φ = 0 points down and ±180° up, where the sky is
//! and the revolution's seam does no harm. The ray is cast from the TRUE scan-head position; the
//! point is recorded with the ERRONEOUS (measured) pose and a noisy range:
//! `p_rec = c_err + R_err·(ℓ + (ρ + ε)·d_body)`.

use crate::config::SimConfig;
use crate::rng;
use crate::town::Town;
use crate::truth::{SurfaceClass, TruthPoint, TruthWriter};
use crate::SimError;
use precimap_core::{Trajectory, Vec3};
use precimap_formats::{NewPoint, StripWriter};
use std::path::PathBuf;

/// LAS coordinate resolution.
pub const LAS_SCALE: f64 = 1e-4;

/// A scan head.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Head {
    Left,
    Right,
}

impl Head {
    pub fn name(self) -> &'static str {
        match self {
            Head::Left => "left",
            Head::Right => "right",
        }
    }

    /// LAS scanner channel.
    pub fn channel(self) -> u8 {
        match self {
            Head::Left => 0,
            Head::Right => 1,
        }
    }

    pub fn lever_arm(self, cfg: &SimConfig) -> [f64; 3] {
        match self {
            Head::Left => cfg.scanner.lever_arm_left_m,
            Head::Right => cfg.scanner.lever_arm_right_m,
        }
    }

    /// The heads of a vehicle with `heads` of them (1: the left one alone).
    pub fn mounted(heads: u32) -> &'static [Head] {
        if heads == 1 {
            &[Head::Left]
        } else {
            &[Head::Left, Head::Right]
        }
    }

    /// Body-frame unit direction of every measurement of a revolution.
    pub fn directions(self, cfg: &SimConfig) -> Vec<Vec3> {
        let n = cfg.scanner.points_per_revolution;
        let az = match self {
            Head::Left => cfg.scanner.azimuth_deg,
            Head::Right => -cfg.scanner.azimuth_deg,
        }
        .to_radians();
        (0..n)
            .map(|j| {
                let (s, c) = scan_angle_deg(j, n).to_radians().sin_cos();
                Vec3::new(s * az.cos(), s * az.sin(), -c)
            })
            .collect()
    }
}

/// Scan angle of measurement `j` of a revolution of `n`, degrees in [−180, 180).
pub fn scan_angle_deg(j: u32, n: u32) -> f64 {
    -180.0 + j as f64 * 360.0 / n as f64
}

/// One strip to simulate.
#[derive(Debug)]
pub(crate) struct StripJob<'a> {
    pub id: String,
    pub number: u16,
    pub head: Head,
    pub pass: u32,
    pub truth_traj: &'a Trajectory,
    pub measured_traj: &'a Trajectory,
    pub t_start: f64,
    pub t_end: f64,
    pub las_path: PathBuf,
    pub truth_path: PathBuf,
}

/// What a strip came out as.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct StripStats {
    pub id: String,
    pub measurements: u64,
    pub points: u64,
    /// Points per [`SurfaceClass`] (index = class code).
    #[serde(skip)]
    pub class_counts: [u64; 9],
    pub first_time: f64,
    pub last_time: f64,
}

/// Plausible 16-bit intensity: a reflectance per surface, Lambertian-ish incidence falloff, range
/// falloff and 5 % speckle.
fn intensity(class: SurfaceClass, surface_id: u32, cos_incidence: f64, range: f64, key: u64) -> u16 {
    let base = match class {
        SurfaceClass::Road => 0.18,
        SurfaceClass::Sidewalk => 0.30,
        SurfaceClass::Curb => 0.35,
        SurfaceClass::Facade => 0.45,
        SurfaceClass::Pole => 0.40,
        SurfaceClass::Car => 0.55,
        SurfaceClass::Roof => 0.25,
        SurfaceClass::Foliage => 0.22,
    };
    let per_surface = 0.75 + 0.5 * rng::unit(rng::hash2(0x1A7E, surface_id as u64));
    let speckle = 1.0 + 0.05 * rng::normal(rng::hash2(key, 0x5BEC));
    let v = base * per_surface * (0.25 + 0.75 * cos_incidence) / (1.0 + (range / 40.0).powi(2)) * speckle;
    (v * 65535.0).clamp(1.0, 65535.0) as u16
}

/// How a head's points are recorded when its calibration is off
/// ([`crate::config::CalibrationErrors`]): `p = c + R·(ℓ + δℓ + R_b·d·(ρ·(1 + s) + o))`.
struct Miscalibration {
    lever_arm: Vec3,
    boresight: precimap_core::geom::Mat3,
    range_scale: f64,
    range_offset_m: f64,
}

impl Miscalibration {
    fn of(cfg: &SimConfig, head: Head) -> Option<Self> {
        let c = &cfg.errors.calibration;
        if c.is_none() {
            return None;
        }
        let (bore, arm) = match head {
            Head::Left => (c.boresight_left_deg, c.lever_arm_left_m),
            Head::Right => (c.boresight_right_deg, c.lever_arm_right_m),
        };
        let [r, p, y] = bore.map(f64::to_radians);
        Some(Self {
            lever_arm: Vec3::from(head.lever_arm(cfg)) + Vec3::from(arm),
            boresight: precimap_core::geom::rot_from_rpy(r, p, y),
            range_scale: 1.0 + c.range_scale_ppm * 1e-6,
            range_offset_m: c.range_offset_m,
        })
    }
}

/// Simulates one strip, streaming to its files.
pub(crate) fn run_strip(cfg: &SimConfig, town: &Town, job: &StripJob<'_>) -> Result<StripStats, SimError> {
    let sc = &cfg.scanner;
    let n_rev = sc.points_per_revolution;
    let dt = 1.0 / (sc.revolutions_per_s * n_rev as f64);
    let count = ((job.t_end - job.t_start) / dt).floor().max(0.0) as u64;
    let dirs = job.head.directions(cfg);
    let lever = Vec3::from(job.head.lever_arm(cfg));
    let miscalibration = Miscalibration::of(cfg, job.head);
    let origin = Vec3::from(cfg.origin);
    let strip_key = rng::hash3(cfg.seed, job.pass as u64, job.head.channel() as u64);
    let mut writer = StripWriter::create(
        &job.las_path,
        cfg.origin,
        LAS_SCALE,
        "precimap-sim VMX-250",
        concat!("precimap-sim ", env!("CARGO_PKG_VERSION")),
    )?;
    let mut truth = TruthWriter::create(&job.truth_path)?;
    let times = job.truth_traj.times();
    let mut seg = 0usize;
    let mut stats = StripStats { id: job.id.clone(), measurements: count, ..StripStats::default() };
    for k in 0..count {
        let t = job.t_start + k as f64 * dt;
        // Both trajectories share their time stamps: locate once, incrementally.
        while seg + 2 < times.len() && times[seg + 1] <= t {
            seg += 1;
        }
        let lambda = ((t - times[seg]) / (times[seg + 1] - times[seg])).clamp(0.0, 1.0);
        let pose = job.truth_traj.pose_in_segment(seg, lambda);
        let j = (k % n_rev as u64) as u32;
        let d_body = dirs[j as usize];
        let head = pose.position + pose.rotation * lever;
        let d = pose.rotation * d_body;
        let o = head - origin;
        let key = rng::hash2(strip_key, k);
        let Some(hit) = town.cast([o.x, o.y, o.z], [d.x, d.y, d.z], sc.max_range_m, key) else {
            continue;
        };
        if hit.t < sc.min_range_m {
            continue;
        }
        let rho = hit.t;
        let noisy = rho + sc.range_noise_m * rng::normal(rng::hash2(key, 0x0015E));
        let p_true = head + d * rho;
        let m = job.measured_traj.pose_in_segment(seg, lambda);
        let p_rec = match &miscalibration {
            None => m.position + m.rotation * (lever + d_body * noisy),
            Some(c) => {
                let range = noisy * c.range_scale + c.range_offset_m;
                m.position + m.rotation * (c.lever_arm + c.boresight * d_body * range)
            }
        };
        let n = hit.normal;
        let cos_inc = (n[0] * d.x + n[1] * d.y + n[2] * d.z).abs();
        writer.push(&NewPoint {
            position: [p_rec.x, p_rec.y, p_rec.z],
            gps_time: t,
            scan_angle_deg: scan_angle_deg(j, n_rev) as f32,
            channel: job.head.channel(),
            intensity: intensity(hit.class, hit.surface_id, cos_inc, rho, key),
            return_number: 1,
            number_of_returns: 1,
            point_source_id: job.number,
            classification: 0,
        })?;
        truth.push(&TruthPoint {
            position: [p_true.x, p_true.y, p_true.z],
            normal: [n[0] as f32, n[1] as f32, n[2] as f32],
            surface_id: hit.surface_id,
            class: hit.class,
        })?;
        if stats.points == 0 {
            stats.first_time = t;
        }
        stats.last_time = t;
        stats.points += 1;
        stats.class_counts[hit.class as usize] += 1;
    }
    let written = writer.finish()?;
    let truths = truth.finish()?;
    debug_assert_eq!(written, stats.points);
    debug_assert_eq!(truths, stats.points);
    Ok(stats)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::Scale;

    #[test]
    fn scan_geometry() {
        let cfg = SimConfig::for_scale(Scale::Small, 1);
        let n = cfg.scanner.points_per_revolution;
        assert_eq!(scan_angle_deg(0, n), -180.0);
        assert_eq!(scan_angle_deg(n / 2, n), 0.0);
        // Exactly representable in LAS units of 0.006°.
        for j in 0..n {
            let units = scan_angle_deg(j, n) / 0.006;
            assert!((units - units.round()).abs() < 1e-9);
        }
        let left = Head::Left.directions(&cfg);
        let right = Head::Right.directions(&cfg);
        // Straight down at φ = 0, up at −180°.
        assert!((left[(n / 2) as usize] - Vec3::new(0.0, 0.0, -1.0)).norm() < 1e-12);
        assert!((left[0] - Vec3::new(0.0, 0.0, 1.0)).norm() < 1e-12);
        // At +90° the left head looks forward-left, the right head forward-right: an X on the ground.
        let q = (3 * n / 4) as usize;
        let h = std::f64::consts::FRAC_1_SQRT_2;
        assert!((left[q] - Vec3::new(h, h, 0.0)).norm() < 1e-12);
        assert!((right[q] - Vec3::new(h, -h, 0.0)).norm() < 1e-12);
        // Every direction lies in its head's plane (contains z and the azimuth direction).
        for d in &left {
            assert!((d.dot(&Vec3::new(h, -h, 0.0))).abs() < 1e-12 && (d.norm() - 1.0).abs() < 1e-12);
        }
    }
}
