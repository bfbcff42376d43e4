//! Queue throughput benchmark: claim + complete cycles with N concurrent claimers.

use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};
use serde_json::json;
use sqlx::Connection;
use uuid::Uuid;

use crate::{
    Backend, CampaignRecord, FinishedStage, JobError, JobStore, NewCampaign, NewTask, Next, OutputKey, QueueConfig,
    StagePlanner, StageSpec, StoreOptions, TaskOutcome, Transition,
};

/// Figures of one run of [`queue_bench`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct QueueBenchFigures {
    pub backend: Backend,
    pub claimers: usize,
    pub tasks: usize,
    pub durable_commits: bool,
    /// Claims too wait for their WAL flush ([`StoreOptions::durable_claims`]).
    pub durable_claims: bool,
    pub seconds: f64,
    /// Claim + complete cycles per second (all claimers together).
    pub cycles_per_s: f64,
    pub claim_p50_ms: f64,
    pub claim_p99_ms: f64,
    pub complete_p50_ms: f64,
    pub complete_p99_ms: f64,
}

/// One stage, then success.
struct OneStage;

impl StagePlanner for OneStage {
    fn plan(&self, _: &CampaignRecord, finished: &FinishedStage) -> Result<Transition, String> {
        Ok(Transition {
            plan_state: json!({ "tasks": finished.tasks.len() }),
            tiles: vec![],
            iteration: None,
            next: Next::Succeed,
        })
    }
}

/// Runs `tasks` claim + complete cycles with `claimers` concurrent claimers on a fresh campaign in
/// a fresh database: for `postgres://…` a new database on that server (dropped afterwards), for
/// `sqlite:…` a new file in the temporary directory (removed afterwards).
pub async fn queue_bench(url: &str, claimers: usize, tasks: usize) -> Result<QueueBenchFigures, JobError> {
    queue_bench_with(url, claimers, tasks, true, true).await
}

/// [`queue_bench`] with a choice of [`StoreOptions::durable_commits`] and
/// [`StoreOptions::durable_claims`].
pub async fn queue_bench_with(
    url: &str,
    claimers: usize,
    tasks: usize,
    durable_commits: bool,
    durable_claims: bool,
) -> Result<QueueBenchFigures, JobError> {
    let durability = (durable_commits, durable_claims);
    if url.starts_with("sqlite:") {
        let path = std::env::temp_dir().join(format!("precimap_bench_{}.db", Uuid::new_v4().simple()));
        let out = run(&format!("sqlite://{}", path.display()), claimers, tasks, durability).await;
        for suffix in ["", "-wal", "-shm"] {
            let mut p = path.clone().into_os_string();
            p.push(suffix);
            // Best effort: a file SQLite did not create is simply absent.
            let _ = std::fs::remove_file(p);
        }
        out
    } else if url.starts_with("postgres://") || url.starts_with("postgresql://") {
        let name = format!("precimap_b_{}", Uuid::new_v4().simple());
        let mut admin = sqlx::PgConnection::connect(url).await?;
        sqlx::query(&format!("CREATE DATABASE {name}")).execute(&mut admin).await?;
        let out = run(&with_database(url, &name), claimers, tasks, durability).await;
        sqlx::query(&format!("DROP DATABASE IF EXISTS {name} WITH (FORCE)")).execute(&mut admin).await?;
        admin.close().await?;
        out
    } else {
        Err(JobError::BadUrl { url: url.into(), reason: "expected sqlite:… or postgres://…".into() })
    }
}

