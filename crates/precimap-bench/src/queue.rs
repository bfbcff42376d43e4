//! `precimap bench queue`: the job store's claim + complete cycles with N concurrent claimers on
//! SQLite and PostgreSQL, and the framework's overhead against the in-process driver.

use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};
use serde_json::json;
use sqlx::Connection;
use uuid::Uuid;

use crate::overhead::{measure_overhead, FrameworkOverhead};
use crate::system::{percentile, process_cpu_ms};
use crate::{BenchError, Progress};
use precimap_jobs::{
    with_database, Backend, CampaignRecord, ClaimedTask, FinishedStage, JobError, JobStore, NewCampaign, NewTask, Next,
    OutputKey, QueueConfig, StagePlanner, StageSpec, StoreOptions, TaskOutcome, Transition,
};
use std::path::Path;

/// Figures of one run of [`queue_bench`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct QueueBenchFigures {
    pub backend: Backend,
    pub claimers: usize,
    pub tasks: usize,
    pub durable_commits: bool,
    /// Claims too wait for their WAL flush ([`StoreOptions::durable_claims`]).
    pub durable_claims: bool,
    /// Each completion claims the next task in its own transaction
    /// ([`JobStore::complete_and_claim`]); otherwise a separate claim follows every completion.
    #[serde(default)]
    pub combined: bool,
    pub seconds: f64,
    /// Claim + complete cycles per second (all claimers together).
    pub cycles_per_s: f64,
    /// Latency of getting a task: a claim, or with `combined` the combined call that returned the
    /// next task (the time between finishing one task and holding the next).
    pub claim_p50_ms: f64,
    pub claim_p99_ms: f64,
    pub complete_p50_ms: f64,
    pub complete_p99_ms: f64,
    /// CPU time of this process (claimers, driver, and SQLite itself) per cycle, in ms (Linux).
    pub client_cpu_ms_per_cycle: Option<f64>,
    /// CPU time of the PostgreSQL backends serving the claimers per cycle, in ms: a server on
    /// this machine only, and without background workers (WAL writer, autovacuum).
    pub server_cpu_ms_per_cycle: Option<f64>,
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

/// How [`queue_bench_with`] runs its cycles.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct QueueBenchOptions {
    /// [`StoreOptions::durable_commits`].
    pub durable_commits: bool,
    /// [`StoreOptions::durable_claims`].
    pub durable_claims: bool,
    /// Complete and claim the next task in one transaction ([`JobStore::complete_and_claim`], what
    /// the executor loops do) instead of a claim after every completion.
    pub combined: bool,
}

impl Default for QueueBenchOptions {
    fn default() -> Self {
        QueueBenchOptions { durable_commits: true, durable_claims: true, combined: true }
    }
}

/// Runs `tasks` claim + complete cycles with `claimers` concurrent claimers on a fresh campaign in
/// a fresh database: for `postgres://…` a new database on that server (dropped afterwards), for
/// `sqlite:…` a new file in the temporary directory (removed afterwards).
pub async fn queue_bench(url: &str, claimers: usize, tasks: usize) -> Result<QueueBenchFigures, JobError> {
    queue_bench_with(url, claimers, tasks, QueueBenchOptions::default()).await
}

