//! What happens to stored objects after they are written: which of a campaign's objects stay
//! once it has finished (results always, work files for a while, nothing of a cancelled one),
//! deletion of a campaign with the inputs it alone named, and the sweeps that remove what no
//! campaign owns (prefixes of deleted campaigns, abandoned temporary uploads, expired inputs).

use crate::error::FrameworkError;
use crate::objects::{is_temporary_key, Objects};
use crate::plan::{SEGMENTS_PREFIX, STAGE_EXPORT, STAGE_PREPARE, STAGE_REPORT};
use precimap_jobs::{CampaignState, DeletedCampaign, JobStore};
use std::collections::HashSet;
use std::time::{Duration, SystemTime, UNIX_EPOCH};
use tracing::{info, warn};
use uuid::Uuid;

/// Every campaign writes under `c/{id}` (its object prefix).
pub const CAMPAIGNS_PREFIX: &str = "c";
/// Uploads land under `inputs/`; manifests may name nothing else.
pub const INPUTS_PREFIX: &str = "inputs";
/// A temporary upload file not written to for this long belongs to an upload that died (a live
/// upload keeps writing to it; the server's body timeouts end stalled ones long before).
pub const ABANDONED_UPLOAD_AGE: Duration = Duration::from_secs(3600);

/// How long objects are kept.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Retention {
    /// A finished campaign's work files (everything it wrote that is not a result): kept this
    /// long after it finished, `None` for ever. Default zero: removed as it finishes.
    pub work: Option<Duration>,
    /// A finished campaign (its rows, results and the inputs it alone named) is deleted this
    /// long after it finished; `None` (the default) keeps it until a client deletes it.
    pub campaigns: Option<Duration>,
    /// Inputs no campaign names are deleted once unmodified for this long; `None` (the
    /// default) keeps them until a client deletes them.
    pub inputs: Option<Duration>,
    /// How often an executor sweeps the store for what no campaign owns (and applies the
    /// campaign and input retention).
    pub store_sweep_interval: Duration,
}

impl Default for Retention {
    fn default() -> Self {
        Self {
            work: Some(Duration::ZERO),
            campaigns: None,
            inputs: None,
            store_sweep_interval: Duration::from_secs(300),
        }
    }
}

impl Retention {
    /// Keeps everything (work files included) except what no campaign owns.
    pub fn keep_everything() -> Self {
        Self { work: None, ..Self::default() }
    }

    /// Whether a campaign that has just finished keeps its work files for now.
    pub fn keeps_work_at_finish(&self) -> bool {
        self.work.is_none_or(|d| !d.is_zero())
    }
}

/// The object keys of a campaign's results: segmentations, exported strips and trajectories,
/// the report, its plots and the latent map.
pub async fn result_keys(jobs: &JobStore, id: Uuid) -> Result<Vec<(String, String)>, FrameworkError> {
    let mut out: Vec<(String, String)> = jobs
        .outputs(id, STAGE_PREPARE, 0)
        .await?
        .into_iter()
        .filter(|o| o.name.starts_with(SEGMENTS_PREFIX))
        .map(|o| (o.name, o.object_key))
        .collect();
    for stage in [STAGE_EXPORT, STAGE_REPORT] {
        for o in jobs.outputs(id, stage, 0).await? {
            out.push((o.name, o.object_key));
        }
    }
    out.sort();
    Ok(out)
}

/// Deletes the campaign's objects that are no longer wanted; returns how many.
///
/// A running campaign loses only the outputs of lost attempts (objects no committed task
/// recorded and no live attempt may still be writing). A cancelled campaign loses everything
/// under its prefix; a succeeded one everything but its results, a failed one everything —
/// except, with `keep_work`, the objects its tasks recorded.
pub async fn sweep_campaign(
    jobs: &JobStore,
    objects: &Objects,
    id: Uuid,
    keep_work: bool,
) -> Result<usize, FrameworkError> {
    let (Some(progress), Some(prefix)) = (jobs.campaign_progress(id).await?, jobs.object_prefix(id).await?) else {
        return Ok(0);
    };
    let mut keep: HashSet<String> = HashSet::new();
    let mut live: Vec<String> = Vec::new();
    match progress.state {
        CampaignState::Running => {
            keep.extend(jobs.recorded_keys(id).await?);
            live = jobs
                .live_lease_tokens(id)
                .await?
                .into_iter()
                .map(|t| t.simple().to_string()[..12].to_string())
                .collect();
        }
        CampaignState::Cancelled => {}
        CampaignState::Succeeded | CampaignState::Failed => {
            if keep_work {
                keep.extend(jobs.recorded_keys(id).await?);
            } else if progress.state == CampaignState::Succeeded {
                keep.extend(result_keys(jobs, id).await?.into_iter().map(|(_, key)| key));
            }
        }
    }
    let prefix = prefix.trim_end_matches('/');
    if keep.is_empty() && progress.state != CampaignState::Running {
        return objects.delete_prefix(prefix).await;
    }
    let mut removed = 0;
    for key in objects.list(prefix).await? {
        if keep.contains(&key) || live.iter().any(|tag| key.contains(tag.as_str())) {
            continue;
        }
        objects.delete(&key).await?;
        removed += 1;
    }
    Ok(removed)
}

