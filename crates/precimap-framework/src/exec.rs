//! Runs one claimed task: reads its inputs from the object store, calls the same functions the
//! in-process driver calls, writes its outputs under keys that contain the attempt's lease token
//! (so a lost attempt can never overwrite a committed one), and returns what the job store
//! records. CPU work runs on the blocking pool; nothing here touches the database.

use crate::codec::{
    decode_blocks, decode_corrections, decode_field, decode_positions, encode_blocks, encode_corrections, encode_field,
    encode_positions,
};
use crate::error::{FrameworkError, TaskError};
use crate::objects::Objects;
use crate::plan::{
    CombineResult, CorrectionsRef, EstimateResult, ExportResult, FieldInput, FieldResult, MomentsResult, SegmentResult,
    SolveResult, StripInput, TaskInput, TrajectoryInput, BLOCKS_PREFIX, OUTPUT_ACCELERATED, OUTPUT_CORRECTIONS,
    OUTPUT_FIELD, OUTPUT_LATENT_STD, OUTPUT_POSITIONS, PREVIOUS_PREFIX, SEGMENTS_PREFIX, START_PREFIX,
};
use bytes::Bytes;
use precimap_core::corrections::{AnchorCovariance, TrajectoryCorrections};
use precimap_core::trajectory::Trajectory;
use precimap_core::Vec3;
use precimap_estimate::anderson::{self, TrajectoryHistory};
use precimap_estimate::{SegmentParams, TileChunk};
use precimap_jobs::{OutputKey, TaskOutcome};
use precimap_pipeline::campaign::{StripEntry, TrajectoryEntry};
use precimap_pipeline::tasks::{
    anchor_positions, corrections_for_export, corrections_outputs, export_strip_file, export_trajectory_file,
    prepare_strip_chunks,
};
use precimap_pipeline::PipelineError;
use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::{Instant, SystemTime};
use uuid::Uuid;

/// What one task invocation may use.
#[derive(Clone, Debug)]
pub struct TaskContext {
    pub objects: Objects,
    /// Scratch folder for downloads from a remote store.
    pub scratch: PathBuf,
    /// Trajectories parsed by earlier tasks of this process.
    pub trajectories: TrajectoryCache,
    /// Asked before every object write of the attempt (`None`: writes are never refused).
    gate: Option<Arc<dyn WriteGate>>,
}

impl TaskContext {
    pub fn new(objects: Objects, scratch: PathBuf) -> Self {
        Self { objects, scratch, trajectories: TrajectoryCache::default(), gate: None }
    }

    /// This context for one attempt whose every object write `gate` must allow first.
    pub fn with_gate(&self, gate: Arc<dyn WriteGate>) -> Self {
        Self { gate: Some(gate), ..self.clone() }
    }
}

/// Whether an attempt may still write objects. The executor asks the job store (the attempt
/// holds its lease and its campaign runs) before every write, so that a cancelled or deleted
/// campaign's running attempts stop writing at their next write instead of at their next
/// heartbeat, and the clean-up that follows the cancel or delete is not refilled behind it.
pub trait WriteGate: Send + Sync + std::fmt::Debug {
    /// `Ok(false)`: stop, write nothing more. `Err`: the answer is unknown (a database hiccup).
    fn may_write(&self) -> futures::future::BoxFuture<'_, Result<bool, String>>;
}

/// The message of an attempt its gate stopped.
pub const ATTEMPT_STOPPED: &str =
    "the attempt may no longer write (its campaign was cancelled, failed or deleted, or its lease was lost)";

/// Trajectory files parsed by the tasks of one executor process. A campaign's segment and export
/// tasks (two strips per trajectory each), its trajectory export and its first field task all
/// read the same trajectory CSVs: six parses of each where the in-process driver parses once
/// (callgrind, tiny seed 3: 0.66 G instructions, 2 % of the run). Keyed by the object key and
/// the file's length and modification time, so an input replaced under the same key is parsed
/// anew; a download from a remote store is a new file every time and never hits. Holds the
/// most recently parsed [`TrajectoryCache::CAPACITY`] (strips come in trajectory order, so a
/// campaign's tasks rarely come back to an evicted one).
#[derive(Clone, Debug, Default)]
pub struct TrajectoryCache(Arc<Mutex<VecDeque<CachedTrajectory>>>);

