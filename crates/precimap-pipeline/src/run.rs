//! The in-process driver: prepare every strip, iterate map (tiles) and reduce (trajectories)
//! on the schedule, export. Parallel with rayon; deterministic (results are combined in a fixed
//! order, independent of the thread count).

use crate::calibration::CalibrationState;
use crate::campaign::Campaign;
use crate::control_report::ControlReport;
use crate::error::PipelineError;
use crate::report::{IterationReport, Report, StripReport, Timings, TrajectoryReport};
use crate::tasks::{
    anchor_positions, estimate_tile_task, export_strip_task, export_trajectory_task, prepare_strip_task,
    solve_trajectory_task, Gather, LATENT_DIR,
};
use precimap_core::corrections::{AnchorCovariance, TrajectoryCorrections};
use precimap_core::TileKey;
use precimap_estimate::anderson::AndersonHistory;
use precimap_estimate::{
    solve_field, CalibrationNormals, CurvatureModel, FieldSolution, FieldTrajectory, LatentGather, LatentStdMap,
    TileStats,
};
use rayon::prelude::*;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

#[derive(Clone, Debug)]
pub struct RunOptions {
    pub out_dir: PathBuf,
    /// Keep the tile chunks in `OUT/work` after the run.
    pub keep_work: bool,
    /// After the last iteration, run one more map pass over the final corrections and write the
    /// surface model every point was compared with to `OUT/assignments` (QC: `evaluate` measures
    /// the share of wrong assignments against the simulator's true surfaces).
    pub assignments: bool,
}

/// What the driver reports while it works.
// A few events per iteration: the iteration's report unboxed costs nothing worth a box.
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Debug)]
pub enum Progress {
    Loaded { strips: usize, trajectories: usize },
    Prepared { done: usize, total: usize },
    Iteration(IterationReport, usize),
    Exported { done: usize, total: usize },
}

/// The campaign's state after preparation: which strips each tile holds and every trajectory's
/// anchor range (and its anchors' positions, where the common-mode field and the campaign's
/// motion act).
#[derive(Debug)]
pub struct Prepared {
    pub tiles: BTreeMap<TileKey, Vec<usize>>,
    pub anchor_ranges: Vec<(u32, u32)>,
    pub anchor_positions: Vec<Vec<[f64; 3]>>,
    /// Each anchor's own prior weights, for trajectories with an accuracy file
    /// ([`crate::prior`]).
    pub anchor_priors: Vec<Option<Vec<[f64; 6]>>>,
    pub strips: Vec<StripReport>,
    pub points_total: u64,
}

pub fn prepare_all(
    campaign: &Campaign,
    work: &Path,
    progress: &(dyn Fn(Progress) + Sync),
) -> Result<Prepared, PipelineError> {
    let done = std::sync::atomic::AtomicUsize::new(0);
    let total = campaign.strips.len();
    let outcomes: Vec<_> = (0..total)
        .into_par_iter()
        .map(|s| {
            let r = prepare_strip_task(campaign, s, work);
            let d = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
            progress(Progress::Prepared { done: d, total });
            r
        })
        .collect::<Result<_, _>>()?;
    let mut tiles: BTreeMap<TileKey, Vec<usize>> = BTreeMap::new();
    let mut anchor_ranges = vec![(u32::MAX, 0u32); campaign.trajectories.len()];
    let mut strips = Vec::with_capacity(total);
    let mut points_total = 0;
    for (s, outcome) in outcomes.into_iter().enumerate() {
        let entry = &campaign.strips[s];
        let range = &mut anchor_ranges[entry.trajectory as usize];
        range.0 = range.0.min(outcome.stats.first_anchor);
        range.1 = range.1.max(outcome.stats.last_anchor);
        for t in &outcome.tiles {
            tiles.entry(*t).or_default().push(s);
        }
        points_total += outcome.stats.points;
        strips.push(StripReport::new(&entry.id, &outcome.stats, outcome.tiles.len()));
    }
    let ids: Vec<&str> = campaign.strips.iter().map(|s| s.id.as_str()).collect();
    if let Some(problem) = overlap_problem(tiles.len(), None, &ids) {
        if !campaign.params.allow_low_usable_share {
            return Err(PipelineError::Input { what: format!("campaign {}", campaign.name), message: problem });
        }
        tracing::warn!("campaign {}: {problem}", campaign.name);
    }
    // A trajectory without strips keeps one zero anchor (it is exported unchanged).
    for r in &mut anchor_ranges {
        if r.0 == u32::MAX {
            *r = (0, 0);
        }
    }
    let anchor_positions = campaign
        .trajectories
        .iter()
        .zip(&anchor_ranges)
        .map(|(t, &range)| anchor_positions(t, campaign.params.anchor_spacing_m, range))
        .collect();
    let anchor_priors = crate::prior::anchor_priors(&campaign.trajectories, &campaign.params, &anchor_ranges)?;
    Ok(Prepared { tiles, anchor_ranges, anchor_positions, anchor_priors, strips, points_total })
}

