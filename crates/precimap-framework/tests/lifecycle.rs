//! The storage life cycle against a real job store (SQLite; PostgreSQL at
//! `PRECIMAP_TEST_POSTGRES`, default `postgres://postgres@127.0.0.1:5432/postgres`) and a file
//! store: cancel or delete at every stage stops the running attempt from writing and leaves no
//! object under the campaign's prefix within one sweep; deletion removes the inputs the campaign
//! alone named; manifests may name only complete uploads; inputs are written once; a campaign's
//! parameters are stored once, not in its tasks.

use precimap_framework::lifecycle::{sweep_store, Retention};
use precimap_framework::{
    default_queue, upload_local_inputs, CampaignLimits, Executor, ExecutorConfig, Framework, FrameworkError, Objects,
    SubmitError, TaskContext, WorkOutcome,
};
use precimap_jobs::{CampaignState, JobStore};
use std::path::Path;
use std::time::Duration;
use uuid::Uuid;

/// The executors' lease in these tests: short, so that a finished campaign's sweep is due at once.
const LEASE: Duration = Duration::from_millis(50);

/// A tiny simulated campaign with a two-step schedule (so that export comes soon); returns its
/// manifest's path.
fn tiny_campaign(dir: &Path) -> std::path::PathBuf {
    let campaign = dir.join("campaign");
    let config = precimap_sim::SimConfig::for_scale(precimap_sim::Scale::Tiny, 3);
    precimap_sim::simulate(&config, &campaign, false).expect("simulate tiny");
    let path = campaign.join("manifest.json");
    let mut manifest: serde_json::Value = serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap();
    manifest["parameters"] = serde_json::json!({ "schedule": [
        { "grid_m": 0.25, "threshold_m": 1.0, "cell_m": 3.0, "column_cells": true, "rotation": false },
        { "grid_m": 0.10, "threshold_m": 0.30 },
    ]});
    let short = campaign.join("manifest-short.json");
    std::fs::write(&short, serde_json::to_vec_pretty(&manifest).unwrap()).unwrap();
    short
}

/// A fresh database: SQLite in `dir`, or a new PostgreSQL database.
fn database(dir: &Path, postgres: bool) -> String {
    if !postgres {
        return format!("sqlite://{}", dir.join("jobs.db").display());
    }
    let admin = std::env::var("PRECIMAP_TEST_POSTGRES")
        .unwrap_or_else(|_| "postgres://postgres@127.0.0.1:5432/postgres".into());
    let name = format!("precimap_life_{}", Uuid::new_v4().simple());
    let out = std::process::Command::new("psql")
        .args([admin.as_str(), "-tA", "-c", &format!("CREATE DATABASE {name}")])
        .output()
        .expect("psql");
    assert!(out.status.success(), "CREATE DATABASE: {}", String::from_utf8_lossy(&out.stderr));
    format!("{}/{name}", admin.rsplit_once('/').unwrap().0)
}

struct Setup {
    jobs: JobStore,
    objects: Objects,
    framework: Framework,
    executor: Executor,
}

