//! The prepare barrier and one iteration's stages: `estimate` (the map stage, one task per
//! tile), `field` (the common-mode field, in steps that solve it) and `solve` (the reduce stage,
//! one task per trajectory), with the in-process driver's rule for what follows an iteration.

use super::accelerate::accelerate_stage;
use super::finish::export_stage;
use super::*;
use precimap_estimate::TileStats;
use precimap_jobs::{IterationRecord, StageSpan, StageSpec, TileRecord};
use precimap_pipeline::report::StripReport;
use precimap_pipeline::{after_iteration, effective_step, iteration_report, AfterIteration, Place};
use std::collections::BTreeMap;

/// The tiles to record, and the stage's task seconds.
pub(super) fn after_prepare(state: &mut PlanState, tasks: &[FinishedTask]) -> Result<(Vec<TileRecord>, f64), String> {
    let mut results: Vec<(SegmentResult, &FinishedTask)> =
        tasks.iter().map(|t| parse::<SegmentResult>(t).map(|r| (r, t))).collect::<Result<_, _>>()?;
    // Strip order, as the in-process driver combines them.
    results.sort_by_key(|(r, _)| r.strip);
    let mut tiles: BTreeMap<TileKey, Vec<ChunkRef>> = BTreeMap::new();
    let mut ranges = vec![(u32::MAX, 0u32); state.trajectories.len()];
    let mut reports = Vec::with_capacity(results.len());
    let mut points_total = 0;
    let mut seconds = 0.0;
    for (r, task) in &results {
        let strip =
            state.strips.get(r.strip as usize).ok_or_else(|| format!("result names unknown strip {}", r.strip))?;
        let range = &mut ranges[strip.trajectory as usize];
        range.0 = range.0.min(r.stats.first_anchor);
        range.1 = range.1.max(r.stats.last_anchor);
        for out in task.outputs.iter().filter(|o| !o.name.starts_with(SEGMENTS_PREFIX)) {
            let tile: TileKey =
                out.name.parse().map_err(|_| format!("{}: output {:?} is not a tile key", task.key, out.name))?;
            tiles.entry(tile).or_default().push(ChunkRef { strip: r.strip, key: out.object_key.clone() });
        }
        points_total += r.stats.points;
        seconds += r.seconds;
        reports.push(StripReport::new(&strip.id, &r.stats, r.tiles.len()));
    }
    for r in &mut ranges {
        if r.0 == u32::MAX {
            *r = (0, 0);
        }
    }
    let records = tiles
        .iter()
        .map(|(tile, chunks)| TileRecord {
            key: tile.to_string(),
            strips: chunks.iter().map(|c| state.strips[c.strip as usize].id.clone()).collect(),
            points: 0,
        })
        .collect();
    state.tiles = tiles.into_iter().collect();
    state.anchor_ranges = ranges;
    state.strip_reports = reports;
    state.points_total = points_total;
    state.task_s += seconds;
    Ok((records, seconds))
}

/// Whether the current iteration runs the schedule's last step (the run always ends on it:
/// early convergence jumps to it).
fn is_last_step(state: &PlanState) -> bool {
    state.step_index + 1 == state.params.schedule.len()
}

/// Where the current iteration stands in the run, as the in-process driver tells it.
fn place(state: &PlanState) -> Place {
    Place { first: state.iterations.is_empty(), last: is_last_step(state) }
}

fn corrections_ref(state: &PlanState, trajectory: u32) -> CorrectionsRef {
    CorrectionsRef {
        trajectory,
        anchors: state.anchor_ranges[trajectory as usize],
        key: state.corrections[trajectory as usize].clone(),
    }
}

/// Every trajectory's corrections as tasks read them, from one key (or none: zeros) per
/// trajectory.
fn corrections_refs(state: &PlanState, keys: &[Option<String>]) -> Vec<CorrectionsRef> {
    state.trajectories.iter().map(|t| correction_ref(state, t.index, keys)).collect()
}

/// Trajectory `t`'s entry of `keys` (see [`corrections_refs`]).
pub(super) fn correction_ref(state: &PlanState, t: u32, keys: &[Option<String>]) -> CorrectionsRef {
    CorrectionsRef {
        trajectory: t,
        anchors: state.anchor_ranges[t as usize],
        key: keys.get(t as usize).cloned().flatten(),
    }
}

