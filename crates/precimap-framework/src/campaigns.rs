//! Campaign life cycle on top of the job store and the object store: submit, results, delete,
//! orphan clean-up, and the embedded `run` (SQLite + a local store + in-process executors).

use crate::error::FrameworkError;
use crate::exec::TaskContext;
use crate::objects::{validate_key, Objects};
use crate::plan::{new_campaign, SEGMENTS_PREFIX, STAGE_EXPORT, STAGE_PREPARE, STAGE_REPORT};
use crate::worker::{Executor, ExecutorConfig};
use precimap_formats::{Manifest, ManifestProblem};
use precimap_jobs::{CampaignRecord, CampaignState, JobStore, QueueConfig};
use std::collections::HashSet;
use std::path::{Path, PathBuf};
use std::time::Duration;
use uuid::Uuid;

/// The configured pair every component works with.
#[derive(Clone, Debug)]
pub struct Framework {
    pub jobs: JobStore,
    pub objects: Objects,
    pub queue: QueueConfig,
}

/// Why a submission was refused: every problem with its JSON path, like manifest validation.
#[derive(Debug, thiserror::Error)]
pub enum SubmitError {
    #[error("{}", problems.iter().map(ToString::to_string).collect::<Vec<_>>().join("\n"))]
    Invalid { problems: Vec<ManifestProblem> },
    #[error(transparent)]
    Framework(#[from] FrameworkError),
}

pub fn default_queue() -> QueueConfig {
    QueueConfig { max_attempts: 5, backoff_base: Duration::from_secs(1), backoff_max: Duration::from_secs(60) }
}

impl Framework {
    /// Creates a campaign from a validated manifest whose URIs name objects in the store; every
    /// missing object is reported with its JSON path.
    pub async fn submit(&self, manifest: &Manifest) -> Result<Uuid, SubmitError> {
        let mut problems = Vec::new();
        let named = manifest
            .trajectories
            .iter()
            .enumerate()
            .map(|(i, t)| (format!("$.trajectories[{i}].uri"), &t.uri))
            .chain(manifest.strips.iter().enumerate().map(|(i, s)| (format!("$.strips[{i}].uri"), &s.uri)));
        for (path, uri) in named {
            if let Err(message) = validate_key(uri) {
                problems.push(ManifestProblem { path, message });
                continue;
            }
            if !self.objects.exists(uri).await? {
                problems.push(ManifestProblem {
                    path,
                    message: format!(
                        "no object {uri:?} in the store {}; upload it first (`precimap submit` uploads the files a local manifest names)",
                        self.objects.url()
                    ),
                });
            }
        }
        if !problems.is_empty() {
            return Err(SubmitError::Invalid { problems });
        }
        let prefix = format!("c/{}", Uuid::new_v4().simple());
        let (campaign, first) = new_campaign(manifest, &prefix, self.queue);
        Ok(self.jobs.create_campaign(campaign, first).await.map_err(FrameworkError::from)?)
    }

    /// The downloadable results of a succeeded campaign: `(name, object key)` with names such as
    /// `strips/p01-left.las`, `trajectories/p01.csv`, `report.json`.
    pub async fn results(&self, id: Uuid) -> Result<Vec<(String, String)>, FrameworkError> {
        let mut out: Vec<(String, String)> = self
            .jobs
            .outputs(id, STAGE_PREPARE, 0)
            .await?
            .into_iter()
            .filter(|o| o.name.starts_with(SEGMENTS_PREFIX))
            .map(|o| (o.name, o.object_key))
            .collect();
        for stage in [STAGE_EXPORT, STAGE_REPORT] {
            for o in self.jobs.outputs(id, stage, 0).await? {
                out.push((o.name, o.object_key));
            }
        }
        out.sort();
        Ok(out)
    }