/// [`queue_bench`] with a choice of durability and of combined or separate claims.
pub async fn queue_bench_with(
    url: &str,
    claimers: usize,
    tasks: usize,
    options: QueueBenchOptions,
) -> Result<QueueBenchFigures, JobError> {
    if url.starts_with("sqlite:") {
        let path = std::env::temp_dir().join(format!("precimap_bench_{}.db", Uuid::new_v4().simple()));
        let out = run(&format!("sqlite://{}", path.display()), claimers, tasks, options).await;
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
        let out = run(&with_database(url, &name), claimers, tasks, options).await;
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
    QueueBenchOptions { durable_commits, durable_claims, combined }: QueueBenchOptions,
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
        params: serde_json::Value::Null,
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
    // Another connection, to find the backends serving the claimers (not counted itself).
    let mut observer = match store.backend() {
        Backend::Postgres => Some(sqlx::PgConnection::connect(url).await?),
        Backend::Sqlite => None,
    };
    let server_before = match &mut observer {
        Some(conn) => backends_cpu_ms(conn).await?,
        None => None,
    };
    let client_before = process_cpu_ms("self");
    let start = Instant::now();
    let mut handles = Vec::with_capacity(claimers);
    for w in 0..claimers {
        let store = store.clone();
        handles.push(tokio::spawn(async move {
            let worker = format!("bench-{w}");
            let lease = Duration::from_secs(60);
            let (mut claim_ms, mut complete_ms) = (Vec::new(), Vec::new());
            let mut held: Option<ClaimedTask> = None;
            loop {
                let task = match held.take() {
                    Some(task) => task,
                    None => {
                        let t0 = Instant::now();
                        let Some(task) = store.claim(&worker, lease).await? else {
                            if store.campaign(id).await?.is_none_or(|c| c.state.is_finished()) {
                                break;
                            }
                            // The last tasks are held by other claimers.
                            tokio::time::sleep(Duration::from_millis(1)).await;
                            continue;
                        };
                        claim_ms.push(t0.elapsed().as_secs_f64() * 1e3);
                        task
                    }
                };
                let outcome = TaskOutcome {
                    result: json!({ "ok": true }),
                    outputs: vec![OutputKey {
                        name: "out".into(),
                        object_key: format!("bench/{}.{}", task.key, task.lease_token),
                    }],
                };
                let t1 = Instant::now();
                if combined {
                    let (_, next) = store.complete_and_claim(&task, outcome, &OneStage, &worker, lease).await?;
                    let ms = t1.elapsed().as_secs_f64() * 1e3;
                    complete_ms.push(ms);
                    if next.is_some() {
                        claim_ms.push(ms);
                    }
                    held = next;
                } else {
                    store.complete(&task, outcome, &OneStage).await?;
                    complete_ms.push(t1.elapsed().as_secs_f64() * 1e3);
                }
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
    let client_cpu_ms_per_cycle = process_cpu_ms("self").zip(client_before).map(|(b, a)| (b - a) / cycles);
    let server_cpu_ms_per_cycle = match observer {
        Some(mut conn) => {
            let after = backends_cpu_ms(&mut conn).await?;
            conn.close().await?;
            // A backend that connected during the run counts from zero.
            after.zip(server_before).map(|(after, before)| {
                after.iter().map(|(pid, ms)| ms - before.get(pid).copied().unwrap_or(0.0)).sum::<f64>() / cycles
            })
        }
        None => None,
    };
    let backend = store.backend();
    store.close().await;
    Ok(QueueBenchFigures {
        backend,
        claimers,
        tasks,
        durable_commits,
        durable_claims,
        combined,
        seconds,
        cycles_per_s: cycles / seconds,
        claim_p50_ms: percentile(&mut claim_ms, 0.50),
        claim_p99_ms: percentile(&mut claim_ms, 0.99),
        complete_p50_ms: percentile(&mut complete_ms, 0.50),
        complete_p99_ms: percentile(&mut complete_ms, 0.99),
        client_cpu_ms_per_cycle,
        server_cpu_ms_per_cycle,
    })
}

/// CPU time in ms of every other backend connected to the observer's database, by pid; `None`
/// unless all of them can be read (a server on this machine).
async fn backends_cpu_ms(
    observer: &mut sqlx::PgConnection,
) -> Result<Option<std::collections::HashMap<i32, f64>>, JobError> {
    let pids: Vec<i32> = sqlx::query_scalar(
        "SELECT pid FROM pg_stat_activity WHERE datname = current_database() AND pid <> pg_backend_pid()",
    )
    .fetch_all(&mut *observer)
    .await?;
    Ok(pids.into_iter().map(|pid| process_cpu_ms(&pid.to_string()).map(|ms| (pid, ms))).collect())
}

/// What `precimap bench queue` measures.
#[derive(Clone, Debug)]
pub struct QueueRequest<'a> {
    /// PostgreSQL server to benchmark on (a fresh database is created and dropped).
    pub postgres: &'a str,
    /// Claim + complete cycles per measurement.
    pub tasks: usize,
    pub options: QueueBenchOptions,
    /// The framework's overhead on a simulated campaign of this scale, over this many pairs of
    /// runs; `None` skips it.
    pub overhead: Option<(precimap_sim::Scale, usize)>,
    /// Where the overhead's campaign is cached between runs.
    pub cache: &'a Path,
}

#[derive(Debug, Serialize)]
pub struct QueueBench {
    pub sqlite: Vec<QueueBenchFigures>,
    pub postgres: Vec<QueueBenchFigures>,
    pub postgres_16_cycles_per_s: f64,
    pub postgres_16_claim_p99_ms: f64,
    pub overhead: Option<FrameworkOverhead>,
}

/// Queue figures with 1, 4 and 16 claimers on SQLite and on PostgreSQL, then the framework's
/// overhead; each measurement's line goes to `progress`.
pub fn bench_queue(request: &QueueRequest<'_>, progress: Progress<'_>) -> Result<QueueBench, BenchError> {
    let rt = tokio::runtime::Runtime::new()?;
    let (mut sqlite, mut pg) = (Vec::new(), Vec::new());
    for claimers in [1, 4, 16] {
        let f = rt.block_on(queue_bench_with("sqlite://", claimers, request.tasks, request.options))?;
        progress(&format!("sqlite     {claimers:>2} claimers: {}", f.text()));
        sqlite.push(f);
        let f = rt
            .block_on(queue_bench_with(request.postgres, claimers, request.tasks, request.options))
            .map_err(|source| BenchError::Postgres { url: request.postgres.to_string(), source })?;
        progress(&format!("postgresql {claimers:>2} claimers: {}", f.text()));
        pg.push(f);
    }
    let overhead = match request.overhead {
        None => None,
        Some((scale, runs)) => Some(measure_overhead(&rt, request.cache, scale, runs, progress)?),
    };
    let last = pg.last().cloned();
    Ok(QueueBench {
        postgres_16_cycles_per_s: last.as_ref().map_or(0.0, |f| f.cycles_per_s),
        postgres_16_claim_p99_ms: last.as_ref().map_or(0.0, |f| f.claim_p99_ms),
        sqlite,
        postgres: pg,
        overhead,
    })
}

impl QueueBenchFigures {
    /// One line: cycles/s, claim and completion latency, CPU per cycle.
    pub fn text(&self) -> String {
        let ms = |v: Option<f64>| v.map_or("n/a".to_string(), |v| format!("{v:.3} ms"));
        format!(
            "{:>7.0} cycles/s, claim p50 {:.2} ms, p99 {:.2} ms, completion p99 {:.2} ms, CPU per cycle: client {}, \
             server {}",
            self.cycles_per_s,
            self.claim_p50_ms,
            self.claim_p99_ms,
            self.complete_p99_ms,
            ms(self.client_cpu_ms_per_cycle),
            ms(self.server_cpu_ms_per_cycle)
        )
    }
}