/// A field campaign's CRS (every strip input carries it).
pub(super) fn campaign_crs(state: &PlanState) -> Option<precimap_formats::CrsSpec> {
    state.strips.first().and_then(|s| s.field.as_ref()).map(|f| f.crs.clone())
}

pub(super) fn estimate_stage(state: &mut PlanState) -> Next {
    state.iteration += 1;
    let step = effective_step(&state.params, state.step_index, state.robust_sigma);
    let gather = place(state).latent_gather();
    let control_by_tile = precimap_estimate::control::targets_by_tile(&state.control, &state.params);
    let calibration = state.calibration_input();
    let tasks = state
        .tiles
        .iter()
        .map(|(tile, chunks)| {
            let mut used: Vec<u32> = chunks.iter().map(|c| state.strips[c.strip as usize].trajectory).collect();
            used.sort_unstable();
            used.dedup();
            TaskInput::EstimateTile {
                prefix: state.prefix.clone(),
                iteration: state.iteration,
                tile: *tile,
                step,
                params: None,
                trajectories: state.trajectories.len() as u32,
                chunks: chunks.clone(),
                corrections: used.into_iter().map(|t| corrections_ref(state, t)).collect(),
                std_map: gather.std_map,
                latent_map: gather.map,
                crs: gather.map.then(|| campaign_crs(state)).flatten(),
                control: control_by_tile.get(tile).cloned().unwrap_or_default(),
                calibration: calibration.clone(),
            }
            .task(tile.to_string())
        })
        .collect();
    Next::Stage(StageSpec { stage: STAGE_ESTIMATE.to_string(), iteration: state.iteration as i32, tasks })
}

pub(super) fn after_estimate(state: &mut PlanState, tasks: &[FinishedTask]) -> Result<Next, String> {
    let mut per_tile: Vec<(TileKey, &FinishedTask)> = tasks
        .iter()
        .map(|t| {
            t.key.parse::<TileKey>().map(|k| (k, t)).map_err(|_| format!("estimate task key {:?} is not a tile", t.key))
        })
        .collect::<Result<_, _>>()?;
    // Tile order: the in-process driver sums blocks and statistics in this order.
    per_tile.sort_by_key(|(k, _)| *k);
    let mut stats = TileStats::new(TileKey { tx: 0, ty: 0 });
    let mut blocks: Vec<Vec<String>> = vec![Vec::new(); state.trajectories.len()];
    let mut equations = Vec::new();
    let mut seconds = 0.0;
    let mut latent_std = Vec::with_capacity(per_tile.len());
    let mut latent_map = Vec::new();
    for (tile, task) in &per_tile {
        let r: EstimateResult = parse(task)?;
        stats.merge(&r.stats);
        seconds += r.seconds;
        for out in &task.outputs {
            if out.name == OUTPUT_FIELD {
                equations.push(out.object_key.clone());
                continue;
            }
            if out.name == OUTPUT_LATENT_STD {
                latent_std.push((*tile, out.object_key.clone()));
                continue;
            }
            if out.name.starts_with(LATENT_MAP_PREFIX) {
                latent_map.push((out.name.clone(), out.object_key.clone()));
                continue;
            }
            let t: usize = out
                .name
                .strip_prefix(BLOCKS_PREFIX)
                .and_then(|s| s.parse().ok())
                .filter(|&t: &usize| t < blocks.len())
                .ok_or_else(|| format!("{}: unexpected output {:?}", task.key, out.name))?;
            blocks[t].push(out.object_key.clone());
        }
    }
    state.pending_stats = Some(stats);
    state.pending_seconds = seconds;
    let place = place(state);
    if place.first {
        state.latent_std.first = latent_std.clone();
    }
    if place.last {
        state.latent_std.last = latent_std;
        state.latent_map = latent_map;
    }
    let step = effective_step(&state.params, state.step_index, state.robust_sigma);
    let momentum = state.previous_step.is_some_and(|p| step.momentum_continues(&p, &state.params));
    if !step.solves_field(&state.params) {
        let current = state.corrections.clone();
        let previous = momentum.then(|| state.previous_corrections.clone());
        return Ok(solve_stage(state, blocks, current, previous, None));
    }
    state.pending_blocks = blocks;
    let task = TaskInput::SolveField {
        prefix: state.prefix.clone(),
        iteration: state.iteration,
        params: None,
        trajectories: state.trajectories.clone(),
        positions: state.anchor_positions.clone(),
        current: corrections_refs(state, &state.corrections),
        previous: momentum.then(|| corrections_refs(state, &state.previous_corrections)),
        equations,
    }
    .task("field".into());
    Ok(Next::Stage(StageSpec { stage: STAGE_FIELD.to_string(), iteration: state.iteration as i32, tasks: vec![task] }))
}