type CachedTrajectory = (TrajectoryFile, Arc<Trajectory>);

/// What identifies one version of a trajectory file.
#[derive(Clone, Debug, PartialEq, Eq)]
struct TrajectoryFile {
    key: String,
    len: u64,
    modified: Option<SystemTime>,
}

impl TrajectoryCache {
    /// Trajectories kept (~2 MB each for a 20-minute drive at 200 Hz).
    pub const CAPACITY: usize = 16;

    fn identify(key: &str, path: &Path) -> Option<TrajectoryFile> {
        let meta = std::fs::metadata(path).ok()?;
        Some(TrajectoryFile { key: key.to_string(), len: meta.len(), modified: meta.modified().ok() })
    }

    fn get(&self, file: &TrajectoryFile) -> Option<Arc<Trajectory>> {
        let held = self.0.lock().unwrap_or_else(|poisoned| poisoned.into_inner());
        held.iter().find(|(f, _)| f == file).map(|(_, t)| Arc::clone(t))
    }

    fn insert(&self, file: TrajectoryFile, trajectory: Arc<Trajectory>) {
        let mut held = self.0.lock().unwrap_or_else(|poisoned| poisoned.into_inner());
        held.retain(|(f, _)| f.key != file.key);
        if held.len() >= Self::CAPACITY {
            held.pop_front();
        }
        held.push_back((file, trajectory));
    }

    /// How many trajectories are held.
    #[cfg(test)]
    fn len(&self) -> usize {
        self.0.lock().unwrap_or_else(|poisoned| poisoned.into_inner()).len()
    }
}

/// A local copy of an object: the object itself in a `file://` store, otherwise a temporary
/// download removed on drop.
struct LocalObject {
    path: PathBuf,
    _temp: Option<tempfile::TempDir>,
}

impl TaskContext {
    async fn local(&self, key: &str) -> Result<LocalObject, TaskError> {
        if let Some(path) = self.objects.local_path(key) {
            if !path.is_file() {
                return Err(TaskError::permanent(format!("object {key} does not exist in the store")));
            }
            return Ok(LocalObject { path, _temp: None });
        }
        std::fs::create_dir_all(&self.scratch)
            .map_err(|e| TaskError::transient(FrameworkError::io(&self.scratch, e)))?;
        let dir = tempfile::tempdir_in(&self.scratch)
            .map_err(|e| TaskError::transient(FrameworkError::io(&self.scratch, e)))?;
        let name = key.rsplit('/').next().unwrap_or("object");
        let path = dir.path().join(name);
        self.objects.get_to_file(key, &path).await.map_err(TaskError::from_store)?;
        Ok(LocalObject { path, _temp: Some(dir) })
    }

    async fn get(&self, key: &str) -> Result<Bytes, TaskError> {
        self.objects.get(key).await.map_err(TaskError::from_store)
    }

    async fn get_many(&self, keys: &[String]) -> Result<Vec<Bytes>, TaskError> {
        self.objects.get_many(keys).await.map_err(TaskError::from_store)
    }

    /// Refuses with a permanent error once the attempt's gate says it may no longer write.
    async fn check_gate(&self) -> Result<(), TaskError> {
        match &self.gate {
            None => Ok(()),
            Some(gate) => match gate.may_write().await {
                Ok(true) => Ok(()),
                Ok(false) => Err(TaskError::permanent(ATTEMPT_STOPPED)),
                Err(e) => Err(TaskError::transient(format!("cannot tell whether the attempt may write: {e}"))),
            },
        }
    }