/// What one iteration produced.
#[derive(Debug)]
pub struct Iterated {
    pub solutions: Vec<precimap_estimate::TrajectorySolution>,
    pub stats: TileStats,
    /// The common-mode field, in steps that solve it.
    pub field: Option<FieldSolution>,
    /// The corrections the per-trajectory solves started from: the input corrections plus the
    /// field (the input itself without one). Momentum measures the next step from these.
    pub started_from: Vec<TrajectoryCorrections>,
    /// Every tile's latent-map standard deviation (QC), in tile order; empty unless asked for.
    pub latent_std: Vec<(TileKey, LatentStdMap)>,
}

/// Where an iteration stands in a run, which decides what it reports besides the corrections.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Place {
    /// The run's first iteration: its latent map's σ is kept (QC, before any correction).
    pub first: bool,
    /// The schedule's last step, where every run ends (early convergence jumps to it): the
    /// corrections' posterior σ, the latent map's σ and the latent map itself are reported.
    pub last: bool,
}

impl Place {
    /// What the iteration gathers of the latent map: its standard deviation (QC) in the first
    /// and the last iteration, the map itself (a product) in the last; every other iteration
    /// runs the estimation without either (the framework's planner asks the same).
    pub fn latent_gather(self) -> LatentGather {
        LatentGather { std_map: self.first || self.last, map: self.last }
    }
}