pub(super) fn after_field(state: &mut PlanState, tasks: &[FinishedTask]) -> Result<Next, String> {
    let task = tasks.first().ok_or("the field stage finished without its task")?;
    let r: FieldResult = parse(task)?;
    state.pending_seconds += r.seconds;
    state.pending_field_max_m = r.max_m;
    state.pending_campaign_rotation_deg = r.rotation_deg;
    state.pending_field_heading_max_deg = r.heading_max_deg;
    state.pending_field_tilt_max_deg = r.tilt_max_deg;
    let n = state.trajectories.len();
    let mut start = vec![None; n];
    let mut previous = vec![None; n];
    let mut any_previous = false;
    for out in &task.outputs {
        if out.name == OUTPUT_POSITIONS {
            state.anchor_positions = Some(out.object_key.clone());
            continue;
        }
        let (slot, name) = if let Some(t) = out.name.strip_prefix(START_PREFIX) {
            (&mut start, t)
        } else if let Some(t) = out.name.strip_prefix(PREVIOUS_PREFIX) {
            any_previous = true;
            (&mut previous, t)
        } else {
            return Err(format!("{}: unexpected output {:?}", task.key, out.name));
        };
        let t: usize = name
            .parse()
            .ok()
            .filter(|&t: &usize| t < n)
            .ok_or_else(|| format!("{}: output {:?} names no trajectory", task.key, out.name))?;
        slot[t] = Some(out.object_key.clone());
    }
    if start.iter().any(Option::is_none) {
        return Err(format!("{}: not every trajectory's shifted corrections were recorded", task.key));
    }
    let blocks = std::mem::take(&mut state.pending_blocks);
    state.started_from = start.clone();
    let iteration_start = state.corrections.clone();
    Ok(solve_stage(state, blocks, start, any_previous.then_some(previous), Some(iteration_start)))
}

/// The reduce stage: one `solve_trajectory` per trajectory from `current` (with `previous` when
/// momentum carries the last step on), its change measured from `iteration_start` where the
/// field moved `current` away from it.
fn solve_stage(
    state: &mut PlanState,
    mut blocks: Vec<Vec<String>>,
    current: Vec<Option<String>>,
    previous: Option<Vec<Option<String>>>,
    iteration_start: Option<Vec<Option<String>>>,
) -> Next {
    let step = effective_step(&state.params, state.step_index, state.robust_sigma);
    let with_sigma = is_last_step(state);
    let reference = |keys: &[Option<String>], t: u32| CorrectionsRef {
        trajectory: t,
        anchors: state.anchor_ranges[t as usize],
        key: keys.get(t as usize).cloned().flatten(),
    };
    let tasks = state
        .trajectories
        .iter()
        .map(|traj| {
            TaskInput::SolveTrajectory {
                prefix: state.prefix.clone(),
                iteration: state.iteration,
                trajectory: traj.clone(),
                step,
                params: None,
                with_sigma,
                current: reference(&current, traj.index),
                previous: previous.as_ref().map(|p| reference(p, traj.index)),
                iteration_start: iteration_start.as_ref().map(|s| reference(s, traj.index)),
                blocks: std::mem::take(&mut blocks[traj.index as usize]),
                calibration: if step.rotation { state.calibration.len() as u32 } else { 0 },
            }
            .task(traj.id.clone())
        })
        .collect();
    Next::Stage(StageSpec { stage: STAGE_SOLVE.to_string(), iteration: state.iteration as i32, tasks })
}

