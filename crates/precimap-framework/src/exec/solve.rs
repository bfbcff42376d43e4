//! `solve_trajectory`: one trajectory's corrections from the blocks of every tile it crosses.

use super::*;
use precimap_core::IterationStep;

/// The input of a `solve_trajectory` task ([`TaskInput::SolveTrajectory`]).
#[derive(Debug)]
pub(super) struct TrajectoryTask {
    pub(super) prefix: String,
    pub(super) iteration: u32,
    pub(super) trajectory: TrajectoryInput,
    pub(super) step: IterationStep,
    pub(super) params: Option<Box<Parameters>>,
    pub(super) with_sigma: bool,
    pub(super) current: CorrectionsRef,
    pub(super) previous: Option<CorrectionsRef>,
    pub(super) iteration_start: Option<CorrectionsRef>,
    pub(super) blocks: Vec<String>,
}

pub(super) async fn solve_trajectory(at: &Attempt<'_>, task: TrajectoryTask) -> Result<TaskOutcome, TaskError> {
    let TrajectoryTask {
        prefix,
        iteration,
        trajectory,
        step,
        params,
        with_sigma,
        current,
        previous,
        iteration_start,
        blocks,
    } = task;
    let (ctx, tag, started) = (at.ctx, at.tag.as_str(), at.started);
    let params = required(params)?;
    let prior = read_anchor_prior(ctx, &trajectory, &params, current.anchors).await?;
    let has_previous = previous.is_some();
    let mut refs = vec![current];
    refs.extend(previous);
    refs.extend(iteration_start);
    let mut read = read_corrections_many(ctx, &refs).await?.into_iter();
    let current = read.next().expect("the current corrections");
    let previous = if has_previous { read.next() } else { None };
    let iteration_start = read.next();
    let mut all = Vec::new();
    for (key, bytes) in blocks.iter().zip(ctx.get_many(&blocks).await?) {
        all.extend(decode_blocks(&bytes).map_err(|e| TaskError::permanent(format!("blocks object {key}: {e}")))?);
    }
    let id = trajectory.id.clone();
    let solution = blocking(move || {
        // The change between iterations, the field's share included.
        precimap_estimate::solve_trajectory(
            all.iter(),
            &current,
            previous.as_ref(),
            iteration_start.as_ref(),
            &params,
            prior.as_deref(),
            step.rotation,
            with_sigma,
            None,
        )
    })
    .await?
    .map_err(|e| {
        TaskError::permanent(format!(
            "trajectory {id}: the normal equations could not be solved ({e}); the campaign parameters (sigma values) are probably inconsistent"
        ))
    })?;
    let key = format!("{prefix}/it/{iteration}/corr/{}.{tag}.bin", trajectory.index);
    ctx.put(&key, encode_corrections(&solution.corrections, solution.covariance.as_deref())).await?;
    let result = SolveResult {
        trajectory: trajectory.index,
        max_change_m: solution.max_change_m,
        max_change_anchor: solution.max_change_anchor,
        change_histogram: solution.change_histogram.clone(),
        report: precimap_pipeline::trajectory_report(&trajectory.id, &solution),
        seconds: started.elapsed().as_secs_f64(),
    };
    Ok(TaskOutcome {
        result: to_json(&result)?,
        outputs: vec![OutputKey { name: OUTPUT_CORRECTIONS.into(), object_key: key }],
    })
}