/// Removes a campaign's rows, every object under its prefix and the inputs it alone named.
/// `None` if there is no such campaign.
pub async fn delete_campaign(
    jobs: &JobStore,
    objects: &Objects,
    id: Uuid,
) -> Result<Option<DeletedCampaign>, FrameworkError> {
    let Some(deleted) = jobs.delete_campaign_with_inputs(id).await? else { return Ok(None) };
    objects.delete_prefix(deleted.object_prefix.trim_end_matches('/')).await?;
    for key in &deleted.unreferenced_inputs {
        objects.delete(key).await?;
    }
    Ok(Some(deleted))
}

/// What one [`sweep_store`] removed.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct StoreSweep {
    /// Objects under prefixes no campaign owns (deleted campaigns' stragglers).
    pub orphaned_objects: usize,
    /// Temporary files of uploads that died.
    pub abandoned_uploads: usize,
    /// Inputs no campaign names, older than the input retention.
    pub expired_inputs: usize,
    /// Finished campaigns older than the campaign retention, deleted.
    pub expired_campaigns: usize,
}

/// Removes what no campaign owns: objects under campaign prefixes without a campaign (written by
/// attempts of a deleted campaign after its deletion), temporary upload files untouched for
/// [`ABANDONED_UPLOAD_AGE`], and, by `retention`, expired campaigns and unreferenced inputs.
pub async fn sweep_store(
    jobs: &JobStore,
    objects: &Objects,
    retention: &Retention,
) -> Result<StoreSweep, FrameworkError> {
    let mut sweep = StoreSweep::default();
    if let Some(age) = retention.campaigns {
        for id in jobs.finished_before(age, 1000).await? {
            if delete_campaign(jobs, objects, id).await?.is_some() {
                sweep.expired_campaigns += 1;
            }
        }
    }
    // Prefixes are read after the listing: a campaign created in between owns a prefix the
    // listing does not show yet, never one it shows.
    let folders = objects.list_folders(CAMPAIGNS_PREFIX).await?;
    let owned: HashSet<String> = jobs.object_prefixes().await?.into_iter().collect();
    for folder in folders {
        let folder = folder.trim_end_matches('/');
        if !owned.contains(folder) {
            sweep.orphaned_objects += objects.delete_prefix(folder).await?;
        }
    }
    let now_ms = SystemTime::now().duration_since(UNIX_EPOCH).map_or(0, |d| d.as_millis() as i64);
    let older = |modified_ms: i64, age: Duration| now_ms.saturating_sub(modified_ms) >= age.as_millis() as i64;
    let inputs = objects.list_meta(INPUTS_PREFIX).await?;
    let mut candidates = Vec::new();
    for object in inputs {
        if is_temporary_key(&object.key) {
            if older(object.modified_ms, ABANDONED_UPLOAD_AGE) {
                objects.delete(&object.key).await?;
                sweep.abandoned_uploads += 1;
            }
        } else if retention.inputs.is_some_and(|age| older(object.modified_ms, age)) {
            candidates.push(object.key);
        }
    }
    if !candidates.is_empty() {
        let named: HashSet<String> = jobs.input_references(&candidates).await?.into_iter().map(|r| r.key).collect();
        for key in candidates.into_iter().filter(|k| !named.contains(k)) {
            objects.delete(&key).await?;
            sweep.expired_inputs += 1;
        }
    }
    if sweep != StoreSweep::default() {
        info!(?sweep, "swept the object store");
    }
    Ok(sweep)
}

/// [`sweep_store`], logging instead of failing (a failed sweep only postpones the clean-up).
pub(crate) async fn sweep_store_logged(jobs: &JobStore, objects: &Objects, retention: &Retention) {
    if let Err(e) = sweep_store(jobs, objects, retention).await {
        warn!(error = %e, "sweeping the object store failed");
    }
}
