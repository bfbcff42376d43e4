//! Anderson acceleration between two settling iterations: each trajectory's share of the
//! coefficients' problem (`accelerate`), the coefficients solved at the barrier, then each
//! trajectory's combination (`combine`), which the next iteration starts from.

use super::iterate::{correction_ref, estimate_stage};
use super::*;
use precimap_estimate::anderson::{self, AndersonEntry, AndersonMoments};
use precimap_jobs::StageSpec;

/// One `anderson_moments` task per trajectory over its recorded history (the in-process
/// driver's `AndersonHistory::accelerate` computes the same shares).
pub(super) fn accelerate_stage(state: &PlanState) -> Next {
    let tasks = state
        .trajectories
        .iter()
        .map(|traj| {
            TaskInput::AndersonMoments {
                trajectory: traj.index,
                starts: history_refs(state, traj.index, |e| &e.starts),
                results: history_refs(state, traj.index, |e| &e.results),
            }
            .task(traj.id.clone())
        })
        .collect();
    Next::Stage(StageSpec { stage: STAGE_ACCELERATE.to_string(), iteration: state.iteration as i32, tasks })
}

/// Trajectory `t`'s recorded corrections in the Anderson history, oldest first (`pick`: each
/// entry's starts or results).
fn history_refs(
    state: &PlanState,
    t: u32,
    pick: impl Fn(&AndersonEntry<Option<String>>) -> &Vec<Option<String>>,
) -> Vec<CorrectionsRef> {
    state.anderson.entries.iter().map(|e| correction_ref(state, t, pick(e))).collect()
}

/// Sums the trajectories' shares in trajectory order (as `precimap_estimate::anderson::accelerate`
/// does), solves for the coefficients and enqueues one `anderson_combine` task per trajectory.
pub(super) fn after_accelerate(
    state: &mut PlanState,
    tasks: &[FinishedTask],
    finished: &FinishedStage,
) -> Result<Next, String> {
    let (shares, seconds) = by_trajectory(state, tasks, |r: &MomentsResult| (r.trajectory, r.seconds))?;
    let mut total = AndersonMoments::zeros(state.anderson.entries.len().saturating_sub(1));
    for (t, share) in shares.iter().enumerate() {
        let (share, _) = share.as_ref().ok_or_else(|| format!("no Anderson share was recorded for trajectory {t}"))?;
        total.add(t, &share.moments).map_err(|e| format!("Anderson acceleration: {e}"))?;
    }
    let coefficients = anderson::coefficients(&total);
    state.task_s += seconds;
    // The next iteration starts here.
    state.iteration_enqueued_at_ms = finished.span_ms.map(|s| s.enqueued_at_ms);
    let tasks = state
        .trajectories
        .iter()
        .map(|traj| {
            TaskInput::AndersonCombine {
                prefix: state.prefix.clone(),
                iteration: state.iteration,
                trajectory: traj.index,
                results: history_refs(state, traj.index, |e| &e.results),
                coefficients: coefficients.clone(),
            }
            .task(traj.id.clone())
        })
        .collect();
    state.pending_anderson_coefficients = coefficients;
    Ok(Next::Stage(StageSpec { stage: STAGE_COMBINE.to_string(), iteration: state.iteration as i32, tasks }))
}

/// The combinations become the next iteration's corrections.
pub(super) fn after_combine(state: &mut PlanState, tasks: &[FinishedTask]) -> Result<Next, String> {
    let (combined, seconds) = by_trajectory(state, tasks, |r: &CombineResult| (r.trajectory, r.seconds))?;
    let mut accelerated = Vec::with_capacity(combined.len());
    for (t, c) in combined.iter().enumerate() {
        let (_, task) =
            c.as_ref().ok_or_else(|| format!("trajectory {t}'s accelerated corrections were not recorded"))?;
        let out = task
            .outputs
            .iter()
            .find(|o| o.name == OUTPUT_ACCELERATED)
            .ok_or_else(|| format!("{}: no accelerated corrections recorded", task.key))?;
        accelerated.push(Some(out.object_key.clone()));
    }
    state.corrections = accelerated;
    state.task_s += seconds;
    Ok(estimate_stage(state))
}

/// Per trajectory index, its task's result and the task (`None` where no task named it).
type ByTrajectory<'a, T> = Vec<Option<(T, &'a FinishedTask)>>;

/// A per-trajectory stage's results by trajectory index, and the sum of the tasks' seconds
/// (`of`: a result's trajectory index and seconds).
fn by_trajectory<'a, T: serde::de::DeserializeOwned>(
    state: &PlanState,
    tasks: &'a [FinishedTask],
    of: impl Fn(&T) -> (u32, f64),
) -> Result<(ByTrajectory<'a, T>, f64), String> {
    let mut out: ByTrajectory<'a, T> = state.trajectories.iter().map(|_| None).collect();
    let mut seconds = 0.0;
    for task in tasks {
        let r: T = parse(task)?;
        let (t, s) = of(&r);
        let slot =
            out.get_mut(t as usize).ok_or_else(|| format!("{}: result names unknown trajectory {t}", task.key))?;
        seconds += s;
        *slot = Some((r, task));
    }
    Ok((out, seconds))
}
