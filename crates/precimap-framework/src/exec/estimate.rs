//! `estimate_tile`: a tile's latent map, normal-equation blocks and field equations.

use super::*;
use crate::plan::ChunkRef;
use precimap_core::{IterationStep, TileKey};

/// The input of an `estimate_tile` task ([`TaskInput::EstimateTile`]).
#[derive(Debug)]
pub(super) struct TileTask {
    pub(super) prefix: String,
    pub(super) iteration: u32,
    pub(super) tile: TileKey,
    pub(super) step: IterationStep,
    pub(super) params: Option<Box<Parameters>>,
    pub(super) trajectories: u32,
    pub(super) chunks: Vec<ChunkRef>,
    pub(super) corrections: Vec<CorrectionsRef>,
    pub(super) std_map: bool,
    pub(super) latent_map: bool,
    pub(super) crs: Option<precimap_formats::CrsSpec>,
    pub(super) control: Vec<precimap_core::ControlTarget>,
    pub(super) calibration: Option<CalibrationInput>,
}

pub(super) async fn estimate_tile(at: &Attempt<'_>, task: TileTask) -> Result<TaskOutcome, TaskError> {
    let TileTask {
        prefix,
        iteration,
        tile,
        step,
        params,
        trajectories,
        chunks,
        corrections,
        std_map,
        latent_map,
        crs,
        control,
        calibration,
    } = task;
    let (ctx, tag, started) = (at.ctx, at.tag.as_str(), at.started);
    let params = required(params)?;
    let georef = georeference_of(crs.as_ref())?;
    let chunk_keys: Vec<String> = chunks.iter().map(|c| c.key.clone()).collect();
    let bytes = ctx.get_many(&chunk_keys).await?;
    let decoded: Vec<(String, Bytes)> = chunk_keys.into_iter().zip(bytes).collect();
    let mut all = vec![TrajectoryCorrections::zeros(0, 0); trajectories as usize];
    for (c, read) in corrections.iter().zip(read_corrections_many(ctx, &corrections).await?) {
        let slot = all
            .get_mut(c.trajectory as usize)
            .ok_or_else(|| TaskError::permanent(format!("tile {tile}: unknown trajectory {}", c.trajectory)))?;
        *slot = read;
    }
    let (estimate, latent_map) = blocking(move || {
        // Each object's bytes are dropped once decoded, as the in-process driver reads them.
        let chunks = decoded
            .into_iter()
            .map(|(key, bytes)| {
                TileChunk::decode(&bytes).map_err(|e| TaskError::permanent(format!("tile chunk {key}: {e}")))
            })
            .collect::<Result<Vec<_>, _>>()?;
        let gather = precimap_estimate::LatentGather { std_map, map: latent_map };
        let calibration = calibration.as_ref().map(CalibrationInput::tile);
        let mut estimate = precimap_estimate::estimate_tile_recording(
            tile,
            &chunks,
            &all,
            &params,
            &step,
            &control,
            calibration.as_ref(),
            None,
            gather,
        )
        .map_err(|e| TaskError::permanent(format!("tile {tile}: {e}")))?;
        let map = match estimate.latent_map.take() {
            Some(points) => {
                let (points, wkt) = precimap_pipeline::tasks::latent_map_in_crs(tile, &points, georef.as_ref())
                    .map_err(|e| TaskError::permanent(e.to_string()))?;
                Some(
                    precimap_formats::encode_latent_map(&points, wkt)
                        .map_err(|e| TaskError::permanent(format!("tile {tile}: latent map does not encode: {e}")))?,
                )
            }
            None => None,
        };
        Ok::<_, TaskError>((estimate, map))
    })
    .await??;
    let mut objects = Vec::with_capacity(estimate.blocks.len() + 1);
    for tb in &estimate.blocks {
        let key = format!("{prefix}/it/{iteration}/blocks/{}/{tile}.{tag}.blk", tb.trajectory);
        let bytes = encode_trajectory_blocks(&tb.blocks, tb.calibration.as_ref());
        objects.push((format!("{BLOCKS_PREFIX}{}", tb.trajectory), key, bytes));
    }
    if let Some(field) = &estimate.field {
        let key = format!("{prefix}/it/{iteration}/field/{tile}.{tag}.fld");
        objects.push((OUTPUT_FIELD.into(), key, encode_field(field)));
    }
    if let Some(map) = &estimate.latent_std {
        let key = format!("{prefix}/it/{iteration}/latent-std/{tile}.{tag}.json");
        objects.push((OUTPUT_LATENT_STD.into(), key, to_bytes(map)?));
    }
    if let Some(bytes) = latent_map {
        let key = format!("{prefix}/it/{iteration}/latent/{tile}.{tag}.las");
        objects.push((precimap_pipeline::tasks::latent_map_name(tile), key, bytes));
    }
    let outputs = ctx.put_many(objects).await?;
    let result = EstimateResult { stats: estimate.stats, seconds: started.elapsed().as_secs_f64() };
    Ok(TaskOutcome { result: to_json(&result)?, outputs })
}