async fn setup(dir: &Path, postgres: bool) -> Setup {
    let jobs = JobStore::connect(&database(dir, postgres)).await.unwrap();
    let objects = Objects::from_url(&format!("file://{}", dir.join("store").display())).unwrap();
    let framework = Framework { jobs: jobs.clone(), objects: objects.clone(), queue: default_queue() };
    let retention = Retention { store_sweep_interval: Duration::ZERO, ..Retention::default() };
    let config = ExecutorConfig { lease: LEASE, retention, ..ExecutorConfig::default() };
    let executor = Executor::new(jobs.clone(), TaskContext::new(objects.clone(), dir.join("scratch")), config);
    Setup { jobs, objects, framework, executor }
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Stop {
    Cancel,
    Delete,
}

/// Runs a campaign up to `stage` (one of its tasks done), claims the next task, stops the
/// campaign with `stop`, then runs the claimed task: it must write nothing, and one sweep must
/// leave nothing under the campaign's prefix. A second campaign names some of the same inputs:
/// deleting the first removes exactly the inputs it alone named.
async fn stop_during(stage: &str, stop: Stop, postgres: bool) {
    let dir = tempfile::tempdir().unwrap();
    let manifest_path = tiny_campaign(dir.path());
    let s = setup(dir.path(), postgres).await;
    let manifest = upload_local_inputs(&s.objects, &manifest_path).await.unwrap();
    let id = s.framework.submit(&manifest).await.unwrap();
    // A campaign that shares the first strip and its trajectory (cancelled at once, so the
    // executor never runs it; it still names its inputs).
    let mut sharing = manifest.clone();
    sharing.strips.truncate(1);
    let trajectory = sharing.strips[0].trajectory.clone();
    sharing.trajectories.retain(|t| t.id == trajectory);
    let other = s.framework.submit(&sharing).await.unwrap();
    assert!(s.framework.cancel(other).await.unwrap());
    let prefix = s.jobs.object_prefix(id).await.unwrap().unwrap();

    // Up to `stage`, with one of its tasks done (so the stage has written objects).
    let mut steps = 0;
    while s.jobs.campaign_progress(id).await.unwrap().unwrap().stage != stage {
        let outcome = s.executor.work_once().await.unwrap();
        assert!(matches!(outcome, WorkOutcome::Done { .. }), "{outcome:?}");
        steps += 1;
        assert!(steps < 500, "{stage} never reached");
    }
    assert!(matches!(s.executor.work_once().await.unwrap(), WorkOutcome::Done { .. }));
    assert!(!s.objects.list(&prefix).await.unwrap().is_empty(), "{stage} wrote objects");
    let task = s.jobs.claim("in-flight", Duration::from_secs(60)).await.unwrap().expect("a task to run");
    assert_eq!(task.stage, stage);

    assert!(s.framework.cancel(id).await.unwrap());
    assert!(s.objects.list(&prefix).await.unwrap().is_empty(), "cancel removes everything under the prefix");
    if stop == Stop::Delete {
        assert!(s.framework.delete(id).await.unwrap());
        assert!(s.jobs.campaign_progress(id).await.unwrap().is_none());
    }
    // The attempt that was running finds it may not write: nothing of it lands in the store.
    let outcome = s.executor.run_task(task).await.unwrap();
    assert!(matches!(outcome, WorkOutcome::LeaseLost { .. }), "{outcome:?}");
    assert!(s.objects.list(&prefix).await.unwrap().is_empty(), "the stopped attempt wrote {prefix}");

    // A write that passed its check just before the stop lands afterwards: one sweep removes it.
    let straggler = format!("{prefix}/it/1/blocks/0/late.0123456789ab.blk");
    s.objects.put(&straggler, b"late".to_vec().into()).await.unwrap();
    tokio::time::sleep(LEASE * 2).await;
    s.executor.reconcile().await.unwrap();
    assert!(s.objects.list(&prefix).await.unwrap().is_empty(), "one sweep leaves nothing under {prefix}");

    let shared: Vec<&String> =
        sharing.trajectories.iter().map(|t| &t.uri).chain(sharing.strips.iter().map(|s| &s.uri)).collect();
    let alone: Vec<&String> = manifest
        .trajectories
        .iter()
        .map(|t| &t.uri)
        .chain(manifest.strips.iter().map(|s| &s.uri))
        .filter(|k| !shared.contains(k))
        .collect();
    assert!(!alone.is_empty());
    for key in &shared {
        assert!(s.objects.exists(key).await.unwrap(), "{key}: named by another campaign, kept");
    }
    for key in &alone {
        assert_eq!(s.objects.exists(key).await.unwrap(), stop == Stop::Cancel, "{key} after {stop:?}");
    }
    if stop == Stop::Delete {
        // Once the other campaign goes too, so do the inputs they shared.
        assert!(s.framework.delete(other).await.unwrap());
        for key in &shared {
            assert!(!s.objects.exists(key).await.unwrap(), "{key}: named by no campaign now");
        }
        assert!(s.objects.list("inputs").await.unwrap().is_empty());
    }
    s.jobs.close().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cancel_during_prepare_leaves_nothing() {
    stop_during("prepare", Stop::Cancel, false).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn delete_during_prepare_leaves_nothing_and_removes_its_own_inputs() {
    stop_during("prepare", Stop::Delete, false).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cancel_during_an_iteration_leaves_nothing() {
    stop_during("estimate", Stop::Cancel, false).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn delete_during_an_iteration_leaves_nothing_and_removes_its_own_inputs() {
    stop_during("solve", Stop::Delete, false).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cancel_during_export_leaves_nothing() {
    stop_during("export", Stop::Cancel, false).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn delete_during_export_leaves_nothing_and_removes_its_own_inputs() {
    stop_during("export", Stop::Delete, false).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn postgres_cancel_during_an_iteration_leaves_nothing() {
    stop_during("estimate", Stop::Cancel, true).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn postgres_delete_during_export_leaves_nothing_and_removes_its_own_inputs() {
    stop_during("export", Stop::Delete, true).await;
}

/// The problems of a refused submission, as `(JSON path, message)`.
fn problems(e: SubmitError) -> Vec<(String, String)> {
    match e {
        SubmitError::Invalid { problems } => problems.into_iter().map(|p| (p.path, p.message)).collect(),
        SubmitError::Framework(e) => panic!("not a manifest problem: {e}"),
    }
}

/// A manifest may name only complete uploads under `inputs/`: not another campaign's work
/// objects, not a temporary upload file; inputs are written once; and the bounds.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn manifests_name_only_complete_inputs_within_the_bounds() {
    let dir = tempfile::tempdir().unwrap();
    let manifest_path = tiny_campaign(dir.path());
    let s = setup(dir.path(), false).await;
    let manifest = upload_local_inputs(&s.objects, &manifest_path).await.unwrap();
    let id = s.framework.submit(&manifest).await.unwrap();
    assert!(matches!(s.executor.work_once().await.unwrap(), WorkOutcome::Done { .. }));
    let prefix = s.jobs.object_prefix(id).await.unwrap().unwrap();
    let work = s.objects.list(&prefix).await.unwrap().into_iter().next().expect("a work object");

    // Another campaign's work object, though it exists.
    let mut stealing = manifest.clone();
    stealing.strips[1].uri = work.clone();
    let found = problems(s.framework.submit(&stealing).await.unwrap_err());
    assert_eq!(found.len(), 1, "{found:?}");
    assert_eq!(found[0].0, "$.strips[1].uri");
    assert!(found[0].1.contains("inputs/"), "{}", found[0].1);

    // A half-written upload (as the file store leaves it while the upload streams).
    let partial = format!("{}.upload-{}", manifest.strips[0].uri.trim_end_matches(".las"), Uuid::new_v4().simple());
    s.objects.put(&partial, b"half".to_vec().into()).await.unwrap();
    let mut half = manifest.clone();
    half.strips[0].uri = partial.clone();
    let found = problems(s.framework.submit(&half).await.unwrap_err());
    assert_eq!(found.len(), 1, "{found:?}");
    assert_eq!(found[0].0, "$.strips[0].uri");
    assert!(found[0].1.contains("temporary"), "{}", found[0].1);

    // An input a campaign reads cannot be replaced (nor can any input: they are written once).
    let key = manifest.strips[0].uri.clone();
    let before = s.objects.get(&key).await.unwrap();
    let stream = futures::stream::iter([Ok::<_, std::io::Error>(bytes::Bytes::from_static(b"other"))]);
    let refused = s.objects.put_stream(&key, stream, 1 << 20).await.unwrap_err();
    assert!(matches!(refused, FrameworkError::Exists { .. }), "{refused}");
    assert_eq!(s.objects.get(&key).await.unwrap(), before, "the input is unchanged");
    // The refused upload left no temporary file behind (the planted one is the only one).
    let temporary: Vec<String> = s
        .objects
        .list("inputs")
        .await
        .unwrap()
        .into_iter()
        .filter(|k| precimap_framework::is_temporary_key(k))
        .collect();
    assert_eq!(temporary, std::slice::from_ref(&partial));

    // A setting only the in-process driver carries out.
    let mut estimated = manifest.clone();
    estimated.parameters.process_model = precimap_core::ProcessModel::Estimated;
    let found = problems(s.framework.submit(&estimated).await.unwrap_err());
    assert_eq!(found.len(), 1, "{found:?}");
    assert_eq!(found[0].0, "$.parameters.process_model");
    assert!(found[0].1.contains("in-process"), "{}", found[0].1);

    // Bounds: each count, then the bytes, each with its path; nothing is created.
    let tight = CampaignLimits { max_strips: 3, max_trajectories: 1, max_input_bytes: 1000 };
    let found = problems(s.framework.submit_with_limits(&manifest, &tight).await.unwrap_err());
    let paths: Vec<&str> = found.iter().map(|p| p.0.as_str()).collect();
    assert_eq!(paths, ["$.strips", "$.trajectories"], "{found:?}");
    assert!(found[0].1.contains("at most 3 strips"), "{}", found[0].1);
    let bytes = CampaignLimits { max_input_bytes: 1000, ..CampaignLimits::default() };
    let found = problems(s.framework.submit_with_limits(&manifest, &bytes).await.unwrap_err());
    assert_eq!(found.len(), 1);
    assert_eq!(found[0].0, "$");
    assert!(found[0].1.contains("at most 1000"), "{}", found[0].1);
    assert_eq!(s.jobs.list_campaigns(10).await.unwrap().len(), 1, "refused submissions create nothing");
    s.framework.submit_with_limits(&manifest, &CampaignLimits::default()).await.unwrap();

    // The sweep removes a temporary upload only once it is abandoned (untouched for an hour).
    let swept = sweep_store(&s.jobs, &s.objects, &Retention::default()).await.unwrap();
    assert_eq!(swept.abandoned_uploads, 0);
    assert!(s.objects.exists(&partial).await.unwrap());
    s.jobs.close().await;
}

/// Tasks carry no parameters: the campaign stores them once, and the executor reads them there.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn parameters_are_stored_once_per_campaign() {
    let dir = tempfile::tempdir().unwrap();
    let manifest_path = tiny_campaign(dir.path());
    let s = setup(dir.path(), false).await;
    let manifest = upload_local_inputs(&s.objects, &manifest_path).await.unwrap();
    let id = s.framework.submit(&manifest).await.unwrap();
    let stored = s.jobs.campaign_params(id).await.unwrap().expect("the campaign's parameters");
    assert_eq!(stored, serde_json::to_value(&manifest.parameters).unwrap());
    let task = s.jobs.claim("look", Duration::from_secs(60)).await.unwrap().unwrap();
    assert!(task.input.get("params").is_none(), "{}", task.input);
    // The stored spec holds the manifest without its strip and trajectory lists (rows of their own).
    let record = s.jobs.campaign(id).await.unwrap().unwrap();
    assert_eq!(record.spec["strips"], serde_json::json!([]));
    assert_eq!(s.jobs.strips(id).await.unwrap().len(), manifest.strips.len());
    // The claimed task runs with the campaign's parameters.
    let outcome = s.executor.run_task(task).await.unwrap();
    assert!(matches!(outcome, WorkOutcome::Done { .. }), "{outcome:?}");
    assert_eq!(s.jobs.campaign_progress(id).await.unwrap().unwrap().state, CampaignState::Running);
    s.jobs.close().await;
}
