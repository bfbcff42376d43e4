//! Simulated mobile-mapping campaigns that know their truth.
//!
//! [`simulate`] builds a small town ([`town`]) on a gentle slope, drives a two-headed
//! VMX-250-like scanner (or one multi-beam head on the roof, [`MultiBeamConfig`]) through it on
//! figure-8 passes ([`drive`]), georeferences every laser hit
//! with an erroneous GNSS/IMU trajectory ([`gnss`]) and writes a campaign in the public formats
//! plus everything the estimation must never see:
//!
//! ```text
//! DIR/manifest.json                    scanners left/right, one trajectory per pass, two strips
//!                                      each; the surveyed control targets with `SimConfig::control`
//! DIR/trajectories/v01.csv             MEASURED trajectory (200 Hz)
//! DIR/strips/v01-left.las|laz          LAS 1.4 point format 6, acquisition order
//! DIR/truth/v01-left.truth             per point: true position, normal, surface id, class
//! DIR/truth/trajectories/v01.csv       TRUE trajectory, same time stamps
//! DIR/truth/truth.json                 seed, config, σ_range, per-pass error statistics, the
//!                                      outage and the stop, point counts per class and strip,
//!                                      the control targets' true and surveyed positions
//! ```
//!
//! Everything is a pure function of the [`SimConfig`] (including its seed): files are identical
//! for any number of threads.

pub mod config;
pub mod control;
pub mod drive;
pub mod field;
pub mod gnss;
pub mod process;
pub mod rng;
pub mod scan;
pub mod scenario;
pub mod town;
pub mod truth;

pub use config::{
    CalibrationErrors, ControlConfig, DriveConfig, ErrorConfig, ErrorProcess, MultiBeamConfig, ParseScaleError, Scale,
    ScannerConfig, SimConfig, TownConfig,
};
pub use gnss::{ErrorStats, Outage};
pub use scan::Head;
pub use scenario::{ErrorModel, Scenario, Scene};
pub use town::Town;
pub use truth::{SurfaceClass, TruthPoint, TruthReader, TruthWriter};

use precimap_core::{Parameters, Trajectory, TrajectoryError};
use precimap_formats::{FormatError, Manifest, ScannerSpec, StripRef, TrajectoryRef};
use rayon::prelude::*;
use serde::Serialize;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

