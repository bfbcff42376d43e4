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
    pub(super) calibration: u32,
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
        calibration,
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
    // The calibration's normal equations, summed in tile order (as the in-process driver does).
    let mut normals = (calibration > 0).then(precimap_estimate::CalibrationNormals::default);
    for (key, bytes) in blocks.iter().zip(ctx.get_many(&blocks).await?) {
        let (b, n) =
            decode_trajectory_blocks(&bytes).map_err(|e| TaskError::permanent(format!("blocks object {key}: {e}")))?;
        all.extend(b);
        if let (Some(sum), Some(n)) = (normals.as_mut(), n) {
            sum.add(&n);
        }
    }
    if let Some(n) = normals.as_mut().filter(|n| n.is_empty()) {
        *n = precimap_estimate::CalibrationNormals::zeros(calibration as usize);
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
            normals.as_ref(),
            // The framework solves with the campaign's curvature σ's: it refuses an estimated
            // process model at submission.
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
    let mut outputs = vec![OutputKey { name: OUTPUT_CORRECTIONS.into(), object_key: key }];
    // The share's `Y` goes to an object; the planner reads the rest from the result.
    let share = solution.calibration.clone().map(|mut share| {
        let y = std::mem::take(&mut share.y);
        (share, y)
    });
    let share = match share {
        Some((share, y)) => {
            let key = format!("{prefix}/it/{iteration}/share/{}.{tag}.bin", trajectory.index);
            ctx.put(&key, encode_share(share.first_anchor, share.len(), &y)).await?;
            outputs.push(OutputKey { name: OUTPUT_SHARE.into(), object_key: key });
            Some(share)
        }
        None => None,
    };
    let result = SolveResult {
        trajectory: trajectory.index,
        max_change_m: solution.max_change_m,
        max_change_anchor: solution.max_change_anchor,
        change_histogram: solution.change_histogram.clone(),
        report: precimap_pipeline::trajectory_report(&trajectory.id, &solution),
        seconds: started.elapsed().as_secs_f64(),
        calibration: share,
    };
    Ok(TaskOutcome { result: to_json(&result)?, outputs })
}
