//! Behaviour of the job store, each scenario on SQLite (temp file) and PostgreSQL (fresh database).

use crate::common;

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use common::*;
use precimap_jobs::*;
use serde_json::json;
use uuid::Uuid;

const LONG: Duration = Duration::from_secs(60);

fn quick_retries(max_attempts: i32) -> QueueConfig {
    QueueConfig { max_attempts, backoff_base: Duration::from_millis(0), backoff_max: Duration::from_millis(0) }
}

both_backends!(
    lease_guard,
    concurrent_claimers,
    killed_worker,
    retries_then_dead,
    permanent_failure_and_expired_last_attempt,
    cancel_and_delete,
    planner_error_fails_campaign,
    records_round_trip,
    empty_stage_is_planned_through,
    racing_last_completions,
    cancel_races_completions,
    stuck_barrier_is_advanced_by_reconcile,
    combined_concurrent_claimers,
    combined_stale_lease_claims_nothing,
    combined_last_task_advances_the_stage,
    combined_racing_last_completions,
    orphan_sweep_is_claimed_once_then_marked,
);

async fn lease_guard(store: JobStore, _url: String) {
    let planner = ChainPlanner::new(&[2]);
    let id = store.create_campaign(new_campaign("lease", QueueConfig::default()), planner.first()).await.unwrap();
    let task = store.claim("w1", LONG).await.unwrap().expect("a task");
    assert_eq!((task.campaign, task.attempt, task.key.as_str()), (id, 1, "s00000"));

    let stale = ClaimedTask { lease_token: Uuid::new_v4(), ..task.clone() };
    assert!(matches!(store.heartbeat(&stale, LONG).await, Err(JobError::LeaseLost)));
    assert!(matches!(store.complete(&stale, outcome(&stale), &planner).await, Err(JobError::LeaseLost)));
    assert!(matches!(store.fail(&stale, "boom", false).await, Err(JobError::LeaseLost)));
    assert!(store.recorded_keys(id).await.unwrap().is_empty(), "a stale token records nothing");

    let before = task.lease_expires_at_ms;
    let after = store.heartbeat_until(&task, Duration::from_secs(120)).await.unwrap();
    assert!(after > before, "heartbeat extends the lease");
    assert_eq!(store.live_lease_tokens(id).await.unwrap(), vec![task.lease_token]);

    let done = store.complete(&task, outcome(&task), &planner).await.unwrap();
    assert_eq!(done, Completion { stage_finished: false, campaign_state: CampaignState::Running });
    // Completing twice (a duplicated delivery) is refused and records nothing more.
    assert!(matches!(store.complete(&task, outcome(&task), &planner).await, Err(JobError::LeaseLost)));
    assert!(matches!(store.heartbeat(&task, LONG).await, Err(JobError::LeaseLost)));
    assert!(matches!(store.fail(&task, "late", false).await, Err(JobError::LeaseLost)));
    let outs = store.outputs(id, "s0", 0).await.unwrap();
    assert_eq!(outs.len(), 1);
    assert_eq!(outs[0].task_key, "s00000");
    assert_eq!(store.recorded_keys(id).await.unwrap(), vec![outs[0].object_key.clone()]);
    assert!(store.live_lease_tokens(id).await.unwrap().is_empty());
    let counts = store.task_counts(id).await.unwrap();
    assert_eq!((counts.done, counts.queued, counts.leased), (1, 1, 0));

    // Duplicate output names are a caller bug, refused before anything is written.
    let t2 = store.claim("w1", LONG).await.unwrap().unwrap();
    let twice = TaskOutcome {
        result: json!(null),
        outputs: vec![
            OutputKey { name: "a".into(), object_key: "x".into() },
            OutputKey { name: "a".into(), object_key: "y".into() },
        ],
    };
    assert!(matches!(store.complete(&t2, twice, &planner).await, Err(JobError::Invalid(_))));
    let last = store.complete(&t2, outcome(&t2), &planner).await.unwrap();
    assert_eq!(last, Completion { stage_finished: true, campaign_state: CampaignState::Succeeded });
    assert_eq!(planner.calls(), vec![("s0".to_string(), 0, 2)]);
}

async fn concurrent_claimers(store: JobStore, url: String) {
    let planner = Arc::new(ChainPlanner::new(&[500, 40, 7]));
    let id = store.create_campaign(new_campaign("race", QueueConfig::default()), planner.first()).await.unwrap();
    // A second store (its own pool) plays a second executor process.
    let other = JobStore::connect(&url).await.unwrap();
    let completed: Arc<Mutex<HashMap<(String, String), usize>>> = Arc::default();
    let barriers = Arc::new(Mutex::new(0usize));
    let mut workers = Vec::new();
    for w in 0..16 {
        let store = if w % 2 == 0 { store.clone() } else { other.clone() };
        let (planner, completed, barriers) = (planner.clone(), completed.clone(), barriers.clone());
        workers.push(tokio::spawn(async move {
            let name = format!("w{w}");
            loop {
                match store.claim(&name, LONG).await.unwrap() {
                    Some(task) => {
                        let c = store.complete(&task, outcome(&task), planner.as_ref()).await.unwrap();
                        *completed.lock().unwrap().entry((task.stage.clone(), task.key.clone())).or_default() += 1;
                        if c.stage_finished {
                            *barriers.lock().unwrap() += 1;
                        }
                    }
                    None => {
                        let c = store.campaign(id).await.unwrap().unwrap();
                        if c.state.is_finished() {
                            break;
                        }
                        // The stage's last tasks are still running elsewhere.
                        tokio::time::sleep(Duration::from_millis(2)).await;
                    }
                }
            }
        }));
    }
    for w in workers {
        w.await.unwrap();
    }
    let completed = completed.lock().unwrap().clone();
    assert_eq!(completed.len(), 547, "every task was completed");
    assert!(completed.values().all(|&n| n == 1), "no task was completed twice");
    assert_eq!(*barriers.lock().unwrap(), 3, "one barrier per stage");
    assert_eq!(
        planner.calls(),
        vec![("s0".to_string(), 0, 500), ("s1".to_string(), 1, 40), ("s2".to_string(), 2, 7)],
        "the planner ran exactly once per stage, with all of the stage's tasks"
    );
    let c = store.campaign(id).await.unwrap().unwrap();
    assert_eq!(c.state, CampaignState::Succeeded);
    assert_eq!(c.plan_state, json!({ "stage": 3, "seen": 3 }));
    assert_eq!((c.stage.as_str(), c.iteration), ("s2", 2));
    assert!(c.finished_at_ms.is_some());
    let counts = store.task_counts(id).await.unwrap();
    assert_eq!((counts.done, counts.queued, counts.leased, counts.dead), (547, 0, 0, 0));
    assert_eq!(counts.stage.done, 7);
    assert_eq!(store.outputs(id, "s0", 0).await.unwrap().len(), 500);
    assert_eq!(store.recorded_keys(id).await.unwrap().len(), 547);
    other.close().await;
}