#[derive(Debug, thiserror::Error)]
pub enum SimError {
    #[error("invalid simulation config: {}", .0.join("; "))]
    Config(Vec<String>),
    #[error("{}: {source}", path.display())]
    Io { path: PathBuf, source: std::io::Error },
    #[error(transparent)]
    Format(#[from] FormatError),
    #[error(transparent)]
    Truth(#[from] truth::TruthError),
    #[error("trajectory {id}: {source}")]
    Trajectory { id: String, source: TrajectoryError },
    #[error("{}: {source}", path.display())]
    Json { path: PathBuf, source: serde_json::Error },
}

/// What [`simulate`] produced.
#[derive(Clone, Debug, Serialize)]
pub struct SimSummary {
    pub points: u64,
    /// Laser shots fired (points plus shots without a return within range).
    pub measurements: u64,
    pub strips: usize,
    pub trajectories: usize,
    pub seconds_driven: f64,
    pub metres_driven: f64,
    pub points_per_class: BTreeMap<String, u64>,
    /// Control and check targets by kind (all zero without control).
    pub control_targets: control::TargetCounts,
    /// Wall-clock time of the simulation (not part of any file).
    pub wall_seconds: f64,
}

/// One trajectory in `truth.json`.
#[derive(Clone, Debug, Serialize)]
pub struct TrajectoryTruth {
    pub id: String,
    pub uri: String,
    pub truth_uri: String,
    pub plan: drive::PassPlan,
    pub start_time: f64,
    pub end_time: f64,
    pub samples: usize,
    pub duration_s: f64,
    pub length_m: f64,
    /// Standstill at the traffic light, GPS seconds.
    pub stop: Option<[f64; 2]>,
    pub outage: Option<Outage>,
    pub errors: ErrorStats,
}

/// One strip in `truth.json`.
#[derive(Clone, Debug, Serialize)]
pub struct StripTruth {
    pub id: String,
    pub trajectory: String,
    pub scanner: Head,
    pub channel: u8,
    pub point_source_id: u16,
    pub uri: String,
    pub truth_uri: String,
    pub measurements: u64,
    pub points: u64,
    pub first_time: f64,
    pub last_time: f64,
    pub points_per_class: BTreeMap<String, u64>,
}

#[derive(Clone, Debug, Serialize)]
struct NamedWindow {
    trajectory: String,
    start: f64,
    end: f64,
}

/// `truth/truth.json`.
#[derive(Clone, Debug, Serialize)]
struct TruthJson<'a> {
    format: &'static str,
    seed: u64,
    scale: Scale,
    range_noise_sigma_m: f64,
    origin: [f64; 3],
    town: town::TownStats,
    points: u64,
    measurements: u64,
    points_per_class: BTreeMap<String, u64>,
    outage: Option<NamedWindow>,
    stop: Option<NamedWindow>,
    trajectories: Vec<TrajectoryTruth>,
    strips: Vec<StripTruth>,
    /// The true and surveyed positions of the control and check targets.
    #[serde(skip_serializing_if = "Option::is_none")]
    control: Option<Vec<control::TargetTruth>>,
    config: &'a SimConfig,
}

struct PassOutput {
    trajectory: TrajectoryTruth,
    strips: Vec<(StripTruth, scan::StripStats)>,
}

fn class_map(counts: &[u64; 9]) -> BTreeMap<String, u64> {
    (1..9u8).filter_map(|c| SurfaceClass::from_u8(c).map(|k| (k.name().to_string(), counts[c as usize]))).collect()
}

fn create_dir(path: &Path) -> Result<(), SimError> {
    std::fs::create_dir_all(path).map_err(|source| SimError::Io { path: path.to_path_buf(), source })
}

fn write_json(path: &Path, value: &impl Serialize) -> Result<(), SimError> {
    let text = serde_json::to_string_pretty(value).map_err(|source| SimError::Json { path: path.into(), source })?;
    std::fs::write(path, text + "\n").map_err(|source| SimError::Io { path: path.into(), source })
}

/// Simulates pass `index`: its true and measured trajectories and both strips.
fn simulate_pass(cfg: &SimConfig, town: &Town, index: u32, out: &Path, laz: bool) -> Result<PassOutput, SimError> {
    let plan = drive::PassPlan::new(cfg, &town.layout(), index);
    let id = plan.id.clone();
    let tp = drive::true_pass(cfg, town, plan);
    let errors = gnss::pass_errors(&cfg.errors, cfg.seed, index, &tp.times, &tp.speeds);
    let measured_pos: Vec<_> = tp
        .positions
        .iter()
        .zip(&errors.position)
        .map(|(p, e)| precimap_core::Vec3::new(p.x + e[0], p.y + e[1], p.z + e[2]))
        .collect();
    let measured_rpy: Vec<[f64; 3]> = tp
        .rpy_deg
        .iter()
        .zip(&errors.rpy_deg)
        .map(|(a, e)| [a[0] + e[0], a[1] + e[1], precimap_core::geom::wrap_deg(a[2] + e[2])])
        .collect();
    let uri = format!("trajectories/{id}.csv");
    let truth_uri = format!("truth/trajectories/{id}.csv");
    precimap_formats::write_trajectory_csv(&out.join(&uri), &tp.times, &measured_pos, &measured_rpy)?;
    precimap_formats::write_trajectory_csv(&out.join(&truth_uri), &tp.times, &tp.positions, &tp.rpy_deg)?;
    let traj_err = |source| SimError::Trajectory { id: id.clone(), source };
    let (t0, t1) = (tp.times[0], tp.times[tp.times.len() - 1]);
    let truth_traj = Trajectory::new(tp.times.clone(), tp.positions.clone(), tp.rpy_deg.clone()).map_err(traj_err)?;
    let measured_traj = Trajectory::new(tp.times.clone(), measured_pos, measured_rpy).map_err(traj_err)?;
    let ext = if laz { "laz" } else { "las" };
    let jobs: Vec<scan::StripJob<'_>> = Head::mounted_on(cfg)
        .iter()
        .map(|&head| {
            let sid = format!("{id}-{}", head.name());
            scan::StripJob {
                number: (2 * index + head.channel() as u32 + 1) as u16,
                head,
                pass: index,
                truth_traj: &truth_traj,
                measured_traj: &measured_traj,
                t_start: t0 + cfg.drive.strip_margin_s,
                t_end: t1 - cfg.drive.strip_margin_s,
                las_path: out.join(format!("strips/{sid}.{ext}")),
                truth_path: out.join(format!("truth/{sid}.truth")),
                id: sid,
            }
        })
        .collect();
    let results: Vec<Result<scan::StripStats, SimError>> =
        jobs.par_iter().map(|job| scan::run_strip(cfg, town, job)).collect();
    let mut strips = Vec::new();
    for (job, stats) in jobs.iter().zip(results) {
        let stats = stats?;
        strips.push((
            StripTruth {
                id: job.id.clone(),
                trajectory: id.clone(),
                scanner: job.head,
                channel: job.head.channel(),
                point_source_id: job.number,
                uri: format!("strips/{}.{ext}", job.id),
                truth_uri: format!("truth/{}.truth", job.id),
                measurements: stats.measurements,
                points: stats.points,
                first_time: stats.first_time,
                last_time: stats.last_time,
                points_per_class: class_map(&stats.class_counts),
            },
            stats,
        ));
    }
    let trajectory = TrajectoryTruth {
        id,
        uri,
        truth_uri,
        start_time: t0,
        end_time: t1,
        samples: tp.times.len(),
        duration_s: t1 - t0,
        length_m: tp.length_m,
        stop: tp.stop.map(|(a, b)| [a, b]),
        outage: errors.outage,
        errors: errors.stats,
        plan: tp.plan,
    };
    Ok(PassOutput { trajectory, strips })
}

/// Simulates the campaign of `config` into the folder `out` (created if missing; existing files
/// of the same names are overwritten). Strips are LAZ when `laz`. Passes run in parallel on the
/// current rayon pool; each strip streams to disk, so memory stays bounded at any scale.
pub fn simulate(config: &SimConfig, out: &Path, laz: bool) -> Result<SimSummary, SimError> {
    let started = Instant::now();
    let problems = config.problems();
    if !problems.is_empty() {
        return Err(SimError::Config(problems));
    }
    for dir in ["strips", "trajectories", "truth/trajectories"] {
        create_dir(&out.join(dir))?;
    }
    let town = Town::build(&config.town, config.seed);
    tracing::info!(stats = ?town.stats(), "town built");
    let targets = config.control.as_ref().map(|_| control::place_targets(config, &town));
    let passes: Vec<PassOutput> = (0..config.drive.passes)
        .into_par_iter()
        .map(|p| {
            let r = simulate_pass(config, &town, p, out, laz);
            if let Ok(o) = &r {
                let pts: u64 = o.strips.iter().map(|s| s.0.points).sum();
                tracing::info!(pass = %o.trajectory.id, points = pts, "pass simulated");
            }
            r
        })
        .collect::<Result<_, _>>()?;

    let mut counts = [0u64; 9];
    let mut measurements = 0;
    let mut trajectories = Vec::new();
    let mut strips = Vec::new();
    for p in passes {
        trajectories.push(p.trajectory);
        for (truth, stats) in p.strips {
            for (c, n) in counts.iter_mut().zip(stats.class_counts) {
                *c += n;
            }
            measurements += stats.measurements;
            strips.push(truth);
        }
    }
    let points: u64 = strips.iter().map(|s| s.points).sum();

    let manifest = Manifest {
        name: config.name.clone(),
        crs: None,
        gps_week: None,
        scanners: Head::mounted_on(config)
            .iter()
            .map(|&h| (h.name().to_string(), ScannerSpec { lever_arm_m: h.lever_arm(config), boresight_deg: [0.0; 3] }))
            .collect(),
        trajectories: trajectories.iter().map(|t| TrajectoryRef::csv(t.id.clone(), t.uri.clone())).collect(),
        strips: strips
            .iter()
            .map(|s| StripRef {
                id: s.id.clone(),
                trajectory: s.trajectory.clone(),
                scanner: s.scanner.name().to_string(),
                uri: s.uri.clone(),
            })
            .collect(),
        parameters: Parameters::default(),
        control: config.control.as_ref().zip(targets.as_ref()).map(|(c, t)| control::manifest_control(t, c.sigma_m)),
    };
    // Default parameters are left out, so the campaign follows whatever the estimator's defaults are;
    // a multi-beam head's strips say where their ring numbers are.
    let manifest_path = out.join("manifest.json");
    let mut value =
        serde_json::to_value(&manifest).map_err(|source| SimError::Json { path: manifest_path.clone(), source })?;
    if let Some(obj) = value.as_object_mut() {
        obj.remove("parameters");
        if config.scanner.multibeam.is_some() {
            obj.insert("parameters".into(), serde_json::json!({ "ring": "user_data" }));
        }
    }
    write_json(&manifest_path, &value)?;

    let window = |f: &dyn Fn(&TrajectoryTruth) -> Option<[f64; 2]>| {
        trajectories.iter().find_map(|t| f(t).map(|[start, end]| NamedWindow { trajectory: t.id.clone(), start, end }))
    };
    let summary = SimSummary {
        points,
        measurements,
        strips: strips.len(),
        trajectories: trajectories.len(),
        seconds_driven: trajectories.iter().map(|t| t.duration_s).sum(),
        metres_driven: trajectories.iter().map(|t| t.length_m).sum(),
        points_per_class: class_map(&counts),
        control_targets: control::TargetCounts::of(targets.as_deref().unwrap_or_default()),
        wall_seconds: 0.0,
    };
    let truth = TruthJson {
        format: "precimap-sim-truth/1",
        seed: config.seed,
        scale: config.scale,
        range_noise_sigma_m: config.scanner.range_noise_m,
        origin: config.origin,
        town: town.stats(),
        points,
        measurements,
        points_per_class: summary.points_per_class.clone(),
        outage: window(&|t| t.outage.map(|o| [o.start, o.end])),
        stop: window(&|t| t.stop),
        trajectories,
        strips,
        control: targets,
        config,
    };
    write_json(&out.join("truth/truth.json"), &truth)?;
    Ok(SimSummary { wall_seconds: started.elapsed().as_secs_f64(), ..summary })
}