    /// Writes `objects` and returns their output records (`name`, key) in the same order.
    async fn put_many(&self, objects: Vec<(String, String, Vec<u8>)>) -> Result<Vec<OutputKey>, TaskError> {
        self.check_gate().await?;
        let mut outputs = Vec::with_capacity(objects.len());
        let mut payloads = Vec::with_capacity(objects.len());
        for (name, key, bytes) in objects {
            outputs.push(OutputKey { name, object_key: key.clone() });
            payloads.push((key, Bytes::from(bytes)));
        }
        self.objects.put_many(payloads).await.map_err(TaskError::from_store)?;
        Ok(outputs)
    }

    async fn put(&self, key: &str, bytes: Vec<u8>) -> Result<(), TaskError> {
        self.check_gate().await?;
        self.objects.put(key, Bytes::from(bytes)).await.map_err(TaskError::from_store)
    }

    /// Writes a file-producing output: in place for a `file://` store (through a temporary name),
    /// else to scratch and uploaded.
    async fn put_produced<F>(&self, key: &str, produce: F) -> Result<(), TaskError>
    where
        F: FnOnce(&Path) -> Result<(), PipelineError> + Send + 'static,
    {
        self.check_gate().await?;
        if let Some(dst) = self.objects.local_path(key) {
            let dir = dst.parent().map(Path::to_path_buf).unwrap_or_default();
            std::fs::create_dir_all(&dir).map_err(|e| TaskError::transient(FrameworkError::io(&dir, e)))?;
            let ext = dst.extension().and_then(|e| e.to_str()).unwrap_or("bin").to_string();
            // Keep the extension: the LAS writer picks LAZ compression from it.
            let tmp = dst.with_extension(format!("partial.{ext}"));
            let tmp2 = tmp.clone();
            // An attempt abandoned while the file is produced (its lease lost) leaves no
            // temporary file in the store: whoever finishes last removes it.
            let abandoned = Abandoned::default();
            let flag = abandoned.0.clone();
            let produced = blocking(move || {
                let produced = produce(&tmp2);
                if flag.load(std::sync::atomic::Ordering::SeqCst) {
                    let _ = std::fs::remove_file(&tmp2);
                }
                produced
            })
            .await;
            let allowed = match produced {
                Ok(Ok(())) => self.check_gate().await,
                Ok(Err(e)) => Err(TaskError::from_pipeline(e)),
                Err(e) => Err(e),
            };
            drop(abandoned);
            if let Err(e) = allowed {
                let _ = std::fs::remove_file(&tmp);
                return Err(e);
            }
            std::fs::rename(&tmp, &dst).map_err(|e| TaskError::transient(FrameworkError::io(&dst, e)))?;
            return Ok(());
        }
        std::fs::create_dir_all(&self.scratch)
            .map_err(|e| TaskError::transient(FrameworkError::io(&self.scratch, e)))?;
        let dir = tempfile::tempdir_in(&self.scratch)
            .map_err(|e| TaskError::transient(FrameworkError::io(&self.scratch, e)))?;
        let path = dir.path().join(key.rsplit('/').next().unwrap_or("object"));
        let p2 = path.clone();
        blocking(move || produce(&p2)).await?.map_err(TaskError::from_pipeline)?;
        self.check_gate().await?;
        self.objects.put_file(key, &path).await.map_err(TaskError::from_store)?;
        Ok(())
    }
}

/// Set when the future that owns it is dropped (or done): work still running on the compute
/// pool for it then cleans up after itself.
#[derive(Default)]
struct Abandoned(Arc<std::sync::atomic::AtomicBool>);

impl Drop for Abandoned {
    fn drop(&mut self) {
        self.0.store(true, std::sync::atomic::Ordering::SeqCst);
    }
}

async fn blocking<T: Send + 'static>(f: impl FnOnce() -> T + Send + 'static) -> Result<T, TaskError> {
    crate::cpu::run(f)
        .await
        .map_err(|e| TaskError::transient(FrameworkError::Internal(format!("task thread stopped: {e}"))))
}

