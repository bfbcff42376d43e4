//! Test harness: runs a scenario on a fresh SQLite file and on a fresh PostgreSQL database.

#![allow(dead_code)]

use std::future::Future;
use std::sync::Mutex;

use precimap_jobs::*;
use serde_json::json;
use sqlx::Connection;
use uuid::Uuid;

/// Admin URL of the test PostgreSQL server (a database we may create others from).
pub fn pg_admin_url() -> String {
    std::env::var("PRECIMAP_TEST_POSTGRES").unwrap_or_else(|_| "postgres://postgres@127.0.0.1:5432/postgres".into())
}

pub async fn create_pg_database() -> (String, String) {
    let admin = pg_admin_url();
    let name = format!("precimap_t_{}", Uuid::new_v4().simple());
    let mut conn = sqlx::PgConnection::connect(&admin).await.expect("connect to the test PostgreSQL server");
    sqlx::query(&format!("CREATE DATABASE {name}")).execute(&mut conn).await.expect("create test database");
    conn.close().await.ok();
    (precimap_jobs::with_database(&admin, &name), name)
}

pub async fn drop_pg_database(name: &str) {
    let mut conn = sqlx::PgConnection::connect(&pg_admin_url()).await.expect("connect to drop");
    sqlx::query(&format!("DROP DATABASE IF EXISTS {name} WITH (FORCE)")).execute(&mut conn).await.expect("drop db");
    conn.close().await.ok();
}

/// Runs `scenario` against a store on `backend`; the database is removed afterwards, also when
/// the scenario panics (the panic is then re-raised).
pub async fn run<F, Fut>(backend: Backend, scenario: F)
where
    F: FnOnce(JobStore, String) -> Fut,
    Fut: Future<Output = ()> + Send + 'static,
{
    match backend {
        Backend::Sqlite => {
            let dir = tempfile::tempdir().unwrap();
            let url = format!("sqlite://{}", dir.path().join("jobs.db").display());
            let store = JobStore::connect(&url).await.unwrap();
            assert_eq!(store.backend(), Backend::Sqlite);
            let res = tokio::spawn(scenario(store.clone(), url)).await;
            store.close().await;
            if let Err(e) = res {
                std::panic::resume_unwind(e.into_panic());
            }
        }
        Backend::Postgres => {
            let (url, name) = create_pg_database().await;
            let store = JobStore::connect(&url).await.unwrap();
            assert_eq!(store.backend(), Backend::Postgres);
            let res = tokio::spawn(scenario(store.clone(), url)).await;
            store.close().await;
            drop_pg_database(&name).await;
            if let Err(e) = res {
                std::panic::resume_unwind(e.into_panic());
            }
        }
    }
}

/// Declares one test per backend for a scenario `async fn(JobStore, String)`.
#[macro_export]
macro_rules! both_backends {
    ($($name:ident),* $(,)?) => {
        mod sqlite {
            $(
                #[tokio::test(flavor = "multi_thread", worker_threads = 4)]
                async fn $name() {
                    $crate::common::run(precimap_jobs::Backend::Sqlite, super::$name).await;
                }
            )*
        }
        mod postgres {
            $(
                #[tokio::test(flavor = "multi_thread", worker_threads = 4)]
                async fn $name() {
                    $crate::common::run(precimap_jobs::Backend::Postgres, super::$name).await;
                }
            )*
        }
    };
}

pub fn tasks(prefix: &str, n: usize) -> Vec<NewTask> {
    (0..n).map(|i| NewTask { kind: "work".into(), key: format!("{prefix}{i:04}"), input: json!({ "i": i }) }).collect()
}

pub fn new_campaign(name: &str, queue: QueueConfig) -> NewCampaign {
    NewCampaign {
        name: name.into(),
        spec: json!({ "manifest": name }),
        params: json!({ "grid_m": 1.0 }),
        plan_state: json!({ "stage": 0 }),
        object_prefix: format!("c/{name}/"),
        iterations_planned: 2,
        strips: vec![
            StripRecord { index: 0, id: "s0".into(), trajectory: "t0".into(), uri: "s0.laz".into(), points: Some(10) },
            StripRecord { index: 1, id: "s1".into(), trajectory: "t0".into(), uri: "s1.laz".into(), points: None },
        ],
        trajectories: vec![TrajectoryRecord { index: 0, id: "t0".into(), uri: "t0.csv".into() }],
        queue,
    }
}

pub fn stage(name: &str, iteration: i32, n: usize) -> StageSpec {
    StageSpec { stage: name.into(), iteration, tasks: tasks(name, n) }
}

/// Runs stages `s0`, `s1`, … with the given task counts, then succeeds. Records every call, so a
/// test can check the barrier fired exactly once per stage.
pub struct ChainPlanner {
    pub sizes: Vec<usize>,
    pub calls: Mutex<Vec<(String, i32, usize)>>,
}

impl ChainPlanner {
    pub fn new(sizes: &[usize]) -> Self {
        ChainPlanner { sizes: sizes.to_vec(), calls: Mutex::new(Vec::new()) }
    }

    pub fn first(&self) -> StageSpec {
        stage("s0", 0, self.sizes[0])
    }

    pub fn calls(&self) -> Vec<(String, i32, usize)> {
        self.calls.lock().unwrap().clone()
    }
}

impl StagePlanner for ChainPlanner {
    fn plan(&self, campaign: &CampaignRecord, finished: &FinishedStage) -> Result<Transition, String> {
        self.calls.lock().unwrap().push((finished.stage.clone(), finished.iteration, finished.tasks.len()));
        let i: usize = finished.stage.trim_start_matches('s').parse().map_err(|_| "bad stage".to_string())?;
        let tiles = if i == 0 {
            vec![TileRecord { key: "1_2".into(), strips: vec!["s0".into(), "s1".into()], points: 42 }]
        } else {
            Vec::new()
        };
        let iteration =
            (i > 0).then(|| IterationRecord { iteration: i as i32, stats: json!({ "tasks": finished.tasks.len() }) });
        let next = match self.sizes.get(i + 1) {
            Some(&n) => Next::Stage(stage(&format!("s{}", i + 1), i as i32 + 1, n)),
            None => Next::Succeed,
        };
        let seen = campaign.plan_state.get("seen").and_then(|v| v.as_u64()).unwrap_or(0);
        Ok(Transition { plan_state: json!({ "stage": i + 1, "seen": seen + 1 }), tiles, iteration, next })
    }
}

/// A planner that always refuses.
pub struct FailingPlanner;

impl StagePlanner for FailingPlanner {
    fn plan(&self, _: &CampaignRecord, _: &FinishedStage) -> Result<Transition, String> {
        Err("no tile has points: check the manifest's CRS".into())
    }
}

pub fn outcome(task: &ClaimedTask) -> TaskOutcome {
    TaskOutcome {
        result: json!({ "key": task.key }),
        outputs: vec![OutputKey {
            name: "out".into(),
            object_key: format!("c/{}/{}/{}.{}.bin", task.campaign, task.stage, task.key, task.lease_token),
        }],
    }
}