/// One iteration: every tile's map task, then (in steps that solve it) the common-mode field,
/// then every trajectory's reduce task, and with `calibration` the calibration's step from
/// every trajectory's share. `process`: every trajectory's own curvature σ's, where the campaign
/// estimates them (its solutions then carry the sums that update them).
#[allow(clippy::too_many_arguments)]
pub fn iterate(
    campaign: &Campaign,
    work: &Path,
    prepared: &Prepared,
    corrections: &[TrajectoryCorrections],
    previous: Option<&[TrajectoryCorrections]>,
    step: &precimap_core::IterationStep,
    place: Place,
    calibration: Option<&mut CalibrationState>,
    process: Option<&[CurvatureModel]>,
) -> Result<Iterated, PipelineError> {
    let latent = place.latent_gather();
    let tile_calibration = calibration.as_deref().map(CalibrationState::tile);
    let tiles: Vec<(&TileKey, &Vec<usize>)> = prepared.tiles.iter().collect();
    let mut estimates = tiles
        .par_iter()
        .map(|(tile, strips)| {
            let ids: Vec<&str> = strips.iter().map(|&s| campaign.strips[s].id.as_str()).collect();
            let mut estimate = estimate_tile_task(
                work,
                **tile,
                &ids,
                corrections,
                campaign,
                step,
                tile_calibration.as_ref(),
                Gather { used: None, latent },
            )?;
            // Written as each tile finishes, so the map never has to fit in memory whole.
            if let Some(points) = estimate.latent_map.take() {
                let georef = campaign.strips.first().and_then(|s| s.georef.as_deref());
                crate::tasks::write_latent_map_tile(work, **tile, &points, georef)?;
            }
            Ok::<_, PipelineError>(estimate)
        })
        .collect::<Result<Vec<_>, _>>()?;
    let mut stats = TileStats::new(TileKey { tx: 0, ty: 0 });
    let mut per_trajectory: Vec<Vec<&precimap_estimate::AnchorBlock>> = vec![Vec::new(); corrections.len()];
    let mut calibration_normals: Vec<Option<CalibrationNormals>> = vec![None; corrections.len()];
    let latent_std: Vec<_> = estimates.iter_mut().filter_map(|e| Some((e.tile, e.latent_std.take()?))).collect();
    for e in &estimates {
        stats.merge(&e.stats);
        for tb in &e.blocks {
            per_trajectory[tb.trajectory as usize].extend(tb.blocks.iter());
            if let Some(normals) = &tb.calibration {
                calibration_normals[tb.trajectory as usize]
                    .get_or_insert_with(CalibrationNormals::default)
                    .add(normals);
            }
        }
    }
    // The calibration is solved in the steps that estimate the attitude, with every trajectory
    // (one without observations of its own brings an empty share).
    let unknowns = calibration.as_deref().map_or(0, |c| c.layout.len());
    if unknowns > 0 && step.rotation {
        for n in &mut calibration_normals {
            n.get_or_insert_with(|| CalibrationNormals::zeros(unknowns));
        }
    }
    let mut field = None;
    let mut started_from = corrections.to_vec();
    let mut previous = previous.map(<[TrajectoryCorrections]>::to_vec);
    if step.solves_field(&campaign.params) {
        let trajectories: Vec<FieldTrajectory> = corrections
            .iter()
            .zip(&prepared.anchor_positions)
            .zip(&prepared.anchor_priors)
            .enumerate()
            .map(|(t, ((c, positions), prior))| FieldTrajectory {
                positions,
                corrections: c,
                prior: prior.as_deref(),
                curvature: process.and_then(|p| p.get(t)),
            })
            .collect();
        let solved = solve_field(estimates.iter().filter_map(|e| e.field.as_ref()), &trajectories, &campaign.params)
            .map_err(PipelineError::Field)?;
        if campaign.params.field_free_momentum {
            if let Some(p) = previous.as_mut() {
                *p = precimap_estimate::field::remove_field_share(
                    &trajectories,
                    p,
                    campaign.params.common_mode_field_m,
                    precimap_estimate::field::rotation_axes(&campaign.params),
                )
                .map_err(PipelineError::Field)?;
            }
        }
        for (t, positions) in prepared.anchor_positions.iter().enumerate() {
            started_from[t] = solved.apply(positions, &corrections[t]);
            // Momentum carries the last fine step only, not this field step.
            if let Some(p) = previous.as_mut() {
                p[t] = solved.apply(positions, &p[t]);
            }
        }
        field = Some(solved);
    }
    let mut solutions = per_trajectory
        .par_iter()
        .enumerate()
        .map(|(t, blocks)| {
            let before = previous.as_ref().map(|p| &p[t]);
            // The change between iterations, the field's share included.
            let start = &corrections[t];
            solve_trajectory_task(
                campaign,
                t,
                blocks.iter().copied(),
                &started_from[t],
                before,
                start,
                prepared.anchor_priors[t].as_deref(),
                step,
                place.last,
                calibration_normals[t].as_ref(),
                process.and_then(|p| p.get(t)),
            )
        })
        .collect::<Result<Vec<_>, _>>()?;
    if let Some(calibration) = calibration {
        calibration.step(&mut solutions, corrections)?;
    }
    Ok(Iterated { solutions, stats, field, started_from, latent_std })
}

/// Runs a whole campaign in-process and writes `OUT/strips`, `OUT/trajectories`, `OUT/report.json`.
/// A failed run leaves no working files (`OUT/work`) behind unless `keep_work`.
pub fn run_campaign(
    manifest: &Path,
    options: &RunOptions,
    progress: &(dyn Fn(Progress) + Sync),
) -> Result<Report, PipelineError> {
    let result = run_campaign_in(manifest, options, progress);
    let work = options.out_dir.join("work");
    if result.is_err() && !options.keep_work && work.exists() {
        // Best effort: the error being returned matters more than a leftover folder.
        let _ = std::fs::remove_dir_all(&work);
    }
    result
}

