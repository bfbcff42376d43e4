//! `apply_calibration`: one trajectory's corrections moved by the calibration's step.

use super::*;
use crate::plan::ApplyCalibrationInput;

pub(super) async fn apply_calibration(at: &Attempt<'_>, task: ApplyCalibrationInput) -> Result<TaskOutcome, TaskError> {
    let ApplyCalibrationInput { prefix, iteration, trajectory, corrections, share, iteration_start, delta, report } =
        task;
    let (ctx, tag, started) = (at.ctx, at.tag.as_str(), at.started);
    let (current, covariance) = read_corrections(ctx, &corrections).await?;
    let start = read_corrections_many(ctx, &[iteration_start]).await?.pop().expect("one corrections object");
    let bytes = ctx.get(&share).await?;
    let (first_anchor, unknowns, y) =
        decode_share(&bytes).map_err(|e| TaskError::permanent(format!("calibration share {share}: {e}")))?;
    if unknowns != delta.len() || first_anchor != current.first_anchor {
        return Err(TaskError::permanent(format!(
            "calibration share {share} ({unknowns} unknowns from anchor {first_anchor}) does not match the step \
             ({} unknowns) or the corrections (from anchor {}); the campaign state is corrupt: submit the campaign again",
            delta.len(),
            current.first_anchor
        )));
    }
    let (solution, corrections_bytes) = blocking(move || {
        let share = precimap_estimate::calibration::CalibrationShare {
            normals: Default::default(),
            schur: Vec::new(),
            rhs: vec![0.0; unknowns],
            first_anchor,
            y,
        };
        let mut solution = precimap_estimate::TrajectorySolution {
            corrections: current,
            max_change_m: 0.0,
            max_change_anchor: 0,
            change_histogram: Default::default(),
            anchors_observed: report.anchors_observed,
            observations: report.observations,
            covariance,
            calibration: Some(share),
            curvature_moments: None,
        };
        precimap_estimate::solve::apply_calibration_step(&mut solution, &delta, &start);
        let bytes = encode_corrections(&solution.corrections, solution.covariance.as_deref());
        (solution, bytes)
    })
    .await?;
    let key = format!("{prefix}/it/{iteration}/calibrated/{}.{tag}.bin", trajectory.index);
    ctx.put(&key, corrections_bytes).await?;
    let result = ApplyResult {
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
