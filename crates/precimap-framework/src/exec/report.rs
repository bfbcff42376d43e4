//! `write_report`: report.json and the QC plots.

use super::*;
use crate::plan::LatentStdKeys;
use precimap_pipeline::report::Report;

#[allow(clippy::too_many_arguments)]
pub(super) async fn write_report(
    at: &Attempt<'_>,
    prefix: String,
    report: Box<Report>,
    latent_std: LatentStdKeys,
    tile_size_m: f64,
    latent_map: Vec<(String, String)>,
    georef: Option<&precimap_formats::crs::Georeference>,
) -> Result<TaskOutcome, TaskError> {
    let (ctx, tag, started) = (at.ctx, at.tag.as_str(), at.started);
    let key = format!("{prefix}/out/{tag}/report.json");
    let json = serde_json::to_vec_pretty(&report)
        .map_err(|e| TaskError::permanent(format!("report does not serialise: {e}")))?;
    let mut objects = vec![("report.json".to_string(), key, json)];
    let mut maps = [Vec::new(), Vec::new()];
    for (list, refs) in maps.iter_mut().zip([&latent_std.first, &latent_std.last]) {
        let keys: Vec<String> = refs.iter().map(|(_, key)| key.clone()).collect();
        for ((tile, key), bytes) in refs.iter().zip(ctx.get_many(&keys).await?) {
            let map: precimap_estimate::LatentStdMap = serde_json::from_slice(&bytes)
                .map_err(|e| TaskError::permanent(format!("latent-map QC object {key}: {e}")))?;
            list.push((*tile, map));
        }
    }
    let [first, last] = &maps;
    let plots = precimap_pipeline::qc::report_qc(&report).into_iter().chain(precimap_pipeline::qc::latent_std_plots(
        tile_size_m,
        first,
        last,
        georef,
    ));
    for (name, svg) in plots {
        let key = format!("{prefix}/out/{tag}/{name}");
        objects.push((name, key, svg.into_bytes()));
    }
    let mut outputs = ctx.put_many(objects).await?;
    // The latent map's tiles stay where their estimate tasks recorded them.
    outputs.extend(latent_map.into_iter().map(|(name, object_key)| OutputKey { name, object_key }));
    Ok(TaskOutcome { result: serde_json::json!({ "seconds": started.elapsed().as_secs_f64() }), outputs })
}