fn run_campaign_in(
    manifest: &Path,
    options: &RunOptions,
    progress: &(dyn Fn(Progress) + Sync),
) -> Result<Report, PipelineError> {
    let started = Instant::now();
    let campaign = Campaign::load(manifest)?;
    progress(Progress::Loaded { strips: campaign.strips.len(), trajectories: campaign.trajectories.len() });
    let out = &options.out_dir;
    let work = out.join("work");
    std::fs::create_dir_all(&work).map_err(|e| PipelineError::io(&work, e))?;

    let t = Instant::now();
    let prepared = prepare_all(&campaign, &work, progress)?;
    let prepare_s = t.elapsed().as_secs_f64();

    let t = Instant::now();
    let mut corrections: Vec<TrajectoryCorrections> =
        prepared.anchor_ranges.iter().map(|&(a, b)| TrajectoryCorrections::zeros(a, b)).collect();
    let schedule = &campaign.params.schedule;
    let mut iterations = Vec::new();
    let mut histogram;
    let mut control_sums;
    let converged;
    let mut solutions;
    let mut step_index = 0;
    let mut robust_sigma: Option<f64> = None;
    // The latent map's standard deviation per tile in the first and the last iteration (QC).
    let mut first_latent_std = Vec::new();
    let mut last_latent_std = Vec::new();
    // The corrections before the last iteration and that iteration's step (for momentum).
    let mut previous: Option<(Vec<TrajectoryCorrections>, precimap_core::IterationStep)> = None;
    let mut anderson = AndersonHistory::default();
    let mut calibration = CalibrationState::new(&campaign);
    // Every trajectory's own curvature σ's, where the campaign estimates them.
    let mut process: Option<Vec<CurvatureModel>> = CurvatureModel::from_params(&campaign.params)
        .filter(|_| !campaign.params.process_model.is_fixed())
        .map(|m| vec![m; corrections.len()]);
    // The coefficients that made the next iteration's start (its report names them).
    let mut anderson_coefficients = Vec::new();
    // An iteration's clock starts where the previous one's stopped, so that the Anderson
    // combination between them counts in the iteration it starts (as in the framework).
    let mut iteration_started = Instant::now();
    loop {
        let step = &effective_step(&campaign.params, step_index, robust_sigma);
        let last = step_index + 1 == schedule.len();
        let before =
            previous.as_ref().filter(|(_, s)| step.momentum_continues(s, &campaign.params)).map(|(c, _)| c.as_slice());
        // Posterior σ is only reported for the final corrections, and the loop always ends on the
        // schedule's last step (early convergence jumps to it).
        let first = iterations.is_empty();
        let Iterated { solutions: sol, stats, field, started_from, latent_std } = iterate(
            &campaign,
            &work,
            &prepared,
            &corrections,
            before,
            step,
            Place { first, last },
            calibration.as_mut(),
            process.as_deref(),
        )?;
        if !last {
            update_process_models(process.as_deref_mut(), step, &sol, &campaign.params);
        }
        if first {
            first_latent_std = latent_std.clone();
        }
        if last {
            last_latent_std = latent_std;
        }
        let (max_change, max_change_at) = crate::report::ChangeLocation::largest(
            campaign.trajectories.iter().zip(&sol).map(|(t, s)| (t.id.as_str(), s.max_change_m, s.max_change_anchor)),
            campaign.params.anchor_spacing_m,
        );
        let mut changes = precimap_core::ChangeHistogram::default();
        sol.iter().for_each(|s| changes.merge(&s.change_histogram));
        let next: Vec<TrajectoryCorrections> = sol.iter().map(|s| s.corrections.clone()).collect();
        let starts = std::mem::replace(&mut corrections, next);
        let mix = anderson.record(&campaign.params, step, before.is_some(), starts, || corrections.clone());
        previous = Some((started_from, *step));
        solutions = sol;
        histogram = stats.histogram.clone();
        control_sums = stats.control.clone();
        robust_sigma = histogram.robust_sigma_m();
        let seconds = iteration_started.elapsed().as_secs_f64();
        iteration_started = Instant::now();
        let mut report = iteration_report(iterations.len() + 1, step, &stats, max_change, &changes, seconds);
        report.max_correction_change_at = max_change_at;
        report.anderson_coefficients = std::mem::take(&mut anderson_coefficients);
        let largest = field.as_ref().map(|f| f.largest(&prepared.anchor_positions)).unwrap_or_default();
        report.common_mode_field_max_m = largest.translation_m;
        report.common_mode_heading_max_deg = largest.heading_deg;
        report.common_mode_tilt_max_deg = largest.tilt_deg;
        report.campaign_rotation_deg = field.as_ref().map_or([0.0; 3], FieldSolution::rotation_deg);
        progress(Progress::Iteration(report.clone(), schedule.len()));
        iterations.push(report);
        match after_iteration(step_index, schedule.len(), max_change, campaign.params.convergence_tolerance_m) {
            AfterIteration::Step(next) => {
                if mix {
                    // As the framework's `accelerate` and `combine` stages compute it.
                    let accelerated = anderson.accelerate().map_err(PipelineError::Anderson)?;
                    corrections = accelerated.corrections;
                    anderson_coefficients = accelerated.coefficients;
                }
                step_index = next;
            }
            AfterIteration::Done { converged: c } => {
                // Nothing observed is nothing adjusted, however still the corrections stood.
                converged = c && observed_enough(&campaign, prepared.tiles.len(), iterations.last())?;
                break;
            }
        }
    }
    let estimate_s = t.elapsed().as_secs_f64();

    let t = Instant::now();
    export_all(&campaign, &corrections, &solutions, calibration.as_ref(), out, progress)?;
    let export_s = t.elapsed().as_secs_f64();
    if options.assignments {
        let step = effective_step(&campaign.params, schedule.len() - 1, robust_sigma);
        write_assignments(&campaign, &work, &prepared, &corrections, &step, calibration.as_ref(), out)?;
    }
    move_results_out_of_work(&work, out, options.keep_work)?;

    let trajectories = trajectory_reports(&campaign, &solutions, process.as_deref());
    let report = Report {
        campaign: campaign.name.clone(),
        manifest: manifest.display().to_string(),
        points_total: prepared.points_total,
        tiles: prepared.tiles.len(),
        strips: prepared.strips,
        iterations,
        converged,
        trajectories,
        residual_histogram: histogram,
        control: ControlReport::new(&campaign.control, &control_sums),
        calibration: calibration.as_ref().map(|c| c.report(&campaign.scanners)),
        timings: Timings { prepare_s, estimate_s, export_s, total_s: started.elapsed().as_secs_f64(), task_s: None },
    };
    write_report(&campaign, &report, [&first_latent_std, &last_latent_std], out)?;
    Ok(report)
}

