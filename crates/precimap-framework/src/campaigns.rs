//! Campaign life cycle on top of the job store and the object store: submit, results, delete,
//! orphan clean-up, and the embedded `run` (SQLite + a local store + in-process executors).

use crate::error::FrameworkError;
use crate::exec::TaskContext;
use crate::lifecycle::{delete_campaign, result_keys, sweep_campaign, Retention, CAMPAIGNS_PREFIX, INPUTS_PREFIX};
use crate::objects::{is_temporary_key, validate_key, Objects};
use crate::plan::new_campaign;
use crate::worker::{Executor, ExecutorConfig};
use precimap_formats::{Manifest, ManifestProblem};
use precimap_jobs::{CampaignRecord, CampaignState, JobStore, QueueConfig};
use precimap_pipeline::ResolvedManifest;
use std::collections::HashMap;
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

/// Bounds on what one submission may ask of the server, checked before anything is stored.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct CampaignLimits {
    pub max_strips: usize,
    pub max_trajectories: usize,
    /// Sum of the sizes of the distinct input objects the manifest names.
    pub max_input_bytes: u64,
}

impl Default for CampaignLimits {
    /// 10,000 strips, 1,000 trajectories, 1 TiB of inputs.
    fn default() -> Self {
        Self { max_strips: 10_000, max_trajectories: 1_000, max_input_bytes: 1 << 40 }
    }
}

impl CampaignLimits {
    /// No bounds (the embedded runner: the user's own machine and files).
    pub const UNBOUNDED: CampaignLimits =
        CampaignLimits { max_strips: usize::MAX, max_trajectories: usize::MAX, max_input_bytes: u64::MAX };

    /// The counts over their bounds, as manifest problems.
    fn count_problems(&self, manifest: &Manifest) -> Vec<ManifestProblem> {
        let mut problems = Vec::new();
        for (path, n, max, setting) in [
            ("$.strips", manifest.strips.len(), self.max_strips, "--max-strips (PRECIMAP_MAX_STRIPS)"),
            (
                "$.trajectories",
                manifest.trajectories.len(),
                self.max_trajectories,
                "--max-trajectories (PRECIMAP_MAX_TRAJECTORIES)",
            ),
        ] {
            if n > max {
                let what = &path[2..];
                problems.push(ManifestProblem {
                    path: path.to_string(),
                    message: format!(
                        "{n} {what}: this server accepts at most {max} {what} per campaign (its {setting}); \
                         split the campaign"
                    ),
                });
            }
        }
        problems
    }
}

/// Why `key` cannot be a campaign's input, if it cannot: only complete uploads under `inputs/`.
fn input_key_problem(key: &str) -> Option<String> {
    if let Err(message) = validate_key(key) {
        return Some(message);
    }
    if !key.starts_with(&format!("{INPUTS_PREFIX}/")) {
        return Some(format!(
            "{key:?} is not an input: a manifest may name only uploaded objects under {INPUTS_PREFIX}/ \
             (PUT /v1/objects/{INPUTS_PREFIX}/…)"
        ));
    }
    if is_temporary_key(key) {
        return Some(format!("{key:?} is the temporary file of an upload, not a complete object"));
    }
    None
}

impl Framework {
    /// Creates a campaign from a validated manifest whose URIs name objects in the store, without
    /// bounds on its size (see [`Framework::submit_with_limits`]).
    pub async fn submit(&self, manifest: &Manifest) -> Result<Uuid, SubmitError> {
        self.submit_with_limits(manifest, &CampaignLimits::UNBOUNDED).await
    }

