//! Runs one claimed task: reads its inputs from the object store, calls the same functions the
//! in-process driver calls, writes its outputs under keys that contain the attempt's lease token
//! (so a lost attempt can never overwrite a committed one), and returns what the job store
//! records. CPU work runs on the blocking pool; nothing here touches the database.

use crate::codec::{
    decode_corrections, decode_field, decode_positions, decode_share, decode_trajectory_blocks, encode_corrections,
    encode_field, encode_positions, encode_share, encode_trajectory_blocks,
};
use crate::error::{FrameworkError, TaskError};
use crate::objects::Objects;
use crate::plan::{
    ApplyResult, CalibrationInput, CombineResult, CorrectionsRef, EstimateResult, ExportResult, FieldInput,
    FieldResult, MomentsResult, SegmentResult, SolveResult, StripInput, TaskInput, TrajectoryInput, BLOCKS_PREFIX,
    OUTPUT_ACCELERATED, OUTPUT_CORRECTIONS, OUTPUT_FIELD, OUTPUT_LATENT_STD, OUTPUT_POSITIONS, OUTPUT_SHARE,
    PREVIOUS_PREFIX, SEGMENTS_PREFIX, START_PREFIX,
};
use bytes::Bytes;
use precimap_core::corrections::{AnchorCovariance, TrajectoryCorrections};
use precimap_core::trajectory::Trajectory;
use precimap_core::{Parameters, Vec3};
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

mod accelerate;
mod calibrate;
mod estimate;
mod export;
mod field;
mod report;
mod segment;
mod solve;

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
        accuracy: None,
        accuracy_uri: String::new(),
    })
}

/// A trajectory's anchor prior over `anchors` from its accuracy file (`None` without one, as
/// `precimap_pipeline::prior`): the solve and field tasks compute it from their inputs alike.
async fn read_anchor_prior(
    ctx: &TaskContext,
    t: &TrajectoryInput,
    params: &Parameters,
    anchors: (u32, u32),
) -> Result<Option<Vec<[f64; 6]>>, TaskError> {
    let Some((accuracy, uri, local)) = read_accuracy(ctx, t).await? else { return Ok(None) };
    let mut entry = read_trajectory(ctx, t).await?;
    entry.accuracy = Some(Arc::new(accuracy));
    entry.accuracy_uri = uri.clone();
    let params = params.clone();
    blocking(move || precimap_pipeline::prior::anchor_prior(&entry, &params, anchors))
        .await?
        .map_err(|e| TaskError::permanent(e.to_string()).naming(&uri, &local.path))
}

/// A trajectory's accuracy file, read and checked, with its URI and local copy; `None` without
/// one.
async fn read_accuracy(
    ctx: &TaskContext,
    t: &TrajectoryInput,
) -> Result<Option<(precimap_formats::sbet::NavAccuracy, String, LocalObject)>, TaskError> {
    let Some((f, uri)) = t.field.as_ref().and_then(|f| Some((f, f.trajectory.accuracy_uri.clone()?))) else {
        return Ok(None);
    };
    let local = ctx.local(&uri).await?;
    let (path, spec, week) = (local.path.clone(), f.trajectory.clone(), f.gps_week);
    let accuracy = blocking(move || precimap_formats::trajectory::load_accuracy(&path, &spec, week))
        .await?
        .map_err(|e| TaskError::permanent(format!("trajectory {}: {e}", t.id)).naming(&uri, &local.path))?;
    Ok(Some((accuracy, uri, local)))
}

/// A trajectory file in its manifest format, in the processing frame of a field campaign (its
/// accuracy file is read where the prior is needed, [`read_anchor_prior`]).
fn read_trajectory_file(path: &Path, field: Option<&FieldInput>) -> Result<Trajectory, PipelineError> {
    let Some(f) = field else { return Ok(precimap_formats::read_trajectory_csv(path)?) };
    let frame =
        f.crs.frame().map_err(|e| PipelineError::Input { what: "manifest $.crs".into(), message: e.to_string() })?;
    let loaded = precimap_formats::trajectory::load_trajectory(path, &f.trajectory, None, Some(&frame), f.gps_week)?;
    Ok(loaded.trajectory)
}

fn georeference_of(
    crs: Option<&precimap_formats::CrsSpec>,
) -> Result<Option<precimap_formats::crs::Georeference>, TaskError> {
    crs.map(|c| c.georeference().map_err(|e| TaskError::permanent(format!("manifest $.crs: {e}")))).transpose()
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
        scanner: s.scanner,
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
    let at = Attempt { ctx, tag: attempt_tag(token), started: Instant::now() };
    match input {
        TaskInput::SegmentStrip { prefix, strip, params } => segment::segment_strip(&at, prefix, strip, params).await,
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
            crs,
            control,
            calibration,
        } => {
            let task = estimate::TileTask {
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
            };
            estimate::estimate_tile(&at, task).await
        }
        TaskInput::SolveField { prefix, iteration, params, trajectories, positions, current, previous, equations } => {
            let task =
                field::FieldTask { prefix, iteration, params, trajectories, positions, current, previous, equations };
            field::solve_field(&at, task).await
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
            calibration,
        } => {
            let task = solve::TrajectoryTask {
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
                calibration,
            };
            solve::solve_trajectory(&at, task).await
        }
        TaskInput::AndersonMoments { trajectory, starts, results } => {
            accelerate::anderson_moments(&at, trajectory, starts, results).await
        }
        TaskInput::AndersonCombine { prefix, iteration, trajectory, results, coefficients } => {
            accelerate::anderson_combine(&at, prefix, iteration, trajectory, results, coefficients).await
        }
        TaskInput::ApplyCalibration(task) => calibrate::apply_calibration(&at, *task).await,
        TaskInput::ExportStrip { prefix, strip, anchor_spacing_m, corrections, mounting } => {
            export::export_strip(&at, prefix, strip, anchor_spacing_m, corrections, mounting).await
        }
        TaskInput::ExportTrajectory { prefix, trajectory, anchor_spacing_m, corrections, params } => {
            export::export_trajectory(&at, prefix, trajectory, anchor_spacing_m, corrections, params).await
        }
        TaskInput::WriteReport { prefix, report, latent_std, tile_size_m, latent_map, crs } => {
            let georef = georeference_of(crs.as_ref())?;
            report::write_report(&at, prefix, report, latent_std, tile_size_m, latent_map, georef.as_ref()).await
        }
    }
}

/// One attempt at a task: where it reads and writes, the tag in its output keys, and when it
/// started.
#[derive(Debug)]
struct Attempt<'a> {
    ctx: &'a TaskContext,
    tag: String,
    started: Instant,
}
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