/// Moves every trajectory's process model by what its solve found, after an iteration of a step
/// that updates it; the last iteration reports the σ's it solved with.
fn update_process_models(
    models: Option<&mut [CurvatureModel]>,
    step: &precimap_core::IterationStep,
    solutions: &[precimap_estimate::TrajectorySolution],
    params: &precimap_core::Parameters,
) {
    let Some(models) = models.filter(|_| step.updates_process_model(params)) else { return };
    for (model, s) in models.iter_mut().zip(solutions) {
        if let Some(moments) = &s.curvature_moments {
            model.update(moments, params);
        }
    }
}

/// Every trajectory's report, with its estimated curvature σ's where the campaign estimates them.
fn trajectory_reports(
    campaign: &Campaign,
    solutions: &[precimap_estimate::TrajectorySolution],
    process: Option<&[CurvatureModel]>,
) -> Vec<TrajectoryReport> {
    campaign
        .trajectories
        .iter()
        .zip(solutions)
        .enumerate()
        .map(|(t, (entry, sol))| {
            let mut report = trajectory_report(&entry.id, sol);
            report.curvature_sigma = process.and_then(|p| p.get(t)).map(CurvatureModel::sigma_m_deg);
            report
        })
        .collect()
}

/// Whether the last iteration observed enough of the campaign (`overlap_problem`): an error
/// naming the strips and the reason, or with `allow_low_usable_share` a warning and `false`.
fn observed_enough(campaign: &Campaign, tiles: usize, last: Option<&IterationReport>) -> Result<bool, PipelineError> {
    let ids: Vec<&str> = campaign.strips.iter().map(|s| s.id.as_str()).collect();
    let Some(problem) = overlap_problem(tiles, last, &ids) else { return Ok(true) };
    if !campaign.params.allow_low_usable_share {
        return Err(PipelineError::Input { what: format!("campaign {}", campaign.name), message: problem });
    }
    tracing::warn!("campaign {}: {problem}", campaign.name);
    Ok(false)
}