    /// Creates a campaign from a validated manifest whose URIs name complete uploads under
    /// `inputs/`; every problem is reported with its JSON path: a campaign over `limits`, a URI
    /// outside `inputs/` or naming a temporary upload file, a missing object.
    pub async fn submit_with_limits(&self, manifest: &Manifest, limits: &CampaignLimits) -> Result<Uuid, SubmitError> {
        let problems = limits.count_problems(manifest);
        if !problems.is_empty() {
            return Err(SubmitError::Invalid { problems });
        }
        let mut problems = Vec::new();
        if !manifest.parameters.process_model.is_fixed() {
            // The estimated σ's are a state carried between iterations, which the framework's
            // tasks do not carry: it would solve with the fixed σ's without saying so.
            problems.push(ManifestProblem {
                path: "$.parameters.process_model".into(),
                message: "an estimated process model runs in the in-process driver only (`precimap run`); \
                          the job framework solves with the fixed curvature σ's"
                    .into(),
            });
        }
        let named = manifest
            .trajectories
            .iter()
            .enumerate()
            .map(|(i, t)| (format!("$.trajectories[{i}].uri"), &t.uri))
            .chain(manifest.trajectories.iter().enumerate().filter_map(|(i, t)| {
                t.accuracy_uri.as_ref().map(|uri| (format!("$.trajectories[{i}].accuracy_uri"), uri))
            }))
            .chain(manifest.strips.iter().enumerate().map(|(i, s)| (format!("$.strips[{i}].uri"), &s.uri)));
        let mut sizes: HashMap<&str, u64> = HashMap::new();
        for (path, uri) in named {
            if let Some(message) = input_key_problem(uri) {
                problems.push(ManifestProblem { path, message });
                continue;
            }
            match self.objects.size(uri).await? {
                Some(bytes) => {
                    sizes.insert(uri.as_str(), bytes);
                }
                None => problems.push(ManifestProblem {
                    path,
                    message: format!(
                        "no object {uri:?} in the store; upload it first (`precimap submit` uploads the files a local manifest names)"
                    ),
                }),
            }
        }
        let total: u64 = sizes.values().sum();
        if total > limits.max_input_bytes {
            problems.push(ManifestProblem {
                path: "$".into(),
                message: format!(
                    "the inputs total {total} bytes: this server accepts at most {} per campaign (its \
                     --max-input-bytes, PRECIMAP_MAX_INPUT_BYTES); split the campaign",
                    limits.max_input_bytes
                ),
            });
        }
        // The manifest is validated, so its strips' references resolve: what can fail here is a
        // control target's conversion into the processing frame (the message names the target).
        let resolved = ResolvedManifest::new(manifest)
            .map_err(|e| problems.push(ManifestProblem { path: "$".into(), message: e.to_string() }));
        let resolved = match resolved {
            Ok(resolved) if problems.is_empty() => resolved,
            _ => return Err(SubmitError::Invalid { problems }),
        };
        let prefix = format!("{CAMPAIGNS_PREFIX}/{}", Uuid::new_v4().simple());
        let (campaign, first) = new_campaign(manifest, resolved, &prefix, self.queue);
        Ok(self.jobs.create_campaign(campaign, first).await.map_err(FrameworkError::from)?)
    }