pub(super) fn after_solve(
    state: &mut PlanState,
    tasks: &[FinishedTask],
    span: Option<StageSpan>,
) -> Result<(Option<IterationRecord>, Next), String> {
    let mut solved = Vec::with_capacity(tasks.len());
    for task in tasks {
        let r: SolveResult = parse(task)?;
        if r.trajectory as usize >= state.trajectories.len() {
            return Err(format!("{}: result names unknown trajectory {}", task.key, r.trajectory));
        }
        let output = |name: &str| task.outputs.iter().find(|o| o.name == name).map(|o| o.object_key.clone());
        let corrections = output(OUTPUT_CORRECTIONS).ok_or_else(|| format!("{}: no corrections recorded", task.key))?;
        let share = output(OUTPUT_SHARE);
        solved.push((r, corrections, share));
    }
    // Trajectory order: the in-process driver sums the calibration's shares in it.
    solved.sort_by_key(|(r, _, _)| r.trajectory);
    if solved.iter().any(|(r, _, _)| r.calibration.is_some()) {
        return calibrate_stage(state, solved).map(|next| (None, next));
    }
    let outcomes = solved
        .into_iter()
        .map(|(r, corrections, _)| TrajectoryOutcome {
            trajectory: r.trajectory,
            max_change_m: r.max_change_m,
            max_change_anchor: r.max_change_anchor,
            change_histogram: r.change_histogram,
            report: r.report,
            seconds: r.seconds,
            corrections,
        })
        .collect();
    finish_iteration(state, outcomes, span).map(|(record, next)| (Some(record), next))
}

/// What an iteration's last stage reports of one trajectory.
struct TrajectoryOutcome {
    trajectory: u32,
    max_change_m: f64,
    max_change_anchor: u32,
    change_histogram: precimap_core::ChangeHistogram,
    report: precimap_pipeline::report::TrajectoryReport,
    seconds: f64,
    corrections: String,
}

/// The calibration's step from every trajectory's share (solved here, like Anderson's
/// coefficients: the shares are small), and the stage that applies it to each trajectory.
fn calibrate_stage(state: &mut PlanState, solved: Vec<(SolveResult, String, Option<String>)>) -> Result<Next, String> {
    let shares: Vec<&precimap_estimate::calibration::CalibrationShare> =
        solved.iter().filter_map(|(r, _, _)| r.calibration.as_ref()).collect();
    let layout = state.params.calibration.layout(state.scanners.len());
    let step = precimap_estimate::calibration::solve_calibration(
        shares,
        &state.calibration,
        &layout,
        &state.params.calibration,
    )
    .map_err(|e| format!("the scanners' calibration: {e}"))?;
    for (value, delta) in state.calibration.iter_mut().zip(&step.delta) {
        *value += delta;
    }
    let starts = state.corrections.clone();
    let mut tasks = Vec::with_capacity(solved.len());
    for (r, corrections, share) in solved {
        state.pending_seconds += r.seconds;
        let t = r.trajectory;
        let share = share.ok_or_else(|| format!("trajectory {t}: its solve recorded no calibration share"))?;
        let reference =
            |key: Option<String>| CorrectionsRef { trajectory: t, anchors: state.anchor_ranges[t as usize], key };
        let traj = state.trajectories[t as usize].clone();
        tasks.push(
            TaskInput::ApplyCalibration(Box::new(ApplyCalibrationInput {
                prefix: state.prefix.clone(),
                iteration: state.iteration,
                corrections: reference(Some(corrections)),
                share,
                iteration_start: reference(starts[t as usize].clone()),
                delta: step.delta.clone(),
                report: r.report,
                trajectory: traj.clone(),
            }))
            .task(traj.id.clone()),
        );
    }
    state.calibration_step = Some(step);
    Ok(Next::Stage(StageSpec { stage: STAGE_CALIBRATE.to_string(), iteration: state.iteration as i32, tasks }))
}

pub(super) fn after_calibrate(
    state: &mut PlanState,
    tasks: &[FinishedTask],
    span: Option<StageSpan>,
) -> Result<(IterationRecord, Next), String> {
    let mut outcomes = Vec::with_capacity(tasks.len());
    for task in tasks {
        let r: ApplyResult = parse(task)?;
        let corrections = task
            .outputs
            .iter()
            .find(|o| o.name == OUTPUT_CORRECTIONS)
            .map(|o| o.object_key.clone())
            .ok_or_else(|| format!("{}: no corrections recorded", task.key))?;
        outcomes.push(TrajectoryOutcome {
            trajectory: r.trajectory,
            max_change_m: r.max_change_m,
            max_change_anchor: r.max_change_anchor,
            change_histogram: r.change_histogram,
            report: r.report,
            seconds: r.seconds,
            corrections,
        });
    }
    finish_iteration(state, outcomes, span)
}

