//! Anderson acceleration's tasks: a trajectory's share of the coefficient problem, and its
//! combined start for the next iteration.

use super::*;
use precimap_estimate::anderson::{self, TrajectoryHistory};

pub(super) async fn anderson_moments(
    at: &Attempt<'_>,
    trajectory: u32,
    starts: Vec<CorrectionsRef>,
    results: Vec<CorrectionsRef>,
) -> Result<TaskOutcome, TaskError> {
    let (ctx, started) = (at.ctx, at.started);
    // One batch of reads for both lists.
    let n = starts.len();
    let mut starts = read_corrections_many(ctx, &[starts, results].concat()).await?;
    let results = starts.split_off(n);
    let moments = blocking(move || {
        let history = TrajectoryHistory { starts: starts.iter().collect(), results: results.iter().collect() };
        anderson::trajectory_moments(trajectory as usize, &history)
    })
    .await?
    .map_err(|e| TaskError::permanent(format!("Anderson acceleration: {e}")))?;
    let result = MomentsResult { trajectory, moments, seconds: started.elapsed().as_secs_f64() };
    Ok(TaskOutcome { result: to_json(&result)?, outputs: Vec::new() })
}

pub(super) async fn anderson_combine(
    at: &Attempt<'_>,
    prefix: String,
    iteration: u32,
    trajectory: u32,
    results: Vec<CorrectionsRef>,
    coefficients: Vec<f64>,
) -> Result<TaskOutcome, TaskError> {
    let (ctx, tag, started) = (at.ctx, at.tag.as_str(), at.started);
    let read = read_corrections_many(ctx, &results).await?;
    let combined =
        blocking(move || anderson::combine(trajectory as usize, &read.iter().collect::<Vec<_>>(), &coefficients))
            .await?
            .map_err(|e| TaskError::permanent(format!("Anderson acceleration: {e}")))?;
    let key = format!("{prefix}/it/{iteration}/accelerated/{trajectory}.{tag}.bin");
    ctx.put(&key, encode_corrections(&combined, None)).await?;
    let result = CombineResult { trajectory, seconds: started.elapsed().as_secs_f64() };
    Ok(TaskOutcome {
        result: to_json(&result)?,
        outputs: vec![OutputKey { name: OUTPUT_ACCELERATED.into(), object_key: key }],
    })
}
