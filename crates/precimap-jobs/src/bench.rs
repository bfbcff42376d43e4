//! Queue throughput benchmark: claim + complete cycles with N concurrent claimers.

use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};
use serde_json::json;
use sqlx::Connection;
use uuid::Uuid;

use crate::{
    Backend, CampaignRecord, ClaimedTask, FinishedStage, JobError, JobStore, NewCampaign, NewTask, Next, OutputKey,
    QueueConfig, StagePlanner, StageSpec, StoreOptions, TaskOutcome, Transition,
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

/// CPU time (user + system) of process `pid` (`self` for this one) in ms, from `/proc`; `None`
/// where there is no such file (another OS, a server on another machine).
fn process_cpu_ms(pid: &str) -> Option<f64> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    // Fields after the parenthesised command name start at field 3 (state); utime and stime are
    // fields 14 and 15, in clock ticks of 10 ms (USER_HZ is 100 on Linux).
    let fields: Vec<&str> = stat.get(stat.rfind(')')? + 1..)?.split_whitespace().collect();
    let ticks = fields.get(11)?.parse::<u64>().ok()? + fields.get(12)?.parse::<u64>().ok()?;
    Some(ticks as f64 * 10.0)
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
    fn own_cpu_time_is_read() {
        let before = process_cpu_ms("self").expect("/proc/self/stat");
        let mut x = 0u64;
        let t = Instant::now();
        while t.elapsed() < Duration::from_millis(100) {
            x = x.wrapping_add(std::hint::black_box(1));
        }
        assert!(x > 0);
        let spent = process_cpu_ms("self").unwrap() - before;
        // 100 ms of spinning; the tick is 10 ms and a busy machine may take CPU away from us.
        assert!((10.0..=1000.0).contains(&spent), "{spent} ms");
        assert_eq!(process_cpu_ms("0"), None);
    }

    #[test]
    fn percentiles() {
        let mut v: Vec<f64> = (1..=100).map(f64::from).collect();
        assert_eq!(percentile(&mut v, 0.5), 51.0);
        assert_eq!(percentile(&mut v, 0.99), 99.0);
        assert!(percentile(&mut [], 0.5).is_nan());
    }
}