async fn killed_worker(store: JobStore, _url: String) {
    let planner = ChainPlanner::new(&[1]);
    let id = store.create_campaign(new_campaign("killed", quick_retries(3)), planner.first()).await.unwrap();
    let dead_worker = store.claim("w-dead", Duration::from_millis(200)).await.unwrap().unwrap();
    assert_eq!(store.reconcile(&planner).await.unwrap(), ReconcileReport::default(), "lease still valid");
    assert!(store.claim("w2", LONG).await.unwrap().is_none(), "a leased task is not claimable");

    tokio::time::sleep(Duration::from_millis(300)).await;
    // Several executors reconcile at once: the task is rescued exactly once.
    let (a, b) = tokio::join!(store.reconcile(&planner), store.reconcile(&planner));
    let (a, b) = (a.unwrap(), b.unwrap());
    assert_eq!(a.requeued + b.requeued, 1);
    assert_eq!(a.dead + b.dead, 0);

    let rescued = store.claim("w2", LONG).await.unwrap().expect("rescued task");
    assert_eq!((rescued.id, rescued.attempt), (dead_worker.id, 2));
    assert_ne!(rescued.lease_token, dead_worker.lease_token);
    assert_eq!(store.live_lease_tokens(id).await.unwrap(), vec![rescued.lease_token]);

    // The worker that was thought dead wakes up: everything it tries is refused.
    assert!(matches!(store.heartbeat(&dead_worker, LONG).await, Err(JobError::LeaseLost)));
    assert!(matches!(store.complete(&dead_worker, outcome(&dead_worker), &planner).await, Err(JobError::LeaseLost)));
    assert!(matches!(store.fail(&dead_worker, "late", false).await, Err(JobError::LeaseLost)));

    let c = store.complete(&rescued, outcome(&rescued), &planner).await.unwrap();
    assert_eq!(c.campaign_state, CampaignState::Succeeded);
    let keys = store.recorded_keys(id).await.unwrap();
    assert_eq!(keys.len(), 1);
    assert!(keys[0].contains(&rescued.lease_token.to_string()), "the rescuer's objects are the recorded ones");
    let kinds: Vec<String> = store.events(id, 0, 100).await.unwrap().into_iter().map(|e| e.kind).collect();
    assert!(kinds.contains(&"lease_expired".to_string()), "{kinds:?}");
}