/// `report.json` and the QC plots, with the latent map's σ per tile in the first and the last
/// iteration.
fn write_report(
    campaign: &Campaign,
    report: &Report,
    [first_latent_std, last_latent_std]: [&[(TileKey, LatentStdMap)]; 2],
    out: &Path,
) -> Result<(), PipelineError> {
    let path = out.join("report.json");
    let json = serde_json::to_vec_pretty(report).expect("report serialises");
    std::fs::write(&path, json).map_err(|e| PipelineError::io(&path, e))?;
    let georef = campaign.strips.first().and_then(|s| s.georef.as_deref());
    let latent_std =
        crate::qc::latent_std_plots(campaign.params.tile_size_m, first_latent_std, last_latent_std, georef);
    crate::tasks::write_plots(out, crate::qc::report_qc(report).into_iter().chain(latent_std))
}

/// Exports every strip (in parallel) and every trajectory with its final corrections; the last
/// iteration solved with covariances, so `solutions` carry the posterior σ of what is exported.
fn export_all(
    campaign: &Campaign,
    corrections: &[TrajectoryCorrections],
    solutions: &[precimap_estimate::TrajectorySolution],
    calibration: Option<&CalibrationState>,
    out: &Path,
    progress: &(dyn Fn(Progress) + Sync),
) -> Result<(), PipelineError> {
    let done = std::sync::atomic::AtomicUsize::new(0);
    let total = campaign.strips.len();
    (0..total).into_par_iter().try_for_each(|s| -> Result<(), PipelineError> {
        let strip = &campaign.strips[s];
        let mounting = calibration.and_then(|c| c.scanners.get(strip.scanner as usize));
        export_strip_task(campaign, s, &corrections[strip.trajectory as usize], mounting, out)?;
        let d = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
        progress(Progress::Exported { done: d, total });
        Ok(())
    })?;
    for (t, c) in corrections.iter().enumerate() {
        export_trajectory_task(campaign, t, c, solutions[t].covariance.as_deref(), out)?;
    }
    Ok(())
}

/// Moves the results written under `work` into `out`, replacing what an earlier run left: the
/// last iteration's latent map (one file per tile) and the segmentation (a result too: evaluate
/// measures its purity against the truth). Then removes `work` unless it is kept.
fn move_results_out_of_work(work: &Path, out: &Path, keep_work: bool) -> Result<(), PipelineError> {
    let latent = out.join(LATENT_DIR);
    if latent.exists() {
        std::fs::remove_dir_all(&latent).map_err(|e| PipelineError::io(&latent, e))?;
    }
    if work.join(LATENT_DIR).exists() {
        std::fs::rename(work.join(LATENT_DIR), &latent).map_err(|e| PipelineError::io(&latent, e))?;
    }
    let segments = out.join("segments");
    if segments.exists() {
        std::fs::remove_dir_all(&segments).map_err(|e| PipelineError::io(&segments, e))?;
    }
    std::fs::rename(work.join("segments"), &segments).map_err(|e| PipelineError::io(&segments, e))?;
    if !keep_work {
        std::fs::remove_dir_all(work).map_err(|e| PipelineError::io(work, e))?;
    }
    Ok(())
}