/// Short, unique per attempt: the first 12 hex digits of the lease token.
fn attempt_tag(token: Uuid) -> String {
    token.simple().to_string()[..12].to_string()
}

async fn read_trajectory(ctx: &TaskContext, t: &TrajectoryInput) -> Result<TrajectoryEntry, TaskError> {
    let local = ctx.local(&t.uri).await?;
    let file = TrajectoryCache::identify(&t.uri, &local.path);
    let cached = file.as_ref().and_then(|f| ctx.trajectories.get(f));
    let data = match cached {
        Some(data) => data,
        None => {
            let path = local.path.clone();
            let field = t.field.clone();
            let data = blocking(move || read_trajectory_file(&path, field.as_ref()))
                .await?
                .map_err(|e| TaskError::permanent(format!("trajectory {}: {e}", t.id)).naming(&t.uri, &local.path))?;
            let data = Arc::new(data);
            if let Some(file) = file {
                ctx.trajectories.insert(file, Arc::clone(&data));
            }
            data
        }
    };
    let clock = t.field.as_ref().map_or_else(Default::default, |f| {
        precimap_formats::trajectory::trajectory_clock(&f.trajectory, f.gps_week, data.times()[0])
    });
    Ok(TrajectoryEntry {
        id: t.id.clone(),
        path: PathBuf::from(&t.uri),
        data,
        mean_lever_arm: Vec3::from(t.mean_lever_arm),
        clock,
        georef: georeference(t.field.as_ref())?,
    })
}

/// A trajectory file in its manifest format, in the processing frame of a field campaign. The
/// accuracy file (reported only) is not read by tasks.
fn read_trajectory_file(path: &Path, field: Option<&FieldInput>) -> Result<Trajectory, PipelineError> {
    let Some(f) = field else { return Ok(precimap_formats::read_trajectory_csv(path)?) };
    let frame =
        f.crs.frame().map_err(|e| PipelineError::Input { what: "manifest $.crs".into(), message: e.to_string() })?;
    let loaded = precimap_formats::trajectory::load_trajectory(path, &f.trajectory, None, Some(&frame), f.gps_week)?;
    Ok(loaded.trajectory)
}

fn georeference(field: Option<&FieldInput>) -> Result<Option<Arc<precimap_formats::crs::Georeference>>, TaskError> {
    field
        .map(|f| f.crs.georeference().map(Arc::new).map_err(|e| TaskError::permanent(format!("manifest $.crs: {e}"))))
        .transpose()
}

/// The pipeline's view of a strip whose file is at `path`.
fn strip_entry(s: &StripInput, path: &Path) -> Result<StripEntry, TaskError> {
    Ok(StripEntry {
        id: s.id.clone(),
        path: path.to_path_buf(),
        trajectory: s.trajectory,
        lever_arm: Vec3::from(s.lever_arm),
        georef: georeference(s.field.as_ref())?,
    })
}

fn strip_trajectory(s: &StripInput) -> TrajectoryInput {
    TrajectoryInput {
        index: s.trajectory,
        id: s.trajectory_id.clone(),
        uri: s.trajectory_uri.clone(),
        mean_lever_arm: [0.0; 3],
        field: s.field.clone(),
    }
}

/// One trajectory's corrections, with the covariances its solve stored (the last iteration's).
async fn read_corrections(
    ctx: &TaskContext,
    c: &CorrectionsRef,
) -> Result<(TrajectoryCorrections, Option<Vec<AnchorCovariance>>), TaskError> {
    let mut read = read_stored_corrections(ctx, std::slice::from_ref(c)).await?;
    Ok(read.pop().expect("one corrections per reference"))
}

/// Several trajectories' corrections, read together (see [`Objects::get_many`]).
async fn read_corrections_many(
    ctx: &TaskContext,
    refs: &[CorrectionsRef],
) -> Result<Vec<TrajectoryCorrections>, TaskError> {
    Ok(read_stored_corrections(ctx, refs).await?.into_iter().map(|(c, _)| c).collect())
}

