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
    /// The multi-beam spinning head on the roof ([`crate::MultiBeamConfig`]).
    Roof,
}

impl Head {
    pub fn name(self) -> &'static str {
        match self {
            Head::Left => "left",
            Head::Right => "right",
            Head::Roof => "roof",
        }
    }

    /// LAS scanner channel.
    pub fn channel(self) -> u8 {
        match self {
            Head::Left | Head::Roof => 0,
            Head::Right => 1,
        }
    }

    pub fn lever_arm(self, cfg: &SimConfig) -> [f64; 3] {
        match self {
            Head::Left => cfg.scanner.lever_arm_left_m,
            Head::Right => cfg.scanner.lever_arm_right_m,
            Head::Roof => cfg.scanner.multibeam.as_ref().map_or([0.0; 3], |m| m.lever_arm_m),
        }
    }

    /// The heads of the vehicle of `cfg`: the roof head alone when it has a multi-beam head.
    pub fn mounted_on(cfg: &SimConfig) -> &'static [Head] {
        if cfg.scanner.multibeam.is_some() {
            &[Head::Roof]
        } else {
            Self::mounted(cfg.scanner.heads)
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
            Head::Left | Head::Roof => cfg.scanner.azimuth_deg,
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
        // The roof head takes the left head's calibration errors.
        let (bore, arm) = match head {
            Head::Left | Head::Roof => (c.boresight_left_deg, c.lever_arm_left_m),
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

/// What every measurement of a strip shares: the scene, the head and the files.
struct Shooter<'a> {
    cfg: &'a SimConfig,
    town: &'a Town,
    job: &'a StripJob<'a>,
    lever: Vec3,
    miscalibration: Option<Miscalibration>,
    origin: Vec3,
    writer: StripWriter,
    truth: TruthWriter,
    stats: StripStats,
    /// Trajectory segment of the last measurement (both trajectories share their time stamps).
    seg: usize,
}

/// One laser shot: when, which body-frame direction, its random key, and what the LAS record
/// says of it.
struct Shot {
    t: f64,
    d_body: Vec3,
    key: u64,
    scan_angle_deg: f32,
    user_data: u8,
}

impl<'a> Shooter<'a> {
    fn new(cfg: &'a SimConfig, town: &'a Town, job: &'a StripJob<'a>, measurements: u64) -> Result<Self, SimError> {
        let writer = StripWriter::create(
            &job.las_path,
            cfg.origin,
            LAS_SCALE,
            if job.head == Head::Roof { "precimap-sim multi-beam" } else { "precimap-sim VMX-250" },
            concat!("precimap-sim ", env!("CARGO_PKG_VERSION")),
        )?;
        Ok(Self {
            cfg,
            town,
            job,
            lever: Vec3::from(job.head.lever_arm(cfg)),
            miscalibration: Miscalibration::of(cfg, job.head),
            origin: Vec3::from(cfg.origin),
            writer,
            truth: TruthWriter::create(&job.truth_path)?,
            stats: StripStats { id: job.id.clone(), measurements, ..StripStats::default() },
            seg: 0,
        })
    }

    /// Casts the ray of `shot` from the true head and records the hit, if any, with the
    /// measured pose and a noisy range.
    fn shoot(&mut self, shot: &Shot) -> Result<(), SimError> {
        let (sc, job, t) = (&self.cfg.scanner, self.job, shot.t);
        let times = job.truth_traj.times();
        // Locate incrementally: shots come in time order.
        while self.seg + 2 < times.len() && times[self.seg + 1] <= t {
            self.seg += 1;
        }
        let seg = self.seg;
        let lambda = ((t - times[seg]) / (times[seg + 1] - times[seg])).clamp(0.0, 1.0);
        let pose = job.truth_traj.pose_in_segment(seg, lambda);
        let d_body = shot.d_body;
        let head = pose.position + pose.rotation * self.lever;
        let d = pose.rotation * d_body;
        let o = head - self.origin;
        let key = shot.key;
        let Some(hit) = self.town.cast([o.x, o.y, o.z], [d.x, d.y, d.z], sc.max_range_m, key) else {
            return Ok(());
        };
        if hit.t < sc.min_range_m {
            return Ok(());
        }
        let rho = hit.t;
        let noisy = rho + sc.range_noise_m * rng::normal(rng::hash2(key, 0x0015E));
        let p_true = head + d * rho;
        let m = job.measured_traj.pose_in_segment(seg, lambda);
        let p_rec = match &self.miscalibration {
            None => m.position + m.rotation * (self.lever + d_body * noisy),
            Some(c) => {
                let range = noisy * c.range_scale + c.range_offset_m;
                m.position + m.rotation * (c.lever_arm + c.boresight * d_body * range)
            }
        };
        let n = hit.normal;
        let cos_inc = (n[0] * d.x + n[1] * d.y + n[2] * d.z).abs();
        let point = NewPoint {
            position: [p_rec.x, p_rec.y, p_rec.z],
            gps_time: t,
            scan_angle_deg: shot.scan_angle_deg,
            channel: job.head.channel(),
            intensity: intensity(hit.class, hit.surface_id, cos_inc, rho, key),
            return_number: 1,
            number_of_returns: 1,
            point_source_id: job.number,
            classification: 0,
        };
        self.writer.push_with_user_data(&point, shot.user_data)?;
        self.truth.push(&TruthPoint {
            position: [p_true.x, p_true.y, p_true.z],
            normal: [n[0] as f32, n[1] as f32, n[2] as f32],
            surface_id: hit.surface_id,
            class: hit.class,
        })?;
        let stats = &mut self.stats;
        if stats.points == 0 {
            stats.first_time = t;
        }
        stats.last_time = t;
        stats.points += 1;
        stats.class_counts[hit.class as usize] += 1;
        Ok(())
    }

    fn finish(self) -> Result<StripStats, SimError> {
        let written = self.writer.finish()?;
        let truths = self.truth.finish()?;
        debug_assert_eq!(written, self.stats.points);
        debug_assert_eq!(truths, self.stats.points);
        Ok(self.stats)
    }
}

/// Simulates one strip, streaming to its files.
pub(crate) fn run_strip(cfg: &SimConfig, town: &Town, job: &StripJob<'_>) -> Result<StripStats, SimError> {
    if let (Head::Roof, Some(mb)) = (job.head, &cfg.scanner.multibeam) {
        return run_multibeam_strip(cfg, mb, town, job);
    }
    let sc = &cfg.scanner;
    let n_rev = sc.points_per_revolution;
    let dt = 1.0 / (sc.revolutions_per_s * n_rev as f64);
    let count = ((job.t_end - job.t_start) / dt).floor().max(0.0) as u64;
    let dirs = job.head.directions(cfg);
    let strip_key = rng::hash3(cfg.seed, job.pass as u64, job.head.channel() as u64);
    let mut shooter = Shooter::new(cfg, town, job, count)?;
    for k in 0..count {
        let j = (k % n_rev as u64) as u32;
        shooter.shoot(&Shot {
            t: job.t_start + k as f64 * dt,
            d_body: dirs[j as usize],
            key: rng::hash2(strip_key, k),
            scan_angle_deg: scan_angle_deg(j, n_rev) as f32,
            user_data: 0,
        })?;
    }
    shooter.finish()
}

/// Random stream of the roof head (the profile heads use their channels, 0 and 1).
const ROOF_STREAM: u64 = 2;

/// A multi-beam strip: firing `f` at `t_start + f/(rate·F)` measures every laser at azimuth
/// `φ = −180° + (f mod F)·360°/F` about the body's z axis (counter-clockwise from x), laser `l`
/// at its elevation θ: `d = (cos θ cos φ, cos θ sin φ, sin θ)`. The scan angle is φ, the user
/// data l, and all lasers of a firing share its GPS time.
fn run_multibeam_strip(
    cfg: &SimConfig,
    mb: &crate::MultiBeamConfig,
    town: &Town,
    job: &StripJob<'_>,
) -> Result<StripStats, SimError> {
    let per_rev = mb.firings_per_revolution;
    let dt = 1.0 / (mb.revolutions_per_s * per_rev as f64);
    let firings = ((job.t_end - job.t_start) / dt).floor().max(0.0) as u64;
    let rings = mb.rings as u64;
    let elevation: Vec<(f64, f64)> = (0..mb.rings).map(|l| mb.elevation_deg(l).to_radians().sin_cos()).collect();
    let strip_key = rng::hash3(cfg.seed, job.pass as u64, ROOF_STREAM);
    let mut shooter = Shooter::new(cfg, town, job, firings * rings)?;
    for f in 0..firings {
        let phi = scan_angle_deg((f % per_rev as u64) as u32, per_rev);
        let (s, c) = phi.to_radians().sin_cos();
        let t = job.t_start + f as f64 * dt;
        for (l, &(se, ce)) in elevation.iter().enumerate() {
            shooter.shoot(&Shot {
                t,
                d_body: Vec3::new(ce * c, ce * s, se),
                key: rng::hash2(strip_key, f * rings + l as u64),
                scan_angle_deg: phi as f32,
                user_data: l as u8,
            })?;
        }
    }
    shooter.finish()
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