/// One map pass over `corrections` on `step` that records, for every point that becomes an
/// observation, the surface model it is compared with; written per strip to
/// `OUT/assignments/{strip}.asg` with ids unique within the campaign (tiles in key order).
/// A QC pass, opt-in: it holds 12 bytes per observation and 4 per point in memory.
fn write_assignments(
    campaign: &Campaign,
    work: &Path,
    prepared: &Prepared,
    corrections: &[TrajectoryCorrections],
    step: &precimap_core::IterationStep,
    calibration: Option<&CalibrationState>,
    out: &Path,
) -> Result<(), PipelineError> {
    let tiles: Vec<(&TileKey, &Vec<usize>)> = prepared.tiles.iter().collect();
    let tile_calibration = calibration.map(CalibrationState::tile);
    let used = tiles
        .par_iter()
        .map(|(tile, strips)| {
            let ids: Vec<&str> = strips.iter().map(|&s| campaign.strips[s].id.as_str()).collect();
            let mut used = Vec::new();
            estimate_tile_task(
                work,
                **tile,
                &ids,
                corrections,
                campaign,
                step,
                tile_calibration.as_ref(),
                Gather { used: Some(&mut used), latent: LatentGather::default() },
            )?;
            Ok(used)
        })
        .collect::<Result<Vec<_>, PipelineError>>()?;
    let mut per_strip: Vec<Vec<u32>> = prepared.strips.iter().map(|s| vec![u32::MAX; s.points as usize]).collect();
    let mut offset = 0u64;
    for tile_used in &used {
        let mut models = 0u64;
        for u in tile_used {
            let id = offset + u.model as u64;
            let slot = per_strip.get_mut(u.strip as usize).and_then(|ids| ids.get_mut(u.source as usize)).ok_or_else(
                || PipelineError::Input {
                    what: format!("tile chunks of strip {}", u.strip),
                    message: format!("point {} is beyond the strip's end; prepare the strips again", u.source),
                },
            )?;
            *slot = u32::try_from(id).map_err(|_| PipelineError::Input {
                what: "assignments".into(),
                message: "more than 2³² surface models in the campaign; the assignment files cannot number them".into(),
            })?;
            models = models.max(u.model as u64 + 1);
        }
        offset += models;
    }
    let dir = out.join("assignments");
    std::fs::create_dir_all(&dir).map_err(|e| PipelineError::io(&dir, e))?;
    for (entry, ids) in campaign.strips.iter().zip(&per_strip) {
        let path = dir.join(format!("{}.asg", entry.id));
        std::fs::write(&path, precimap_formats::encode_assignments(ids)).map_err(|e| PipelineError::io(&path, e))?;
    }
    Ok(())
}