/// Corrections and their covariances where stored, read together; a reference without an object
/// is zero corrections over its anchors.
async fn read_stored_corrections(
    ctx: &TaskContext,
    refs: &[CorrectionsRef],
) -> Result<Vec<(TrajectoryCorrections, Option<Vec<AnchorCovariance>>)>, TaskError> {
    let keys: Vec<String> = refs.iter().filter_map(|c| c.key.clone()).collect();
    let mut stored = ctx.get_many(&keys).await?.into_iter().zip(keys);
    let mut out = Vec::with_capacity(refs.len());
    for c in refs {
        out.push(match &c.key {
            None => (TrajectoryCorrections::zeros(c.anchors.0, c.anchors.1), None),
            Some(_) => {
                let (bytes, key) = stored.next().expect("one object per key");
                decode_corrections(&bytes)
                    .map_err(|e| TaskError::permanent(format!("corrections object {key}: {e}")))?
            }
        });
    }
    Ok(out)
}

/// The anchor positions object does not fit the campaign's trajectories (`detail` says how).
fn corrupt_positions(detail: String) -> TaskError {
    TaskError::permanent(format!(
        "anchor positions ({detail}) do not match the trajectories' anchor ranges; the campaign state is corrupt: \
         submit the campaign again"
    ))
}

