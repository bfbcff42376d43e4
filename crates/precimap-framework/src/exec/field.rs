//! `solve_field`: the common-mode field from the tiles' field equations, applied to every
//! trajectory's corrections.

use super::*;

/// The input of a `solve_field` task ([`TaskInput::SolveField`]).
#[derive(Debug)]
pub(super) struct FieldTask {
    pub(super) prefix: String,
    pub(super) iteration: u32,
    pub(super) params: Option<Box<Parameters>>,
    pub(super) trajectories: Vec<TrajectoryInput>,
    pub(super) positions: Option<String>,
    pub(super) current: Vec<CorrectionsRef>,
    pub(super) previous: Option<Vec<CorrectionsRef>>,
    pub(super) equations: Vec<String>,
}

pub(super) async fn solve_field(at: &Attempt<'_>, task: FieldTask) -> Result<TaskOutcome, TaskError> {
    let FieldTask { prefix, iteration, params, trajectories, positions, current, previous, equations } = task;
    let (ctx, tag, started) = (at.ctx, at.tag.as_str(), at.started);
    let params = required(params)?;
    let mut outputs = Vec::with_capacity(2 * current.len() + 1);
    // The anchors' positions: read once from the trajectory files by the first field task
    // of the campaign, then from the object it wrote.
    let positions = match &positions {
        Some(key) => {
            let bytes = ctx.get(key).await?;
            decode_positions(&bytes).map_err(|e| TaskError::permanent(format!("anchor positions object {key}: {e}")))?
        }
        None => {
            let mut positions = Vec::with_capacity(trajectories.len());
            for (t, c) in trajectories.iter().zip(&current) {
                let entry = read_trajectory(ctx, t).await?;
                positions.push(anchor_positions(&entry, params.anchor_spacing_m, c.anchors));
            }
            let key = format!("{prefix}/anchors/positions.{tag}.bin");
            ctx.put(&key, encode_positions(&positions)).await?;
            outputs.push(OutputKey { name: OUTPUT_POSITIONS.into(), object_key: key });
            positions
        }
    };
    // One list per trajectory (solve_field checks each list's length against its anchors).
    if positions.len() != current.len() {
        return Err(corrupt_positions(format!("{} trajectories for {}", positions.len(), current.len())));
    }
    let mut priors = Vec::with_capacity(trajectories.len());
    for (t, c) in trajectories.iter().zip(&current) {
        priors.push(read_anchor_prior(ctx, t, &params, c.anchors).await?);
    }
    let corrections = read_corrections_many(ctx, &current).await?;
    let before = read_corrections_many(ctx, previous.as_deref().unwrap_or_default()).await?;
    let mut decoded = Vec::with_capacity(equations.len());
    for (key, bytes) in equations.iter().zip(ctx.get_many(&equations).await?) {
        decoded.push(decode_field(&bytes).map_err(|e| TaskError::permanent(format!("field object {key}: {e}")))?);
    }
    let solved = blocking(move || {
        let field_trajectories: Vec<_> = corrections
            .iter()
            .zip(&positions)
            .zip(&priors)
            .map(|((c, p), prior)| precimap_estimate::FieldTrajectory {
                positions: p,
                corrections: c,
                prior: prior.as_deref(),
                curvature: None,
            })
            .collect();
        let field = precimap_estimate::solve_field(decoded.iter(), &field_trajectories, &params)?;
        // Momentum carries only what the field cannot represent (as in the in-process driver).
        let before = if params.field_free_momentum && !before.is_empty() {
            precimap_estimate::field::remove_field_share(
                &field_trajectories,
                &before,
                params.common_mode_field_m,
                precimap_estimate::field::rotation_axes(&params),
            )?
        } else {
            before
        };
        let start: Vec<_> = corrections.iter().zip(&positions).map(|(c, p)| field.apply(p, c)).collect();
        let before: Vec<_> = before.iter().zip(&positions).map(|(c, p)| field.apply(p, c)).collect();
        let figures = (field.largest(&positions), field.rotation_deg(), field.nodes.len());
        Ok::<_, precimap_estimate::field::FieldError>((start, before, figures))
    })
    .await?
    .map_err(|e| match e {
        // solve_field and remove_field_share check the positions against the corrections.
        precimap_estimate::field::FieldError::Positions { .. }
        | precimap_estimate::field::FieldError::Trajectories { .. } => corrupt_positions(e.to_string()),
        e => TaskError::permanent(format!(
            "common-mode field: {e}; check parameters.common_mode_field_m and the sigma values"
        )),
    })?;
    let (start, before, (largest, rotation_deg, nodes)) = solved;
    let mut objects = Vec::with_capacity(start.len() + before.len());
    for (name, list) in [(START_PREFIX, &start), (PREVIOUS_PREFIX, &before)] {
        for (t, c) in trajectories.iter().zip(list) {
            let key = format!("{prefix}/it/{iteration}/{name}{}.{tag}.bin", t.index);
            objects.push((format!("{name}{}", t.index), key, encode_corrections(c, None)));
        }
    }
    outputs.extend(ctx.put_many(objects).await?);
    let seconds = started.elapsed().as_secs_f64();
    let result = FieldResult {
        max_m: largest.translation_m,
        rotation_deg,
        heading_max_deg: largest.heading_deg,
        tilt_max_deg: largest.tilt_deg,
        nodes,
        seconds,
    };
    Ok(TaskOutcome { result: to_json(&result)?, outputs })
}