/// The end of an iteration, once every trajectory's corrections are final: the iteration's
/// report and record, and what follows it.
fn finish_iteration(
    state: &mut PlanState,
    outcomes: Vec<TrajectoryOutcome>,
    span: Option<StageSpan>,
) -> Result<(IterationRecord, Next), String> {
    let mut changes = precimap_core::ChangeHistogram::default();
    let mut reports = vec![None; state.trajectories.len()];
    // Per trajectory, its largest change and where (in trajectory order, as the in-process
    // driver picks the place among equal changes).
    let mut largest = vec![None; state.trajectories.len()];
    let step = effective_step(&state.params, state.step_index, state.robust_sigma);
    let momentum_carried = state.previous_step.is_some_and(|p| step.momentum_continues(&p, &state.params));
    let starts = state.corrections.clone();
    // Momentum measures the next step from where this one started (after the field, if any).
    state.previous_corrections =
        if state.started_from.is_empty() { state.corrections.clone() } else { std::mem::take(&mut state.started_from) };
    state.previous_step = Some(effective_step(&state.params, state.step_index, state.robust_sigma));
    let mut seconds = state.pending_seconds;
    for r in outcomes {
        let t = r.trajectory as usize;
        if t >= reports.len() {
            return Err(format!("a result names unknown trajectory {t}"));
        }
        largest[t] = Some((r.max_change_m, r.max_change_anchor));
        changes.merge(&r.change_histogram);
        seconds += r.seconds;
        state.corrections[t] = Some(r.corrections);
        reports[t] = Some(r.report);
    }
    state.trajectory_reports = reports.into_iter().flatten().collect();
    let accelerate =
        state.anderson.record(&state.params, &step, momentum_carried, starts, || state.corrections.clone());
    let stats = state.pending_stats.take().unwrap_or_else(|| TileStats::new(TileKey { tx: 0, ty: 0 }));
    state.task_s += seconds;
    // Wall time from the map stage's enqueueing to the last solve, as the in-process driver
    // reports it (task seconds where the store gave no span).
    let wall = match (state.iteration_enqueued_at_ms.take(), span) {
        (Some(enqueued_at_ms), Some(span)) => StageSpan { enqueued_at_ms, ..span }.seconds(),
        _ => seconds,
    };
    let (max_change, max_change_at) = precimap_pipeline::report::ChangeLocation::largest(
        state
            .trajectories
            .iter()
            .zip(&largest)
            .filter_map(|(t, c)| c.map(|(change, anchor)| (t.id.as_str(), change, anchor))),
        state.params.anchor_spacing_m,
    );
    let mut report = iteration_report(state.iteration as usize, &step, &stats, max_change, &changes, wall);
    report.max_correction_change_at = max_change_at;
    report.common_mode_field_max_m = std::mem::take(&mut state.pending_field_max_m);
    report.campaign_rotation_deg = std::mem::take(&mut state.pending_campaign_rotation_deg);
    report.common_mode_heading_max_deg = std::mem::take(&mut state.pending_field_heading_max_deg);
    report.common_mode_tilt_max_deg = std::mem::take(&mut state.pending_field_tilt_max_deg);
    report.anderson_coefficients = std::mem::take(&mut state.pending_anderson_coefficients);
    state.histogram = stats.histogram.clone();
    state.control_sums = stats.control.clone();
    state.robust_sigma = stats.histogram.robust_sigma_m();
    state.estimate_s += wall;
    state.iterations.push(report.clone());
    let record = IterationRecord {
        iteration: state.iteration as i32,
        stats: serde_json::to_value(&report).map_err(|e| e.to_string())?,
    };
    let next = match after_iteration(
        state.step_index,
        state.params.schedule.len(),
        max_change,
        state.params.convergence_tolerance_m,
    ) {
        AfterIteration::Step(s) => {
            state.step_index = s;
            if accelerate {
                accelerate_stage(state)
            } else {
                estimate_stage(state)
            }
        }
        AfterIteration::Done { converged } => {
            let ids: Vec<&str> = state.strips.iter().map(|s| s.id.as_str()).collect();
            let problem = overlap_problem(state.tiles.len(), state.iterations.last(), &ids);
            if let Some(problem) = &problem {
                if !state.params.allow_low_usable_share {
                    return Err(problem.clone());
                }
                tracing::warn!("campaign {}: {problem}", state.name);
            }
            state.converged = converged && problem.is_none();
            export_stage(state)
        }
    };
    Ok((record, next))
}