/// Runs a task; `token` is its lease token (part of every output key).
pub async fn execute(ctx: &TaskContext, input: TaskInput, token: Uuid) -> Result<TaskOutcome, TaskError> {
    let started = Instant::now();
    let tag = attempt_tag(token);
    match input {
        TaskInput::SegmentStrip { prefix, strip, params } => {
            let params = required(params)?;
            let traj = read_trajectory(ctx, &strip_trajectory(&strip)).await?;
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
        TaskInput::EstimateTile {
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
        } => {
            let params = required(params)?;
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
                let mut estimate =
                    precimap_estimate::estimate_tile_recording(tile, &chunks, &all, &params, &step, None, gather)
                        .map_err(|e| TaskError::permanent(format!("tile {tile}: {e}")))?;
                let map =
                    match estimate.latent_map.take() {
                        Some(points) => Some(precimap_formats::encode_latent_map(&points).map_err(|e| {
                            TaskError::permanent(format!("tile {tile}: latent map does not encode: {e}"))
                        })?),
                        None => None,
                    };
                Ok::<_, TaskError>((estimate, map))
            })
            .await??;
            let mut objects = Vec::with_capacity(estimate.blocks.len() + 1);
            for tb in &estimate.blocks {
                let key = format!("{prefix}/it/{iteration}/blocks/{}/{tile}.{tag}.blk", tb.trajectory);
                objects.push((format!("{BLOCKS_PREFIX}{}", tb.trajectory), key, encode_blocks(&tb.blocks)));
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
        TaskInput::SolveField { prefix, iteration, params, trajectories, positions, current, previous, equations } => {
            let params = required(params)?;
            let mut outputs = Vec::with_capacity(2 * current.len() + 1);
            // The anchors' positions: read once from the trajectory files by the first field task
            // of the campaign, then from the object it wrote.
            let positions = match &positions {
                Some(key) => {
                    let bytes = ctx.get(key).await?;
                    decode_positions(&bytes)
                        .map_err(|e| TaskError::permanent(format!("anchor positions object {key}: {e}")))?
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
            let corrections = read_corrections_many(ctx, &current).await?;
            let before = read_corrections_many(ctx, previous.as_deref().unwrap_or_default()).await?;
            let mut decoded = Vec::with_capacity(equations.len());
            for (key, bytes) in equations.iter().zip(ctx.get_many(&equations).await?) {
                decoded
                    .push(decode_field(&bytes).map_err(|e| TaskError::permanent(format!("field object {key}: {e}")))?);
            }
            let solved = blocking(move || {
                let field_trajectories: Vec<_> = corrections
                    .iter()
                    .zip(&positions)
                    .map(|(c, p)| precimap_estimate::FieldTrajectory { positions: p, corrections: c })
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
        TaskInput::SolveTrajectory {
            prefix,
            iteration,
            trajectory,
            step,
            params,
            with_sigma,
            current,
            previous,
            iteration_start,
            blocks,
        } => {
            let params = required(params)?;
            let has_previous = previous.is_some();
            let mut refs = vec![current];
            refs.extend(previous);
            refs.extend(iteration_start);
            let mut read = read_corrections_many(ctx, &refs).await?.into_iter();
            let current = read.next().expect("the current corrections");
            let previous = if has_previous { read.next() } else { None };
            let iteration_start = read.next();
            let mut all = Vec::new();
            for (key, bytes) in blocks.iter().zip(ctx.get_many(&blocks).await?) {
                all.extend(
                    decode_blocks(&bytes).map_err(|e| TaskError::permanent(format!("blocks object {key}: {e}")))?,
                );
            }
            let id = trajectory.id.clone();
            let solution = blocking(move || {
                // The change between iterations, the field's share included.
                precimap_estimate::solve_trajectory(
                    all.iter(),
                    &current,
                    previous.as_ref(),
                    iteration_start.as_ref(),
                    &params,
                    step.rotation,
                    with_sigma,
                )
            })
            .await?
            .map_err(|e| {
                TaskError::permanent(format!(
                    "trajectory {id}: the normal equations could not be solved ({e}); the campaign parameters (sigma values) are probably inconsistent"
                ))
            })?;
            let key = format!("{prefix}/it/{iteration}/corr/{}.{tag}.bin", trajectory.index);
            ctx.put(&key, encode_corrections(&solution.corrections, solution.covariance.as_deref())).await?;
            let result = SolveResult {
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
        TaskInput::AndersonMoments { trajectory, starts, results } => {
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
        TaskInput::AndersonCombine { prefix, iteration, trajectory, results, coefficients } => {
            let read = read_corrections_many(ctx, &results).await?;
            let combined = blocking(move || {
                anderson::combine(trajectory as usize, &read.iter().collect::<Vec<_>>(), &coefficients)
            })
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
        TaskInput::ExportStrip { prefix, strip, anchor_spacing_m, corrections } => {
            let (corrections, _) = read_corrections(ctx, &corrections).await?;
            let traj = read_trajectory(ctx, &strip_trajectory(&strip)).await?;
            let local = ctx.local(&strip.uri).await?;
            let entry = strip_entry(&strip, &local.path)?;
            let name = format!("strips/{}", precimap_pipeline::tasks::export_strip_name(&entry));
            let key = format!("{prefix}/out/{tag}/{name}");
            let points = std::sync::Arc::new(std::sync::atomic::AtomicU64::new(0));
            let counter = points.clone();
            ctx.put_produced(&key, move |dst| {
                let n = export_strip_file(&entry, &traj, anchor_spacing_m, &corrections, dst)?;
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
        TaskInput::ExportTrajectory { prefix, trajectory, anchor_spacing_m, corrections, params } => {
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
            ctx.put_produced(&key, move |dst| export_trajectory_file(&entry, anchor_spacing_m, &corrections, dst))
                .await?;
            let mut outputs = vec![OutputKey { name, object_key: key }];
            outputs.extend(ctx.put_many(beside).await?);
            let result = ExportResult { points: 0, seconds: started.elapsed().as_secs_f64() };
            Ok(TaskOutcome { result: to_json(&result)?, outputs })
        }
        TaskInput::WriteReport { prefix, report, latent_std, tile_size_m, latent_map } => {
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
            let plots = precimap_pipeline::qc::report_plots(&report)
                .into_iter()
                .chain(precimap_pipeline::qc::latent_std_plots(tile_size_m, first, last));
            for (name, svg) in plots {
                let key = format!("{prefix}/out/{tag}/{name}");
                objects.push((name, key, svg.into_bytes()));
            }
            let mut outputs = ctx.put_many(objects).await?;
            // The latent map's tiles stay where their estimate tasks recorded them.
            outputs.extend(latent_map.into_iter().map(|(name, object_key)| OutputKey { name, object_key }));
            Ok(TaskOutcome { result: serde_json::json!({ "seconds": started.elapsed().as_secs_f64() }), outputs })
        }
    }
}

/// The parameters a task needs: its own, or the campaign's that the executor filled in
/// ([`TaskInput::with_campaign_params`]).
fn required(params: Option<Box<precimap_core::Parameters>>) -> Result<Box<precimap_core::Parameters>, TaskError> {
    params.ok_or_else(|| {
        TaskError::permanent("the task carries no parameters and its campaign stores none; submit the campaign again")
    })
}

fn to_bytes<T: serde::Serialize>(value: &T) -> Result<Vec<u8>, TaskError> {
    serde_json::to_vec(value).map_err(|e| TaskError::permanent(format!("object does not serialise: {e}")))
}

fn to_json<T: serde::Serialize>(value: &T) -> Result<serde_json::Value, TaskError> {
    serde_json::to_value(value).map_err(|e| TaskError::permanent(format!("result does not serialise: {e}")))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn csv(samples: usize, x0: f64) -> String {
        let mut s = String::from("time,x,y,z,roll,pitch,yaw\n");
        for i in 0..samples {
            s.push_str(&format!("{},{},0,0,0,0,90\n", i as f64 * 0.005, x0 + i as f64 * 0.05));
        }
        s
    }

    #[tokio::test]
    async fn trajectories_are_parsed_once_per_version_of_their_file() {
        let dir = tempfile::tempdir().unwrap();
        let objects = Objects::from_url(&format!("file://{}", dir.path().display())).unwrap();
        let ctx = TaskContext::new(objects.clone(), dir.path().join("scratch"));
        let key = "inputs/u/trajectories/v01.csv";
        objects.put(key, Bytes::from(csv(400, 0.0))).await.unwrap();
        let input =
            TrajectoryInput { index: 0, id: "v01".into(), uri: key.into(), mean_lever_arm: [0.0; 3], field: None };

        let first = read_trajectory(&ctx, &input).await.unwrap();
        assert_eq!(ctx.trajectories.len(), 1);
        let again = read_trajectory(&ctx, &input).await.unwrap();
        assert_eq!(ctx.trajectories.len(), 1, "the second read is served from the cache");
        assert_eq!(format!("{:?}", first.data), format!("{:?}", again.data));

        // The same key replaced by another file (another length): parsed anew, the old one dropped.
        objects.put(key, Bytes::from(csv(500, 10.0))).await.unwrap();
        let replaced = read_trajectory(&ctx, &input).await.unwrap();
        assert_eq!(ctx.trajectories.len(), 1);
        assert_ne!(format!("{:?}", first.data), format!("{:?}", replaced.data));

        // Bounded: the oldest trajectory goes first.
        for i in 0..TrajectoryCache::CAPACITY + 2 {
            let key = format!("inputs/u/trajectories/t{i}.csv");
            objects.put(&key, Bytes::from(csv(50, i as f64))).await.unwrap();
            read_trajectory(&ctx, &TrajectoryInput { uri: key, ..input.clone() }).await.unwrap();
        }
        assert_eq!(ctx.trajectories.len(), TrajectoryCache::CAPACITY);
        let oldest = TrajectoryCache::identify(key, &dir.path().join(key)).unwrap();
        assert!(ctx.trajectories.get(&oldest).is_none());

        // A malformed file is an error naming it, and nothing is cached for it.
        objects.put(key, Bytes::from_static(b"time,x\n1,2\n")).await.unwrap();
        let e = read_trajectory(&ctx, &input).await.unwrap_err();
        assert!(e.message.contains(key), "{}", e.message);
        let malformed = TrajectoryCache::identify(key, &dir.path().join(key)).unwrap();
        assert!(ctx.trajectories.get(&malformed).is_none());
    }
}
