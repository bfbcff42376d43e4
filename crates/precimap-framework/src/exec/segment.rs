//! `segment_strip`: a strip's geometry, normals and segments, cut into tile chunks.

use super::*;

pub(super) async fn segment_strip(
    at: &Attempt<'_>,
    prefix: String,
    strip: StripInput,
    params: Option<Box<Parameters>>,
) -> Result<TaskOutcome, TaskError> {
    let (ctx, tag, started) = (at.ctx, at.tag.as_str(), at.started);
    let params = required(params)?;
    let traj = read_trajectory(ctx, &strip_trajectory(&strip)).await?;
    // A damaged accuracy file stops the campaign here, before any estimation, as it stops the
    // in-process driver when the campaign loads.
    read_accuracy(ctx, &strip_trajectory(&strip)).await?;
    let local = ctx.local(&strip.uri).await?;
    let entry = strip_entry(&strip, &local.path)?;
    let index = strip.index;
    let prepared = blocking(move || {
        prepare_strip_chunks(&entry, index, &traj, &params, &SegmentParams::default()).map(|p| {
            let segments = precimap_formats::encode_segments(&p.segment);
            // Each decoded chunk is dropped once encoded: the strip is held once, not twice.
            let encoded: Vec<_> = p.chunks.into_iter().map(|c| (c.tile, c.encode())).collect();
            (p.stats, encoded, segments)
        })
    })
    .await?
    .map_err(|e| TaskError::from_pipeline(e).naming(&strip.uri, &local.path))?;
    drop(local);
    let (stats, chunks, segments) = prepared;
    let mut outputs = Vec::with_capacity(chunks.len() + 1);
    // The segmentation is a result too (evaluate measures its purity).
    let name = format!("{SEGMENTS_PREFIX}{}.seg", strip.id);
    let key = format!("{prefix}/out/{tag}/{name}");
    ctx.put(&key, segments).await?;
    outputs.push(OutputKey { name, object_key: key });
    let mut tiles = Vec::with_capacity(chunks.len());
    for (tile, bytes) in chunks {
        let key = format!("{prefix}/tiles/{tile}/{}.{tag}.chunk", strip.id);
        ctx.put(&key, bytes).await?;
        outputs.push(OutputKey { name: tile.to_string(), object_key: key });
        tiles.push(tile);
    }
    let result = SegmentResult { strip: strip.index, stats, tiles, seconds: started.elapsed().as_secs_f64() };
    Ok(TaskOutcome { result: to_json(&result)?, outputs })
}