async fn run(
    url: &str,
    claimers: usize,
    tasks: usize,
    (durable_commits, durable_claims): (bool, bool),
) -> Result<QueueBenchFigures, JobError> {
    let claimers = claimers.max(1);
    let opts = StoreOptions {
        max_connections: (claimers as u32).max(2),
        durable_commits,
        durable_claims,
        ..StoreOptions::default()
    };
    let store = JobStore::connect_with(url, opts).await?;
    let campaign = NewCampaign {
        name: "queue-bench".into(),
        spec: json!({}),
        plan_state: json!({}),
        object_prefix: "bench/".into(),
        iterations_planned: 0,
        strips: vec![],
        trajectories: vec![],
        queue: QueueConfig::default(),
    };
    let stage = StageSpec {
        stage: "bench".into(),
        iteration: 0,
        tasks: (0..tasks)
            .map(|i| NewTask { kind: "noop".into(), key: format!("{i:07}"), input: json!({ "i": i }) })
            .collect(),
    };
    let id = store.create_campaign(campaign, stage).await?;
    let start = Instant::now();
    let mut handles = Vec::with_capacity(claimers);
    for w in 0..claimers {
        let store = store.clone();
        handles.push(tokio::spawn(async move {
            let worker = format!("bench-{w}");
            let (mut claim_ms, mut complete_ms) = (Vec::new(), Vec::new());
            loop {
                let t0 = Instant::now();
                let Some(task) = store.claim(&worker, Duration::from_secs(60)).await? else {
                    if store.campaign(id).await?.is_none_or(|c| c.state.is_finished()) {
                        break;
                    }
                    // The last tasks are held by other claimers.
                    tokio::time::sleep(Duration::from_millis(1)).await;
                    continue;
                };
                claim_ms.push(t0.elapsed().as_secs_f64() * 1e3);
                let outcome = TaskOutcome {
                    result: json!({ "ok": true }),
                    outputs: vec![OutputKey {
                        name: "out".into(),
                        object_key: format!("bench/{}.{}", task.key, task.lease_token),
                    }],
                };
                let t1 = Instant::now();
                store.complete(&task, outcome, &OneStage).await?;
                complete_ms.push(t1.elapsed().as_secs_f64() * 1e3);
            }
            Ok::<_, JobError>((claim_ms, complete_ms))
        }));
    }
    let (mut claim_ms, mut complete_ms) = (Vec::new(), Vec::new());
    for h in handles {
        let (c, d) = h.await.map_err(|e| JobError::Invalid(format!("bench claimer panicked: {e}")))??;
        claim_ms.extend(c);
        complete_ms.extend(d);
    }
    let seconds = start.elapsed().as_secs_f64();
    let cycles = complete_ms.len() as f64;
    let backend = store.backend();
    store.close().await;
    Ok(QueueBenchFigures {
        backend,
        claimers,
        tasks,
        durable_commits,
        durable_claims,
        seconds,
        cycles_per_s: cycles / seconds,
        claim_p50_ms: percentile(&mut claim_ms, 0.50),
        claim_p99_ms: percentile(&mut claim_ms, 0.99),
        complete_p50_ms: percentile(&mut complete_ms, 0.50),
        complete_p99_ms: percentile(&mut complete_ms, 0.99),
    })
}

fn percentile(v: &mut [f64], q: f64) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * q).round() as usize]
}

/// `url` with its database name replaced by `db` (query string kept).
pub fn with_database(url: &str, db: &str) -> String {
    let (base, query) = match url.split_once('?') {
        Some((b, q)) => (b, Some(q)),
        None => (url, None),
    };
    let authority = base.find("://").map(|i| i + 3).unwrap_or(0);
    let server = match base[authority..].find('/') {
        Some(i) => &base[..authority + i],
        None => base,
    };
    match query {
        Some(q) => format!("{server}/{db}?{q}"),
        None => format!("{server}/{db}"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn database_name_is_replaced() {
        assert_eq!(with_database("postgres://u@h:5432/postgres", "x"), "postgres://u@h:5432/x");
        assert_eq!(with_database("postgres://u@h/postgres?sslmode=disable", "x"), "postgres://u@h/x?sslmode=disable");
        assert_eq!(with_database("postgres://u@h", "x"), "postgres://u@h/x");
    }

    #[test]
    fn percentiles() {
        let mut v: Vec<f64> = (1..=100).map(f64::from).collect();
        assert_eq!(percentile(&mut v, 0.5), 51.0);
        assert_eq!(percentile(&mut v, 0.99), 99.0);
        assert!(percentile(&mut [], 0.5).is_nan());
    }
}
