//! The export tasks: a corrected strip, and a corrected trajectory with its corrections table.

use super::*;

pub(super) async fn export_strip(
    at: &Attempt<'_>,
    prefix: String,
    strip: StripInput,
    anchor_spacing_m: f64,
    corrections: CorrectionsRef,
    mounting: Option<precimap_core::ScannerCalibration>,
) -> Result<TaskOutcome, TaskError> {
    let (ctx, tag, started) = (at.ctx, at.tag.as_str(), at.started);
    let (corrections, _) = read_corrections(ctx, &corrections).await?;
    let traj = read_trajectory(ctx, &strip_trajectory(&strip)).await?;
    let local = ctx.local(&strip.uri).await?;
    let entry = strip_entry(&strip, &local.path)?;
    let name = format!("strips/{}", precimap_pipeline::tasks::export_strip_name(&entry));
    let key = format!("{prefix}/out/{tag}/{name}");
    let points = std::sync::Arc::new(std::sync::atomic::AtomicU64::new(0));
    let counter = points.clone();
    ctx.put_produced(&key, move |dst| {
        let n = export_strip_file(&entry, &traj, anchor_spacing_m, &corrections, mounting.as_ref(), dst)?;
        counter.store(n, std::sync::atomic::Ordering::Relaxed);
        Ok(())
    })
    .await
    .map_err(|e| e.naming(&strip.uri, &local.path))?;
    drop(local);
    let result = ExportResult {
        points: points.load(std::sync::atomic::Ordering::Relaxed),
        seconds: started.elapsed().as_secs_f64(),
    };
    Ok(TaskOutcome { result: to_json(&result)?, outputs: vec![OutputKey { name, object_key: key }] })
}

pub(super) async fn export_trajectory(
    at: &Attempt<'_>,
    prefix: String,
    trajectory: TrajectoryInput,
    anchor_spacing_m: f64,
    corrections: CorrectionsRef,
    params: Option<Box<Parameters>>,
) -> Result<TaskOutcome, TaskError> {
    let (ctx, tag, started) = (at.ctx, at.tag.as_str(), at.started);
    let (corrections, covariance) = read_corrections(ctx, &corrections).await?;
    let entry = read_trajectory(ctx, &trajectory).await?;
    let estimated = (corrections.first_anchor, corrections.last_anchor());
    let corrections = match params {
        Some(params) => corrections_for_export(&entry, &corrections, &params),
        None => corrections,
    };
    let name = format!("trajectories/{}.csv", trajectory.id);
    let key = format!("{prefix}/out/{tag}/{name}");
    let beside: Vec<(String, String, Vec<u8>)> =
        corrections_outputs(&entry, anchor_spacing_m, &corrections, estimated, covariance.as_deref())
            .into_iter()
            .map(|(name, bytes)| (name.clone(), format!("{prefix}/out/{tag}/{name}"), bytes))
            .collect();
    ctx.put_produced(&key, move |dst| export_trajectory_file(&entry, anchor_spacing_m, &corrections, dst)).await?;
    let mut outputs = vec![OutputKey { name, object_key: key }];
    outputs.extend(ctx.put_many(beside).await?);
    let result = ExportResult { points: 0, seconds: started.elapsed().as_secs_f64() };
    Ok(TaskOutcome { result: to_json(&result)?, outputs })
}