async fn retries_then_dead(store: JobStore, _url: String) {
    let planner = ChainPlanner::new(&[2]);
    let queue = QueueConfig {
        max_attempts: 3,
        backoff_base: Duration::from_millis(300),
        backoff_max: Duration::from_millis(500),
    };
    assert_eq!(queue.backoff(1), Duration::from_millis(300));
    assert_eq!(queue.backoff(2), Duration::from_millis(500), "capped");
    let a = store.create_campaign(new_campaign("a", queue), planner.first()).await.unwrap();
    let b = store.create_campaign(new_campaign("b", queue), stage("s0", 0, 1)).await.unwrap();

    let t = store.claim("w", LONG).await.unwrap().unwrap();
    assert_eq!((t.campaign, t.key.as_str(), t.attempt), (a, "s00000", 1));
    let now = store.now_ms().await.unwrap();
    let FailOutcome::Retry { not_before_ms } = store.fail(&t, "disk full", false).await.unwrap() else {
        panic!("first failure must be retried");
    };
    assert!((not_before_ms - now - 300).abs() < 200, "back-off of the first retry ≈ 300 ms");

    // While a's first task backs off, the next runnable tasks are claimed.
    let a2 = store.claim("w", LONG).await.unwrap().unwrap();
    assert_eq!((a2.campaign, a2.key.as_str()), (a, "s00001"));
    let b1 = store.claim("w", LONG).await.unwrap().unwrap();
    assert_eq!(b1.campaign, b);
    assert!(store.claim("w", LONG).await.unwrap().is_none(), "the failed task waits for its back-off");

    let mut attempt = 1;
    loop {
        let t = loop {
            if let Some(t) = store.claim("w", LONG).await.unwrap() {
                break t;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        };
        attempt += 1;
        assert_eq!((t.key.as_str(), t.attempt), ("s00000", attempt));
        match store.fail(&t, "disk full", false).await.unwrap() {
            FailOutcome::Retry { .. } => assert!(attempt < 3),
            FailOutcome::Dead => {
                assert_eq!(attempt, 3, "dead after max_attempts");
                break;
            }
        }
    }
    let ca = store.campaign(a).await.unwrap().unwrap();
    assert_eq!(ca.state, CampaignState::Failed);
    assert_eq!(ca.error.as_deref(), Some("`work s00000`: disk full"));
    let counts = store.task_counts(a).await.unwrap();
    assert_eq!((counts.dead, counts.cancelled, counts.queued, counts.leased), (1, 1, 0, 0));
    // a's other running task was cancelled with the campaign.
    assert!(matches!(store.complete(&a2, outcome(&a2), &planner).await, Err(JobError::LeaseLost)));

    // b is unaffected.
    assert_eq!(store.campaign(b).await.unwrap().unwrap().state, CampaignState::Running);
    let done = store.complete(&b1, outcome(&b1), &ChainPlanner::new(&[1])).await.unwrap();
    assert_eq!(done.campaign_state, CampaignState::Succeeded);
}

async fn permanent_failure_and_expired_last_attempt(store: JobStore, _url: String) {
    let planner = ChainPlanner::new(&[1]);
    let a = store.create_campaign(new_campaign("perm", quick_retries(5)), planner.first()).await.unwrap();
    let t = store.claim("w", LONG).await.unwrap().unwrap();
    assert_eq!(store.fail(&t, "not a LAS file", true).await.unwrap(), FailOutcome::Dead);
    let c = store.campaign(a).await.unwrap().unwrap();
    assert_eq!((c.state, c.error.as_deref()), (CampaignState::Failed, Some("`work s00000`: not a LAS file")));

    // A lease that expires on the last attempt makes the task dead and fails the campaign.
    let b = store.create_campaign(new_campaign("expire", quick_retries(1)), stage("s0", 0, 2)).await.unwrap();
    let t = store.claim("w-crash", Duration::from_millis(100)).await.unwrap().unwrap();
    assert_eq!(t.campaign, b);
    tokio::time::sleep(Duration::from_millis(250)).await;
    assert_eq!(
        store.reconcile(&planner).await.unwrap(),
        ReconcileReport { requeued: 0, dead: 1, advanced: 0, finished: vec![b] }
    );
    let c = store.campaign(b).await.unwrap().unwrap();
    assert_eq!(c.state, CampaignState::Failed);
    assert!(c.error.as_deref().unwrap_or("").starts_with("`work s00000`: lease expired"), "{:?}", c.error);
    assert!(store.claim("w", LONG).await.unwrap().is_none(), "the failed campaign's other task was cancelled");
}

async fn cancel_and_delete(store: JobStore, _url: String) {
    let planner = ChainPlanner::new(&[3, 1]);
    let keep = store.create_campaign(new_campaign("keep", QueueConfig::default()), stage("s0", 0, 1)).await.unwrap();
    let id = store.create_campaign(new_campaign("gone", QueueConfig::default()), planner.first()).await.unwrap();
    let kept = store.claim("w", LONG).await.unwrap().unwrap();
    assert_eq!(kept.campaign, keep);
    let first = store.claim("w", LONG).await.unwrap().unwrap();
    let second = store.claim("w", LONG).await.unwrap().unwrap();
    store.complete(&first, outcome(&first), &planner).await.unwrap();

    assert!(store.cancel_campaign(id).await.unwrap());
    assert!(!store.cancel_campaign(id).await.unwrap(), "already finished");
    let c = store.campaign(id).await.unwrap().unwrap();
    assert_eq!(c.state, CampaignState::Cancelled);
    let counts = store.task_counts(id).await.unwrap();
    assert_eq!((counts.done, counts.cancelled, counts.queued, counts.leased), (1, 2, 0, 0));
    assert!(store.claim("w", LONG).await.unwrap().is_none(), "nothing of a cancelled campaign is claimable");
    assert!(matches!(store.heartbeat(&second, LONG).await, Err(JobError::LeaseLost)));
    assert!(matches!(store.complete(&second, outcome(&second), &planner).await, Err(JobError::LeaseLost)));
    assert!(store.live_lease_tokens(id).await.unwrap().is_empty());

    assert_eq!(store.delete_campaign(id).await.unwrap().as_deref(), Some("c/gone/"));
    assert!(store.campaign(id).await.unwrap().is_none());
    assert!(store.strips(id).await.unwrap().is_empty());
    assert!(store.trajectories(id).await.unwrap().is_empty());
    assert!(store.events(id, 0, 100).await.unwrap().is_empty());
    assert!(store.recorded_keys(id).await.unwrap().is_empty());
    assert!(matches!(store.task_counts(id).await, Err(JobError::NotFound(_))));
    assert!(matches!(store.cancel_campaign(id).await, Err(JobError::NotFound(_))));
    assert_eq!(store.delete_campaign(id).await.unwrap(), None);

    // The other campaign is untouched.
    assert_eq!(store.strips(keep).await.unwrap().len(), 2);
    let c = store.complete(&kept, outcome(&kept), &ChainPlanner::new(&[1])).await.unwrap();
    assert_eq!(c.campaign_state, CampaignState::Succeeded);
}

async fn planner_error_fails_campaign(store: JobStore, _url: String) {
    let id = store.create_campaign(new_campaign("bad", QueueConfig::default()), stage("s0", 0, 1)).await.unwrap();
    let t = store.claim("w", LONG).await.unwrap().unwrap();
    let c = store.complete(&t, outcome(&t), &FailingPlanner).await.unwrap();
    assert_eq!(c, Completion { stage_finished: true, campaign_state: CampaignState::Failed });
    let rec = store.campaign(id).await.unwrap().unwrap();
    assert_eq!(rec.state, CampaignState::Failed);
    assert_eq!(rec.error.as_deref(), Some("no tile has points: check the manifest's CRS"));
    // The task's own result stays committed: the failure is the planner's, not the task's.
    assert_eq!(store.outputs(id, "s0", 0).await.unwrap().len(), 1);
    let last = store.events(id, 0, 100).await.unwrap().pop().unwrap();
    assert_eq!(last.kind, "failed");
}

async fn records_round_trip(store: JobStore, _url: String) {
    let planner = ChainPlanner::new(&[1, 1]);
    let older = store.create_campaign(new_campaign("older", QueueConfig::default()), stage("x", 0, 1)).await.unwrap();
    tokio::time::sleep(Duration::from_millis(5)).await;
    let nc = new_campaign("newer", QueueConfig::default());
    let id = store.create_campaign(nc.clone(), planner.first()).await.unwrap();
    let list = store.list_campaigns(10).await.unwrap();
    assert_eq!(list.iter().map(|c| c.id).collect::<Vec<_>>(), vec![id, older], "newest first");
    assert_eq!(store.list_campaigns(1).await.unwrap().len(), 1);
    let c = store.campaign(id).await.unwrap().unwrap();
    assert_eq!((c.name.as_str(), c.spec.clone(), c.queue), ("newer", nc.spec.clone(), nc.queue));
    assert_eq!(store.strips(id).await.unwrap(), nc.strips);
    assert_eq!(store.trajectories(id).await.unwrap(), nc.trajectories);

    // Skip the older campaign's task; run the newer one through its two stages.
    let x = store.claim("w", LONG).await.unwrap().unwrap();
    assert_eq!(x.campaign, older);
    let t = store.claim("w", LONG).await.unwrap().unwrap();
    assert_eq!(t.input, json!({ "i": 0 }));
    let c = store.complete(&t, outcome(&t), &planner).await.unwrap();
    assert_eq!(c, Completion { stage_finished: true, campaign_state: CampaignState::Running });
    assert_eq!(
        store.tiles(id).await.unwrap(),
        vec![TileRecord { key: "1_2".into(), strips: vec!["s0".into(), "s1".into()], points: 42 }]
    );
    let counts = store.task_counts(id).await.unwrap();
    assert_eq!((counts.done, counts.queued, counts.stage.queued, counts.stage.done), (1, 1, 1, 0));
    // The light view a progress display polls agrees with the full record and counts.
    let progress = store.campaign_progress(id).await.unwrap().unwrap();
    assert_eq!(
        (progress.id, progress.name.as_str(), progress.state, progress.stage.as_str(), progress.iteration),
        (id, "newer", CampaignState::Running, "s1", 1)
    );
    let full = store.campaign(id).await.unwrap().unwrap();
    assert_eq!((progress.iterations_planned, progress.error), (full.iterations_planned, full.error));
    assert_eq!(store.stage_counts(id, "s1", 1).await.unwrap(), counts.stage);
    assert_eq!(store.stage_counts(id, "s0", 0).await.unwrap(), StateCounts { done: 1, ..Default::default() });
    assert_eq!(store.stage_counts(id, "nope", 0).await.unwrap(), StateCounts::default());
    assert!(store.campaign_progress(Uuid::new_v4()).await.unwrap().is_none());
    let t = store.claim("w", LONG).await.unwrap().unwrap();
    assert_eq!((t.stage.as_str(), t.iteration), ("s1", 1));
    store.complete(&t, outcome(&t), &planner).await.unwrap();
    assert_eq!(
        store.iterations(id).await.unwrap(),
        vec![IterationRecord { iteration: 1, stats: json!({ "tasks": 1 }) }]
    );
    assert_eq!(store.iterations_after(id, 0).await.unwrap(), store.iterations(id).await.unwrap());
    assert!(store.iterations_after(id, 1).await.unwrap().is_empty());
    let done = store.campaign_progress(id).await.unwrap().unwrap();
    assert_eq!((done.state, done.error), (CampaignState::Succeeded, None));

    let events = store.events(id, 0, 1000).await.unwrap();
    assert!(events.windows(2).all(|w| w[0].id < w[1].id));
    assert_eq!(events.first().map(|e| e.kind.as_str()), Some("campaign_created"));
    assert_eq!(events.last().map(|e| e.kind.as_str()), Some("succeeded"));
    let tail = store.events(id, events[2].id, 2).await.unwrap();
    assert_eq!(tail, events[3..5].to_vec(), "paging after an id");
    let latest = store.latest_events(id, 3).await.unwrap();
    assert_eq!(latest, events[events.len() - 3..].to_vec(), "the newest three, oldest first");
    assert_eq!(store.latest_events(id, 1000).await.unwrap(), events);
}

/// s0 → `gap` (no tasks) → s2 (one task) → `Next::Fail` with a message.
struct GapPlanner;

impl StagePlanner for GapPlanner {
    fn plan(&self, _: &CampaignRecord, finished: &FinishedStage) -> Result<Transition, String> {
        let next = match finished.stage.as_str() {
            "s0" => {
                // The stage's wall-clock span, on the database's clock.
                let span = finished.span_ms.expect("a stage with tasks has a span");
                let now_ms = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_millis();
                assert!(span.enqueued_at_ms <= span.finished_at_ms, "{span:?}");
                assert!((now_ms as i64 - span.finished_at_ms).abs() < 60_000, "{span:?} is not now");
                Next::Stage(StageSpec { stage: "gap".into(), iteration: 1, tasks: vec![] })
            }
            "gap" => {
                assert!(finished.tasks.is_empty());
                assert_eq!(finished.span_ms, None);
                Next::Stage(stage("s2", 2, 1))
            }
            _ => Next::Fail("converged to nonsense".into()),
        };
        Ok(Transition { plan_state: json!({ "after": finished.stage }), tiles: vec![], iteration: None, next })
    }
}

async fn empty_stage_is_planned_through(store: JobStore, _url: String) {
    let id = store.create_campaign(new_campaign("gap", QueueConfig::default()), stage("s0", 0, 1)).await.unwrap();
    let t = store.claim("w", LONG).await.unwrap().unwrap();
    let c = store.complete(&t, outcome(&t), &GapPlanner).await.unwrap();
    assert_eq!(c, Completion { stage_finished: true, campaign_state: CampaignState::Running });
    let rec = store.campaign(id).await.unwrap().unwrap();
    assert_eq!((rec.stage.as_str(), rec.iteration, rec.plan_state.clone()), ("s2", 2, json!({ "after": "gap" })));
    let t = store.claim("w", LONG).await.unwrap().unwrap();
    assert_eq!(t.stage, "s2");
    let c = store.complete(&t, outcome(&t), &GapPlanner).await.unwrap();
    assert_eq!(c.campaign_state, CampaignState::Failed);
    assert_eq!(store.campaign(id).await.unwrap().unwrap().error.as_deref(), Some("converged to nonsense"));
    // An empty first stage could never finish: refused up front.
    let err = store
        .create_campaign(
            new_campaign("empty", QueueConfig::default()),
            StageSpec { stage: "s0".into(), iteration: 0, tasks: vec![] },
        )
        .await
        .unwrap_err();
    assert!(matches!(err, JobError::Invalid(_)), "{err}");
}

#[tokio::test]
async fn unknown_scheme_is_a_clear_error() {
    let err = JobStore::connect("mysql://localhost/db").await.unwrap_err();
    assert!(matches!(err, JobError::BadUrl { .. }), "{err}");
    assert!(err.to_string().contains("postgres://"), "{err}");
}

#[tokio::test]
async fn unreachable_database_is_transient() {
    // Nothing listens on port 1: the error must be one a worker retries.
    let opts = StoreOptions { acquire_timeout: Duration::from_secs(2), ..StoreOptions::default() };
    let err = JobStore::connect_with("postgres://postgres@127.0.0.1:1/none", opts).await.unwrap_err();
    assert!(err.is_transient(), "{err:?}");
}

#[tokio::test]
async fn in_memory_sqlite_works() {
    let store = JobStore::connect("sqlite::memory:").await.unwrap();
    let id = store.create_campaign(new_campaign("mem", QueueConfig::default()), stage("s0", 0, 1)).await.unwrap();
    let t = store.claim("w", LONG).await.unwrap().unwrap();
    let c = store.complete(&t, outcome(&t), &ChainPlanner::new(&[1])).await.unwrap();
    assert_eq!(c.campaign_state, CampaignState::Succeeded);
    assert_eq!(store.campaign(id).await.unwrap().unwrap().state, CampaignState::Succeeded);
}

/// Leases a whole stage of `n` tasks (nothing of it stays claimable).
async fn lease_stage(store: &JobStore, stage: &str, n: usize) -> Vec<ClaimedTask> {
    let mut tasks = Vec::with_capacity(n);
    for _ in 0..n {
        let t = store.claim("w", LONG).await.unwrap().expect("a task of the stage");
        assert_eq!(t.stage, stage);
        tasks.push(t);
    }
    assert!(store.claim("w", LONG).await.unwrap().is_none(), "the whole stage is leased");
    tasks
}

/// All tasks of a stage complete at once, from two pools (two executor processes), each task
/// twice (a duplicated delivery, with an object key of its own), in the second stage while two
/// reconcilers run: every task is committed exactly once with the outputs of the copy that won,
/// and the barrier fires exactly once per stage, whoever sees the stage closed (and without the
/// reconcilers, it does fire).
async fn racing_last_completions(store: JobStore, url: String) {
    const N: usize = 40;
    let planner = Arc::new(ChainPlanner::new(&[N, N, N, 1]));
    let id = store.create_campaign(new_campaign("race", QueueConfig::default()), planner.first()).await.unwrap();
    let other = JobStore::connect(&url).await.unwrap();
    for round in 0..3i32 {
        let stage_name = format!("s{round}");
        let tasks = lease_stage(&store, &stage_name, N).await;
        let reconcilers = if round == 1 { 2 } else { 0 };
        let start = Arc::new(tokio::sync::Barrier::new(2 * N + reconcilers));
        let mut completers = Vec::new();
        for (i, task) in tasks.into_iter().enumerate() {
            for copy in 0..2 {
                let store = if (i + copy) % 2 == 0 { store.clone() } else { other.clone() };
                let (planner, start, task) = (planner.clone(), start.clone(), task.clone());
                completers.push(tokio::spawn(async move {
                    let mut out = outcome(&task);
                    out.outputs[0].object_key.push_str(&format!(".copy{copy}"));
                    let key = out.outputs[0].object_key.clone();
                    start.wait().await;
                    (task.id, key, store.complete(&task, out, planner.as_ref()).await)
                }));
            }
        }
        let reconcilers: Vec<_> = (0..reconcilers)
            .map(|r| {
                let store = if r == 0 { store.clone() } else { other.clone() };
                let (planner, start) = (planner.clone(), start.clone());
                tokio::spawn(async move {
                    start.wait().await;
                    let mut advanced = 0;
                    for _ in 0..5 {
                        let report = store.reconcile(planner.as_ref()).await.unwrap();
                        assert_eq!((report.requeued, report.dead), (0, 0));
                        advanced += report.advanced;
                        tokio::task::yield_now().await;
                    }
                    advanced
                })
            })
            .collect();
        let mut committed: HashMap<i64, String> = HashMap::new();
        let mut barriers = 0;
        for c in completers {
            let (task_id, key, result) = c.await.unwrap();
            match result {
                Ok(c) => {
                    assert_eq!(c.campaign_state, CampaignState::Running);
                    barriers += u64::from(c.stage_finished);
                    assert!(committed.insert(task_id, key).is_none(), "task {task_id} committed twice");
                }
                Err(JobError::LeaseLost) => {}
                Err(e) => panic!("completion failed: {e}"),
            }
        }
        for r in reconcilers {
            barriers += r.await.unwrap();
        }
        assert_eq!(committed.len(), N, "every task committed once");
        assert_eq!(barriers, 1, "stage {stage_name}: the barrier fired once");
        let c = store.campaign(id).await.unwrap().unwrap();
        assert_eq!((c.state, c.stage, c.iteration), (CampaignState::Running, format!("s{}", round + 1), round + 1));
        let mut recorded: Vec<String> =
            store.outputs(id, &stage_name, round).await.unwrap().into_iter().map(|o| o.object_key).collect();
        let mut winners: Vec<String> = committed.into_values().collect();
        recorded.sort();
        winners.sort();
        assert_eq!(recorded, winners, "the recorded objects are those of the committed copies");
    }
    assert_eq!(
        planner.calls(),
        vec![("s0".to_string(), 0, N), ("s1".to_string(), 1, N), ("s2".to_string(), 2, N)],
        "the planner ran once per stage, with all of the stage's tasks"
    );
    let events = store.events(id, 0, 100_000).await.unwrap();
    assert_eq!(events.iter().filter(|e| e.kind == "stage").count(), 3, "one transition per stage");
    let counts = store.task_counts(id).await.unwrap();
    assert_eq!((counts.done, counts.queued, counts.leased, counts.stage.queued), (3 * N as i64, 1, 0, 1));
    let t = store.claim("w", LONG).await.unwrap().unwrap();
    let c = store.complete(&t, outcome(&t), planner.as_ref()).await.unwrap();
    assert_eq!(c, Completion { stage_finished: true, campaign_state: CampaignState::Succeeded });
    assert_eq!(store.recorded_keys(id).await.unwrap().len(), 3 * N + 1);
    other.close().await;
}

/// Cancelling while a stage's tasks complete (the cancel landing at different points): every
/// completion is either committed before the cancel or refused, a cancelled campaign is never
/// advanced, and nothing of it stays claimable or leased.
async fn cancel_races_completions(store: JobStore, url: String) {
    const N: usize = 24;
    let other = JobStore::connect(&url).await.unwrap();
    for (run, yields) in [0usize, 3, 10, 40].into_iter().enumerate() {
        let planner = Arc::new(ChainPlanner::new(&[N, 5]));
        let name = format!("cancel{run}");
        let id = store.create_campaign(new_campaign(&name, QueueConfig::default()), planner.first()).await.unwrap();
        let tasks = lease_stage(&store, "s0", N).await;
        let start = Arc::new(tokio::sync::Barrier::new(N + 1));
        let mut completers = Vec::new();
        for (i, task) in tasks.into_iter().enumerate() {
            let store = if i % 2 == 0 { store.clone() } else { other.clone() };
            let (planner, start) = (planner.clone(), start.clone());
            completers.push(tokio::spawn(async move {
                start.wait().await;
                store.complete(&task, outcome(&task), planner.as_ref()).await
            }));
        }
        let canceller = {
            let store = other.clone();
            tokio::spawn(async move {
                start.wait().await;
                for _ in 0..yields {
                    tokio::task::yield_now().await;
                }
                store.cancel_campaign(id).await.unwrap()
            })
        };
        let (mut committed, mut refused, mut barrier) = (0, 0, false);
        for c in completers {
            match c.await.unwrap() {
                Ok(c) => {
                    committed += 1;
                    barrier |= c.stage_finished;
                }
                Err(JobError::LeaseLost) => refused += 1,
                Err(e) => panic!("completion failed: {e}"),
            }
        }
        assert!(canceller.await.unwrap(), "the campaign was running when cancelled");
        assert_eq!(committed + refused, N);
        let c = store.campaign(id).await.unwrap().unwrap();
        assert_eq!(c.state, CampaignState::Cancelled);
        let counts = store.task_counts(id).await.unwrap();
        assert_eq!((counts.done, counts.queued, counts.leased), (committed as i64, 0, 0));
        if barrier {
            // Every completion came before the cancel, which then cancelled the next stage.
            assert_eq!(committed, N);
            assert_eq!(planner.calls(), vec![("s0".to_string(), 0, N)]);
            assert_eq!(counts.cancelled, 5);
        } else {
            assert!(planner.calls().is_empty(), "a cancelled campaign is not advanced");
            assert_eq!((c.stage.as_str(), counts.cancelled), ("s0", (N - committed) as i64));
        }
        assert_eq!(store.recorded_keys(id).await.unwrap().len(), committed, "refused completions record nothing");
        assert!(store.live_lease_tokens(id).await.unwrap().is_empty());
        assert!(store.claim("w", LONG).await.unwrap().is_none(), "nothing of a cancelled campaign is claimable");
        assert_eq!(store.reconcile(planner.as_ref()).await.unwrap(), ReconcileReport::default());
        assert_eq!(store.campaign(id).await.unwrap().unwrap().state, CampaignState::Cancelled);
    }
    other.close().await;
}

/// A planner that panics: the completer dies between its commit and the barrier.
struct DyingPlanner;

impl StagePlanner for DyingPlanner {
    fn plan(&self, _: &CampaignRecord, _: &FinishedStage) -> Result<Transition, String> {
        panic!("executor killed at the barrier");
    }
}

async fn stuck_barrier_is_advanced_by_reconcile(store: JobStore, _url: String) {
    let planner = ChainPlanner::new(&[2, 1]);
    let id = store.create_campaign(new_campaign("stuck", QueueConfig::default()), planner.first()).await.unwrap();
    let t1 = store.claim("w", LONG).await.unwrap().unwrap();
    let t2 = store.claim("w", LONG).await.unwrap().unwrap();
    let c = store.complete(&t1, outcome(&t1), &planner).await.unwrap();
    assert_eq!(c, Completion { stage_finished: false, campaign_state: CampaignState::Running });
    let died = {
        let (store, t2) = (store.clone(), t2.clone());
        tokio::spawn(async move { store.complete(&t2, outcome(&t2), &DyingPlanner).await }).await
    };
    assert!(died.unwrap_err().is_panic());

    // The task's commit stands, but the stage was not advanced: nothing is claimable.
    let c = store.campaign(id).await.unwrap().unwrap();
    assert_eq!((c.state, c.stage.as_str(), c.iteration), (CampaignState::Running, "s0", 0));
    let counts = store.task_counts(id).await.unwrap();
    assert_eq!((counts.done, counts.queued, counts.leased), (2, 0, 0));
    assert!(store.claim("w", LONG).await.unwrap().is_none());
    assert!(matches!(store.complete(&t2, outcome(&t2), &planner).await, Err(JobError::LeaseLost)));
    assert_eq!(store.recorded_keys(id).await.unwrap().len(), 2);
    assert!(planner.calls().is_empty());

    // The reconciler advances it, once.
    let (a, b) = tokio::join!(store.reconcile(&planner), store.reconcile(&planner));
    assert_eq!(a.unwrap().advanced + b.unwrap().advanced, 1);
    assert_eq!(planner.calls(), vec![("s0".to_string(), 0, 2)]);
    let c = store.campaign(id).await.unwrap().unwrap();
    assert_eq!((c.state, c.stage.as_str(), c.iteration), (CampaignState::Running, "s1", 1));
    let kinds: Vec<String> = store.events(id, 0, 100).await.unwrap().into_iter().map(|e| e.kind).collect();
    assert!(kinds.contains(&"stage_rescued".to_string()), "{kinds:?}");
    assert_eq!(store.reconcile(&planner).await.unwrap(), ReconcileReport::default());

    // The last stage's completer dies too: the reconciler finishes the campaign and names it, so
    // that its caller cleans up the orphaned objects no completion saw the end of.
    let t3 = store.claim("w", LONG).await.unwrap().expect("a task of the next stage");
    assert_eq!((t3.stage.as_str(), t3.iteration), ("s1", 1));
    let died = {
        let (store, t3) = (store.clone(), t3.clone());
        tokio::spawn(async move { store.complete(&t3, outcome(&t3), &DyingPlanner).await }).await
    };
    assert!(died.unwrap_err().is_panic());
    let report = store.reconcile(&planner).await.unwrap();
    assert_eq!(report, ReconcileReport { requeued: 0, dead: 0, advanced: 1, finished: vec![id] });
    assert_eq!(store.campaign(id).await.unwrap().unwrap().state, CampaignState::Succeeded);
    assert_eq!(store.reconcile(&planner).await.unwrap(), ReconcileReport::default());
}

/// 16 executors (two pools) that claim only when they hold nothing and otherwise complete with
/// `complete_and_claim`, through three stages: every task is claimed once and completed once,
/// the barrier fires once per stage with all of the stage's tasks, and most claims are the
/// combined ones.
async fn combined_concurrent_claimers(store: JobStore, url: String) {
    let planner = Arc::new(ChainPlanner::new(&[300, 40, 7]));
    let id = store.create_campaign(new_campaign("chain", QueueConfig::default()), planner.first()).await.unwrap();
    let other = JobStore::connect(&url).await.unwrap();
    let completed: Arc<Mutex<HashMap<(String, String), usize>>> = Arc::default();
    let claimed: Arc<Mutex<HashMap<i64, usize>>> = Arc::default();
    let (barriers, combined) = (Arc::new(Mutex::new(0usize)), Arc::new(Mutex::new(0usize)));
    let mut workers = Vec::new();
    for w in 0..16 {
        let store = if w % 2 == 0 { store.clone() } else { other.clone() };
        let (planner, completed, claimed) = (planner.clone(), completed.clone(), claimed.clone());
        let (barriers, combined) = (barriers.clone(), combined.clone());
        workers.push(tokio::spawn(async move {
            let name = format!("w{w}");
            let mut held: Option<ClaimedTask> = None;
            loop {
                let task = match held.take() {
                    Some(task) => task,
                    None => match store.claim(&name, LONG).await.unwrap() {
                        Some(task) => {
                            *claimed.lock().unwrap().entry(task.id).or_default() += 1;
                            task
                        }
                        None => {
                            if store.campaign(id).await.unwrap().unwrap().state.is_finished() {
                                break;
                            }
                            tokio::time::sleep(Duration::from_millis(2)).await;
                            continue;
                        }
                    },
                };
                let (c, next) =
                    store.complete_and_claim(&task, outcome(&task), planner.as_ref(), &name, LONG).await.unwrap();
                *completed.lock().unwrap().entry((task.stage.clone(), task.key.clone())).or_default() += 1;
                if c.stage_finished {
                    *barriers.lock().unwrap() += 1;
                }
                if let Some(next) = &next {
                    assert_eq!((next.attempt, next.campaign), (1, id));
                    assert_ne!(next.id, task.id);
                    *claimed.lock().unwrap().entry(next.id).or_default() += 1;
                    *combined.lock().unwrap() += 1;
                }
                held = next;
            }
            assert!(held.is_none());
        }));
    }
    for w in workers {
        w.await.unwrap();
    }
    let completed = completed.lock().unwrap().clone();
    assert_eq!(completed.len(), 347, "every task was completed");
    assert!(completed.values().all(|&n| n == 1), "no task was completed twice");
    let claimed = claimed.lock().unwrap().clone();
    assert_eq!(claimed.len(), 347, "every task was claimed");
    assert!(claimed.values().all(|&n| n == 1), "no task was claimed twice");
    let combined = *combined.lock().unwrap();
    assert!(combined > 347 / 2, "only {combined} of 347 claims came with a completion");
    assert_eq!(*barriers.lock().unwrap(), 3, "one barrier per stage");
    assert_eq!(
        planner.calls(),
        vec![("s0".to_string(), 0, 300), ("s1".to_string(), 1, 40), ("s2".to_string(), 2, 7)],
        "the planner ran exactly once per stage, with all of the stage's tasks"
    );
    let c = store.campaign(id).await.unwrap().unwrap();
    assert_eq!(c.state, CampaignState::Succeeded);
    let counts = store.task_counts(id).await.unwrap();
    assert_eq!((counts.done, counts.queued, counts.leased, counts.dead), (347, 0, 0, 0));
    assert_eq!(store.recorded_keys(id).await.unwrap().len(), 347);
    let events = store.events(id, 0, 100_000).await.unwrap();
    assert_eq!(events.iter().filter(|e| e.kind == "claimed").count(), 347, "one claim event per claim");
    assert_eq!(events.iter().filter(|e| e.kind == "done").count(), 347);
    other.close().await;
}

/// A stale lease token (never held, completed already, expired and rescued, campaign cancelled)
/// neither completes nor claims, though other tasks are claimable.
async fn combined_stale_lease_claims_nothing(store: JobStore, _url: String) {
    let planner = ChainPlanner::new(&[4]);
    let id = store.create_campaign(new_campaign("stale", quick_retries(3)), planner.first()).await.unwrap();
    let t1 = store.claim("w", LONG).await.unwrap().unwrap();
    let queued = |store: JobStore| async move { store.task_counts(id).await.unwrap().queued };

    let stale = ClaimedTask { lease_token: Uuid::new_v4(), ..t1.clone() };
    let r = store.complete_and_claim(&stale, outcome(&stale), &planner, "w", LONG).await;
    assert!(matches!(r, Err(JobError::LeaseLost)), "{r:?}");
    assert!(store.recorded_keys(id).await.unwrap().is_empty(), "a stale token records nothing");
    assert_eq!(queued(store.clone()).await, 3, "a stale token claims nothing");
    assert_eq!(store.live_lease_tokens(id).await.unwrap(), vec![t1.lease_token]);

    assert_eq!(store.leased_by("w").await.unwrap(), vec![t1.clone()], "the lease as claimed, found by worker");
    assert!(store.leased_by("v").await.unwrap().is_empty());

    // The holder completes and gets the next task; completing again (a duplicated delivery) is
    // refused and claims nothing more.
    let (c, t2) = store.complete_and_claim(&t1, outcome(&t1), &planner, "w", LONG).await.unwrap();
    assert_eq!(c, Completion { stage_finished: false, campaign_state: CampaignState::Running });
    let t2 = t2.expect("the next task");
    assert_eq!((t2.key.as_str(), t2.attempt, t2.stage.as_str()), ("s00001", 1, "s0"));
    assert_ne!(t2.lease_token, t1.lease_token);
    // What a loop whose call failed after the commit finds: the task it claimed, as returned.
    assert_eq!(store.leased_by("w").await.unwrap(), vec![t2.clone()]);
    let r = store.complete_and_claim(&t1, outcome(&t1), &planner, "w", LONG).await;
    assert!(matches!(r, Err(JobError::LeaseLost)), "{r:?}");
    assert_eq!(queued(store.clone()).await, 2);
    assert_eq!(store.recorded_keys(id).await.unwrap().len(), 1);

    // An expired lease, rescued: the old holder's completion is refused and claims nothing.
    let short = store.claim("slow", Duration::from_millis(100)).await.unwrap().unwrap();
    tokio::time::sleep(Duration::from_millis(200)).await;
    assert_eq!(store.reconcile(&planner).await.unwrap().requeued, 1);
    let r = store.complete_and_claim(&short, outcome(&short), &planner, "slow", LONG).await;
    assert!(matches!(r, Err(JobError::LeaseLost)), "{r:?}");
    assert_eq!(queued(store.clone()).await, 2, "the rescued task and the last one");
    assert_eq!(store.recorded_keys(id).await.unwrap().len(), 1);

    // A cancelled campaign: its holder's completion is refused and claims nothing, although
    // another campaign has a runnable task.
    let b = store.create_campaign(new_campaign("other", QueueConfig::default()), stage("s0", 0, 1)).await.unwrap();
    assert!(store.cancel_campaign(id).await.unwrap());
    let r = store.complete_and_claim(&t2, outcome(&t2), &planner, "w", LONG).await;
    assert!(matches!(r, Err(JobError::LeaseLost)), "{r:?}");
    let other = store.task_counts(b).await.unwrap();
    assert_eq!((other.queued, other.leased), (1, 0), "nothing of the other campaign was claimed");
    assert!(store.live_lease_tokens(id).await.unwrap().is_empty());
    assert_eq!(store.recorded_keys(id).await.unwrap().len(), 1);
    assert!(planner.calls().is_empty());
}

/// The completion of a stage's last task advances it, also when the combined claim takes a task
/// of the same stage before (which skips the barrier check) or of another campaign; after the
/// advance the completer holds the next stage's first task.
async fn combined_last_task_advances_the_stage(store: JobStore, _url: String) {
    let planner = ChainPlanner::new(&[2, 3]);
    let id = store.create_campaign(new_campaign("last", QueueConfig::default()), planner.first()).await.unwrap();
    let t1 = store.claim("w", LONG).await.unwrap().unwrap();
    // t2 is still queued: the completion of t1 claims it (same stage, no barrier).
    let (c, t2) = store.complete_and_claim(&t1, outcome(&t1), &planner, "w", LONG).await.unwrap();
    assert_eq!(c, Completion { stage_finished: false, campaign_state: CampaignState::Running });
    let t2 = t2.expect("the stage's second task");
    assert_eq!((t2.stage.as_str(), t2.key.as_str()), ("s0", "s00001"));
    assert!(planner.calls().is_empty());

    // The last task of s0: the stage advances and the completer holds s1's first task.
    let (c, mut next) = store.complete_and_claim(&t2, outcome(&t2), &planner, "w", LONG).await.unwrap();
    assert_eq!(c, Completion { stage_finished: true, campaign_state: CampaignState::Running });
    assert_eq!(planner.calls(), vec![("s0".to_string(), 0, 2)]);
    let c = store.campaign(id).await.unwrap().unwrap();
    assert_eq!((c.stage.as_str(), c.iteration), ("s1", 1));
    let first = next.clone().expect("the next stage's first task");
    assert_eq!((first.stage.as_str(), first.iteration, first.key.as_str()), ("s1", 1, "s10000"));

    // A second campaign's task is queued behind s1's: the last completion of s1 claims it (not
    // of its own stage, so the barrier is checked) and still finishes the first campaign.
    let b = store.create_campaign(new_campaign("behind", QueueConfig::default()), stage("s0", 0, 1)).await.unwrap();
    let mut done = 0;
    while let Some(t) = next.take() {
        if t.campaign != id {
            next = Some(t);
            break;
        }
        let (c, n) = store.complete_and_claim(&t, outcome(&t), &planner, "w", LONG).await.unwrap();
        done += 1;
        let last = done == 3;
        assert_eq!(c.stage_finished, last, "task {done} of s1");
        let state = if last { CampaignState::Succeeded } else { CampaignState::Running };
        assert_eq!(c.campaign_state, state);
        next = n;
    }
    assert_eq!(done, 3);
    assert_eq!(next.expect("the other campaign's task").campaign, b);
    assert_eq!(planner.calls(), vec![("s0".to_string(), 0, 2), ("s1".to_string(), 1, 3)]);
    let c = store.campaign(id).await.unwrap().unwrap();
    assert_eq!(c.state, CampaignState::Succeeded);
    let counts = store.task_counts(id).await.unwrap();
    assert_eq!((counts.done, counts.queued, counts.leased), (5, 0, 0));
}

/// The whole of a stage completes at once through `complete_and_claim` (two pools): the barrier
/// fires once, and only its completer claims, the next stage's first task.
async fn combined_racing_last_completions(store: JobStore, url: String) {
    const N: usize = 40;
    let planner = Arc::new(ChainPlanner::new(&[N, N, 1]));
    let id = store.create_campaign(new_campaign("race", QueueConfig::default()), planner.first()).await.unwrap();
    let other = JobStore::connect(&url).await.unwrap();
    for round in 0..2i32 {
        // Round 1's stage lost one task to round 0's claim, completed below.
        let n = if round == 0 { N } else { N - 1 };
        let tasks = lease_stage(&store, &format!("s{round}"), n).await;
        let start = Arc::new(tokio::sync::Barrier::new(n));
        let mut completers = Vec::new();
        for (i, task) in tasks.into_iter().enumerate() {
            let store = if i % 2 == 0 { store.clone() } else { other.clone() };
            let (planner, start) = (planner.clone(), start.clone());
            completers.push(tokio::spawn(async move {
                start.wait().await;
                store.complete_and_claim(&task, outcome(&task), planner.as_ref(), "w", LONG).await.unwrap()
            }));
        }
        let mut finished = Vec::new();
        let mut claimed = Vec::new();
        for c in completers {
            let (c, next) = c.await.unwrap();
            assert_eq!(c.campaign_state, CampaignState::Running);
            if c.stage_finished {
                finished.push(next.is_some());
            }
            claimed.extend(next);
        }
        assert_eq!(finished, vec![true], "round {round}: one barrier, whose completer claimed");
        assert_eq!(claimed.len(), 1, "round {round}: only the barrier's completer found a task");
        let next_stage = format!("s{}", round + 1);
        assert_eq!((claimed[0].stage.as_str(), claimed[0].iteration), (next_stage.as_str(), round + 1));
        let size = planner.sizes[round as usize + 1] as i64;
        let counts = store.task_counts(id).await.unwrap();
        assert_eq!((counts.stage.queued, counts.stage.leased, counts.stage.done), (size - 1, 1, 0));
        let c = store.complete(&claimed[0], outcome(&claimed[0]), planner.as_ref()).await.unwrap();
        assert_eq!(c.stage_finished, size == 1);
    }
    assert_eq!(
        planner.calls(),
        vec![("s0".to_string(), 0, N), ("s1".to_string(), 1, N), ("s2".to_string(), 2, 1)],
        "the planner ran once per stage, with all of the stage's tasks"
    );
    assert_eq!(store.campaign(id).await.unwrap().unwrap().state, CampaignState::Succeeded);
    other.close().await;
}

/// The durable orphan sweep: only finished campaigns past the grace period are due, one claimer
/// at a time gets each, a sweeper that died lets it go when its sweep lease expires, and a swept
/// campaign is never due again.
async fn orphan_sweep_is_claimed_once_then_marked(store: JobStore, url: String) {
    let running =
        store.create_campaign(new_campaign("running", QueueConfig::default()), stage("s0", 0, 1)).await.unwrap();
    let id = store.create_campaign(new_campaign("finished", QueueConfig::default()), stage("s0", 0, 1)).await.unwrap();
    assert_eq!(store.claim_sweep(Duration::ZERO, LONG).await.unwrap(), None, "nothing has finished");
    assert!(store.cancel_campaign(id).await.unwrap());
    assert_eq!(store.claim_sweep(LONG, LONG).await.unwrap(), None, "not within the grace period");

    // A sweeper claims it and dies: nobody else gets it until its sweep lease expires.
    assert_eq!(store.claim_sweep(Duration::ZERO, Duration::from_millis(100)).await.unwrap(), Some(id));
    assert_eq!(store.claim_sweep(Duration::ZERO, LONG).await.unwrap(), None, "sweep leased");
    tokio::time::sleep(Duration::from_millis(150)).await;

    // Two claimers at once: exactly one gets it.
    let other = JobStore::connect(&url).await.unwrap();
    let (a, b) = tokio::join!(store.claim_sweep(Duration::ZERO, LONG), other.claim_sweep(Duration::ZERO, LONG));
    let claims: Vec<Uuid> = [a.unwrap(), b.unwrap()].into_iter().flatten().collect();
    assert_eq!(claims, vec![id]);

    // Marked swept: never due again, even with its sweep lease long expired.
    store.mark_swept(id).await.unwrap();
    store.mark_swept(running).await.unwrap();
    assert_eq!(store.claim_sweep(Duration::ZERO, Duration::ZERO).await.unwrap(), None);
    assert_eq!(other.claim_sweep(Duration::ZERO, Duration::ZERO).await.unwrap(), None);

    // Marking a running campaign did nothing: once finished, it is due.
    assert!(store.cancel_campaign(running).await.unwrap());
    assert_eq!(store.claim_sweep(Duration::ZERO, LONG).await.unwrap(), Some(running));
    other.close().await;
}