    /// Writes the results into `dir` in `precimap run`'s layout. A `file://` store hands its
    /// files over by hard link where it can.
    pub async fn download_results(&self, id: Uuid, dir: &Path) -> Result<usize, FrameworkError> {
        let results = self.results(id).await?;
        for (name, key) in &results {
            validate_key(name).map_err(FrameworkError::Invalid)?;
            let dst = dir.join(name);
            if let Some(parent) = dst.parent() {
                std::fs::create_dir_all(parent).map_err(|e| FrameworkError::io(parent, e))?;
            }
            let _ = std::fs::remove_file(&dst);
            match self.objects.local_path(key) {
                Some(src) if std::fs::hard_link(&src, &dst).is_ok() => {}
                _ => {
                    self.objects.get_to_file(key, &dst).await?;
                }
            }
        }
        Ok(results.len())
    }

    /// Deletes the outputs of lost attempts (see [`clean_orphans`]).
    pub async fn clean_orphans(&self, id: Uuid) -> Result<usize, FrameworkError> {
        clean_orphans(&self.jobs, &self.objects, id).await
    }

    /// Removes a campaign's rows and every object under its prefix.
    pub async fn delete(&self, id: Uuid) -> Result<bool, FrameworkError> {
        match self.jobs.delete_campaign(id).await? {
            None => Ok(false),
            Some(prefix) => {
                self.objects.delete_prefix(&prefix).await?;
                Ok(true)
            }
        }
    }
}

/// Deletes objects under a campaign's prefix that no committed task recorded and no live attempt
/// may still be writing (outputs of attempts whose lease was lost). Returns how many. Executors
/// call it when a campaign finishes; an attempt cancelled by a failure may still write afterwards,
/// and deleting the campaign removes those.
pub async fn clean_orphans(jobs: &JobStore, objects: &Objects, id: Uuid) -> Result<usize, FrameworkError> {
    let Some(campaign) = jobs.campaign(id).await? else { return Ok(0) };
    let recorded: HashSet<String> = jobs.recorded_keys(id).await?.into_iter().collect();
    let live: Vec<String> =
        jobs.live_lease_tokens(id).await?.into_iter().map(|t| t.simple().to_string()[..12].to_string()).collect();
    let mut removed = 0;
    for key in objects.list(&campaign.object_prefix).await? {
        if recorded.contains(&key) || live.iter().any(|tag| key.contains(tag.as_str())) {
            continue;
        }
        objects.delete(&key).await?;
        removed += 1;
    }
    Ok(removed)
}

/// Plans the upload of the files a local manifest names: the manifest with its URIs rewritten
/// to keys under `inputs/{upload id}/`, and the `(local file, key)` pairs to upload.
pub fn plan_local_upload(manifest_path: &Path) -> Result<(Manifest, Vec<(PathBuf, String)>), FrameworkError> {
    let mut manifest = precimap_formats::load_manifest(manifest_path)?;
    let dir = manifest_path.parent().unwrap_or(Path::new(".")).to_path_buf();
    let base = format!("inputs/{}", Uuid::new_v4().simple());
    let mut uris: Vec<&mut String> = manifest.trajectories.iter_mut().map(|t| &mut t.uri).collect();
    uris.extend(manifest.strips.iter_mut().map(|s| &mut s.uri));
    let mut files = Vec::with_capacity(uris.len());
    for uri in uris {
        let src = precimap_formats::resolve_uri(&dir, uri).map_err(FrameworkError::Invalid)?;
        let relative = src.strip_prefix(&dir).unwrap_or(&src).to_string_lossy().replace('\\', "/");
        let key = format!("{base}/{relative}");
        files.push((src, key.clone()));
        *uri = key;
    }
    Ok((manifest, files))
}

/// Copies (hard-links where possible) the files a local manifest names into the store (see
/// [`plan_local_upload`]) and returns the manifest with its URIs rewritten to their keys.
pub async fn upload_local_inputs(objects: &Objects, manifest_path: &Path) -> Result<Manifest, FrameworkError> {
    let (manifest, files) = plan_local_upload(manifest_path)?;
    for (src, key) in files {
        match objects.local_path(&key) {
            Some(dst) => {
                if let Some(parent) = dst.parent() {
                    std::fs::create_dir_all(parent).map_err(|e| FrameworkError::io(parent, e))?;
                }
                if std::fs::hard_link(&src, &dst).is_err() {
                    objects.put_file(&key, &src).await?;
                }
            }
            None => {
                objects.put_file(&key, &src).await?;
            }
        }
    }
    Ok(manifest)
}

/// What the embedded runner reports while it works.
#[derive(Clone, Debug)]
pub struct RunStatus {
    pub campaign: precimap_jobs::CampaignProgress,
    /// Task counts of the current stage.
    pub stage_counts: precimap_jobs::StateCounts,
    /// Every iteration recorded so far.
    pub iterations: Vec<precimap_jobs::IterationRecord>,
}

#[derive(Clone, Debug)]
pub struct EmbeddedOptions {
    pub out_dir: PathBuf,
    pub concurrency: usize,
    /// Keep the job database and the store in `OUT/.precimap` after the run.
    pub keep_state: bool,
}

/// The embedded default: SQLite in `OUT/.precimap/jobs.db`, a file store in
/// `OUT/.precimap/store`, `concurrency` in-process executors; results land in `OUT` exactly as
/// the in-process driver writes them.
pub async fn run_embedded(
    manifest_path: &Path,
    options: &EmbeddedOptions,
    mut progress: impl FnMut(&RunStatus),
) -> Result<CampaignRecord, FrameworkError> {
    let state = options.out_dir.join(".precimap");
    if state.exists() {
        std::fs::remove_dir_all(&state).map_err(|e| FrameworkError::io(&state, e))?;
    }
    std::fs::create_dir_all(&state).map_err(|e| FrameworkError::io(&state, e))?;
    let state = state.canonicalize().map_err(|e| FrameworkError::io(&state, e))?;
    let jobs = JobStore::connect(&format!("sqlite://{}", state.join("jobs.db").display())).await?;
    let objects = Objects::from_url(&format!("file://{}", state.join("store").display()))?;
    let framework = Framework { jobs: jobs.clone(), objects: objects.clone(), queue: default_queue() };
    let manifest = upload_local_inputs(&objects, manifest_path).await?;
    let id = match framework.submit(&manifest).await {
        Ok(id) => id,
        Err(SubmitError::Framework(e)) => return Err(e),
        Err(e @ SubmitError::Invalid { .. }) => return Err(FrameworkError::Invalid(e.to_string())),
    };
    let ctx = TaskContext::new(objects.clone(), state.join("scratch"));
    let executor = Executor::new(jobs.clone(), ctx, ExecutorConfig::default());
    let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
    let concurrency = options.concurrency;
    let workers = tokio::spawn(async move { executor.work_loop(concurrency, stop_rx).await });
    // The poll reads only what the display shows (state, the current stage's counts, iterations
    // not seen yet): it runs beside the executors, so its CPU is theirs.
    let mut iterations: Vec<precimap_jobs::IterationRecord> = Vec::new();
    let finished = loop {
        tokio::time::sleep(Duration::from_millis(200)).await;
        if workers.is_finished() {
            break false;
        }
        let Some(campaign) = jobs.campaign_progress(id).await? else { break false };
        let seen = iterations.last().map_or(0, |i| i.iteration);
        iterations.extend(jobs.iterations_after(id, seen).await?);
        let status = RunStatus {
            stage_counts: jobs.stage_counts(id, &campaign.stage, campaign.iteration).await?,
            iterations,
            campaign,
        };
        progress(&status);
        if status.campaign.state != CampaignState::Running {
            break true;
        }
        iterations = status.iterations;
    };
    let _ = stop_tx.send(true);
    let joined = workers.await.map_err(|e| FrameworkError::Internal(e.to_string()))?;
    joined?;
    let campaign = if finished { jobs.campaign(id).await? } else { None }
        .ok_or_else(|| FrameworkError::Internal("the campaign disappeared".into()))?;
    if campaign.state != CampaignState::Succeeded {
        return Err(FrameworkError::CampaignFailed {
            id,
            state: campaign.state.as_str().to_string(),
            error: campaign.error.clone().unwrap_or_default(),
        });
    }
    framework.download_results(id, &options.out_dir).await?;
    if !options.keep_state {
        drop(framework);
        drop(jobs);
        std::fs::remove_dir_all(&state).map_err(|e| FrameworkError::io(&state, e))?;
    }
    Ok(campaign)
}