    /// The downloadable results of a succeeded campaign: `(name, object key)` with names such as
    /// `strips/p01-left.las`, `trajectories/p01.csv`, `report.json`.
    pub async fn results(&self, id: Uuid) -> Result<Vec<(String, String)>, FrameworkError> {
        result_keys(&self.jobs, id).await
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

    /// Cancels a running campaign and removes every object under its prefix (its attempts still
    /// running write nothing more: their next write is refused, see [`crate::WriteGate`]).
    /// False if it had already finished.
    pub async fn cancel(&self, id: Uuid) -> Result<bool, FrameworkError> {
        if !self.jobs.cancel_campaign(id).await? {
            return Ok(false);
        }
        sweep_campaign(&self.jobs, &self.objects, id, false).await?;
        Ok(true)
    }

    /// Removes a campaign's rows, every object under its prefix and the inputs no other campaign
    /// names. False if there is no such campaign.
    pub async fn delete(&self, id: Uuid) -> Result<bool, FrameworkError> {
        Ok(delete_campaign(&self.jobs, &self.objects, id).await?.is_some())
    }
}

/// Deletes objects under a campaign's prefix that no committed task recorded and no live attempt
/// may still be writing (outputs of attempts whose lease was lost), and everything of a cancelled
/// campaign. Returns how many. Work files of a finished campaign stay (see [`sweep_campaign`]).
pub async fn clean_orphans(jobs: &JobStore, objects: &Objects, id: Uuid) -> Result<usize, FrameworkError> {
    sweep_campaign(jobs, objects, id, true).await
}

/// Plans the upload of the files a local manifest names: the manifest with its URIs rewritten
/// to keys under `inputs/{upload id}/`, and the `(local file, key)` pairs to upload.
pub fn plan_local_upload(manifest_path: &Path) -> Result<(Manifest, Vec<(PathBuf, String)>), FrameworkError> {
    let mut manifest = precimap_formats::load_manifest(manifest_path)?;
    let dir = manifest_path.parent().unwrap_or(Path::new(".")).to_path_buf();
    let base = format!("inputs/{}", Uuid::new_v4().simple());
    let mut uris: Vec<&mut String> = Vec::new();
    for t in &mut manifest.trajectories {
        uris.push(&mut t.uri);
        uris.extend(t.accuracy_uri.as_mut());
    }
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
/// the in-process driver writes them. Errors name inputs as the manifest does, and a failed run
/// leaves no copies of them behind unless `keep_state`.
pub async fn run_embedded(
    manifest_path: &Path,
    options: &EmbeddedOptions,
    progress: impl FnMut(&RunStatus),
) -> Result<CampaignRecord, FrameworkError> {
    let state = options.out_dir.join(".precimap");
    if state.exists() {
        std::fs::remove_dir_all(&state).map_err(|e| FrameworkError::io(&state, e))?;
    }
    std::fs::create_dir_all(&state).map_err(|e| FrameworkError::io(&state, e))?;
    let result = run_embedded_in(&state, manifest_path, options, progress).await;
    if result.is_err() && !options.keep_state {
        // Best effort: the error being returned matters more than a leftover folder.
        let _ = std::fs::remove_dir_all(&state);
    }
    result
}

/// Store keys of uploaded inputs and the URIs the user's manifest gave them, longest key first
/// (so that no key is replaced inside a longer one).
fn manifest_names(original: &Manifest, uploaded: &Manifest) -> Vec<(String, String)> {
    let uris = |m: &Manifest| -> Vec<String> {
        m.trajectories
            .iter()
            .flat_map(|t| std::iter::once(t.uri.clone()).chain(t.accuracy_uri.clone()))
            .chain(m.strips.iter().map(|s| s.uri.clone()))
            .collect()
    };
    let mut names: Vec<(String, String)> = uris(uploaded).into_iter().zip(uris(original)).collect();
    names.sort_by_key(|(key, _)| std::cmp::Reverse(key.len()));
    names
}

fn with_manifest_names(message: &str, names: &[(String, String)]) -> String {
    names.iter().fold(message.to_string(), |m, (key, uri)| m.replace(key.as_str(), uri))
}

async fn run_embedded_in(
    state: &Path,
    manifest_path: &Path,
    options: &EmbeddedOptions,
    mut progress: impl FnMut(&RunStatus),
) -> Result<CampaignRecord, FrameworkError> {
    let state = state.canonicalize().map_err(|e| FrameworkError::io(state, e))?;
    let jobs = JobStore::connect(&format!("sqlite://{}", state.join("jobs.db").display())).await?;
    let objects = Objects::from_url(&format!("file://{}", state.join("store").display()))?;
    let framework = Framework { jobs: jobs.clone(), objects: objects.clone(), queue: default_queue() };
    let original = precimap_formats::load_manifest(manifest_path)?;
    let manifest = upload_local_inputs(&objects, manifest_path).await?;
    let names = manifest_names(&original, &manifest);
    let id = match framework.submit(&manifest).await {
        Ok(id) => id,
        Err(SubmitError::Framework(e)) => return Err(e),
        Err(e @ SubmitError::Invalid { .. }) => {
            return Err(FrameworkError::Invalid(with_manifest_names(&e.to_string(), &names)))
        }
    };
    let ctx = TaskContext::new(objects.clone(), state.join("scratch"));
    // `--keep-work` keeps the work files in the store beside the job database.
    let retention = if options.keep_state { Retention::keep_everything() } else { Retention::default() };
    let executor = Executor::new(jobs.clone(), ctx, ExecutorConfig { retention, ..ExecutorConfig::default() });
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
            error: with_manifest_names(campaign.error.as_deref().unwrap_or_default(), &names),
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