/// Per-trajectory statistics of a solution for `report.json`.
pub fn trajectory_report(id: &str, sol: &precimap_estimate::TrajectorySolution) -> TrajectoryReport {
    let values = &sol.corrections.values;
    let n = values.len().max(1) as f64;
    let pos = |v: &[f64; 6]| (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    let rot = |v: &[f64; 6]| (v[3] * v[3] + v[4] * v[4] + v[5] * v[5]).sqrt().to_degrees();
    let (mut ps, mut rs) = (0.0, 0.0);
    for v in values {
        ps += pos(v).powi(2);
        rs += rot(v).powi(2);
    }
    let (mut sig_p, mut sig_r) = (0.0, 0.0);
    if let Some(covariance) = &sol.covariance {
        for s in covariance.iter().map(AnchorCovariance::sigma) {
            sig_p += (s[0] * s[0] + s[1] * s[1] + s[2] * s[2]).sqrt();
            sig_r += (s[3] * s[3] + s[4] * s[4] + s[5] * s[5]).sqrt().to_degrees();
        }
        sig_p /= covariance.len().max(1) as f64;
        sig_r /= covariance.len().max(1) as f64;
    }
    TrajectoryReport {
        id: id.to_string(),
        anchors: values.len(),
        anchors_observed: sol.anchors_observed,
        observations: sol.observations,
        position_correction_rms_m: (ps / n).sqrt(),
        position_correction_max_m: values.iter().map(pos).fold(0.0, f64::max),
        rotation_correction_rms_deg: (rs / n).sqrt(),
        rotation_correction_max_deg: values.iter().map(rot).fold(0.0, f64::max),
        position_sigma_mean_m: sig_p,
        rotation_sigma_mean_deg: sig_r,
        curvature_sigma: None,
    }
}

/// One iteration's line of `report.json`.
pub fn iteration_report(
    iteration: usize,
    step: &precimap_core::IterationStep,
    stats: &TileStats,
    max_change_m: f64,
    changes: &precimap_core::ChangeHistogram,
    seconds: f64,
) -> IterationReport {
    IterationReport {
        iteration,
        common_mode_field_max_m: 0.0,
        common_mode_heading_max_deg: 0.0,
        common_mode_tilt_max_deg: 0.0,
        campaign_rotation_deg: [0.0; 3],
        grid_m: step.grid_m,
        threshold_m: step.threshold_m,
        points_in_tiles: stats.points,
        points_modelled: stats.points_modelled,
        points_used: stats.points_used,
        residual_mean_m: stats.residual_mean_m(),
        residual_std_m: stats.residual_std_m(),
        pixel_std_mean_m: if stats.pixels_shared > 0 {
            stats.pixel_std_sum_m / stats.pixels_shared as f64
        } else {
            0.0
        },
        max_correction_change_m: max_change_m,
        median_correction_change_m: changes.quantile_m(0.5),
        p99_correction_change_m: changes.quantile_m(0.99),
        max_correction_change_at: None,
        anderson_coefficients: Vec::new(),
        seconds,
    }
}

/// Why a campaign cannot be adjusted, shared by both drivers: after preparation (`last`:
/// `None`) no tile holds a usable point; after the last iteration, it observed no point (no
/// surface seen by two passes within the threshold). `strips`: the campaign's strip ids.
pub fn overlap_problem(tiles: usize, last: Option<&IterationReport>, strips: &[&str]) -> Option<String> {
    let names = if strips.len() > 8 {
        format!("{} and {} more", strips[..8].join(", "), strips.len() - 8)
    } else {
        strips.join(", ")
    };
    if tiles == 0 {
        return Some(format!(
            "no usable point in any strip ({names}): no strip yielded a point with a normal and a segment; \
             see each strip's points_usable in the log"
        ));
    }
    let last = last?;
    (last.points_used == 0).then(|| {
        format!(
            "no overlap: the last iteration observed no point among the strips ({names}); no surface was seen by \
             two passes within its threshold {:.3} m. \
             Check that the strips cover the same place and that their trajectories are in one coordinate system \
             and time base; parameters.allow_low_usable_share goes on regardless",
            last.threshold_m
        )
    })
}

/// What follows an iteration on schedule step `step_index`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum AfterIteration {
    /// Run this schedule step next.
    Step(usize),
    /// The schedule is finished.
    Done { converged: bool },
}

/// The schedule rule shared by the in-process driver and the job framework's planner: a step
/// whose largest correction change falls below the tolerance jumps straight to the final step
/// (its grid and threshold); the campaign has converged when the final step itself does.
pub fn after_iteration(step_index: usize, schedule_len: usize, max_change_m: f64, tolerance_m: f64) -> AfterIteration {
    let last = step_index + 1 >= schedule_len;
    let settled = max_change_m < tolerance_m;
    match (last, settled) {
        (true, converged) => AfterIteration::Done { converged },
        (false, true) => AfterIteration::Step(schedule_len - 1),
        (false, false) => AfterIteration::Step(step_index + 1),
    }
}

/// Schedule step `step_index` with its outlier threshold raised to the floor of
/// `threshold_floor_sigmas` robust σ of the previous iteration's distances (shared by the
/// in-process driver and the framework's planner).
pub fn effective_step(
    params: &precimap_core::Parameters,
    step_index: usize,
    robust_sigma: Option<f64>,
) -> precimap_core::IterationStep {
    let mut step = params.schedule[step_index];
    if let Some(sigma) = robust_sigma {
        step.threshold_m = step.threshold_m.max(params.threshold_floor_sigmas * sigma);
    }
    step
}
