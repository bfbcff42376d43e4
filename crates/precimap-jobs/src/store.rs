//! The job store: campaigns, tasks and their leases in SQLite or PostgreSQL.
//!
//! Every operation is written once and expanded for both backends by `with_pool!`/`with_tx!`;
//! the SQL differs only where the dialects do (clock, row locks, data-modifying CTEs).
//!
//! Locking discipline (PostgreSQL): every transaction that changes more than one row of a
//! campaign first locks the campaign row (`FOR NO KEY UPDATE`, which does not block the foreign-key
//! checks of concurrent inserts), then touches tasks. `claim`, `heartbeat` and the commit of
//! `complete` touch one task row only (plus rows they insert) and never wait for a campaign lock,
//! so no cycle of waits can form, and completions of one campaign do not queue behind each other;
//! only the completion that finds its stage closed takes the campaign lock, to advance it.
//! `complete_and_claim` adds a second task row to the commit of `complete`, taken with `SKIP
//! LOCKED` after the first, so it never waits for it. SQLite serialises all writers with
//! `BEGIN IMMEDIATE`.

use std::collections::HashMap;
use std::str::FromStr;
use std::time::Duration;

use serde_json::Value;
use sqlx::postgres::{PgConnectOptions, PgPool, PgPoolOptions};
use sqlx::sqlite::{SqliteConnectOptions, SqliteJournalMode, SqlitePool, SqlitePoolOptions, SqliteSynchronous};
use sqlx::types::Json;
use sqlx::{QueryBuilder, Row};
use tracing::{debug, info, warn};
use uuid::Uuid;

use crate::error::JobError;
use crate::migrations::{self, Embedded};
use crate::types::*;

/// Rows per multi-row INSERT (well below both backends' bind-parameter limits).
const INSERT_CHUNK: usize = 500;

const SQLITE_NOW: &str = "CAST((julianday('now') - 2440587.5) * 86400000.0 AS INTEGER)";
const PG_NOW: &str = "(extract(epoch from clock_timestamp()) * 1000)::bigint";

/// An open (queued or leased) task of a stage, if any: `$1` campaign, `$2` stage, `$3` iteration.
/// Served by the partial index `tasks_open` whatever the statistics say (a sequential or primary-key
/// scan would have to sort or wade through the stage's done tasks, which planners underestimate),
/// newest first: completions happen roughly in id order, so the index entries of tasks that are
/// done (dead until vacuumed) pile up at the low end.
const STAGE_OPEN: &str = "SELECT id FROM tasks WHERE campaign = $1 AND stage = $2 AND iteration = $3 \
     AND state IN ('queued', 'leased') ORDER BY id DESC LIMIT 1";

const CAMPAIGN_COLS: &str = "id, name, state, stage, iteration, iterations_planned, spec, plan_state, \
     object_prefix, error, max_attempts, backoff_base_ms, backoff_max_ms, created_at_ms, updated_at_ms, finished_at_ms";

#[derive(Debug, Clone)]
enum Pool {
    Sqlite(SqlitePool),
    Postgres(PgPool),
}

/// Connection settings of [`JobStore::connect_with`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StoreOptions {
    /// PostgreSQL pool size (SQLite always uses one connection, see `connect_with`).
    pub max_connections: u32,
    /// How long to wait for a connection (including retries while the server is unreachable).
    pub acquire_timeout: Duration,
    /// PostgreSQL: wait for the WAL flush at every commit (`synchronous_commit`). Turning it off
    /// keeps the queue correct (a server crash loses a suffix of the last commits, whose tasks
    /// are then run again: execution is at-least-once and the commit point makes re-runs
    /// harmless) and removes one fsync from every claim and completion.
    pub durable_commits: bool,
    /// PostgreSQL, with `durable_commits`: also wait for the WAL flush when committing a claim.
    /// Without it a claim commits asynchronously (the completions, failures and transitions that
    /// follow still wait for theirs, and each flush covers every earlier commit). A server crash
    /// can then forget the last claims: their tasks are queued again and their executors get
    /// `LeaseLost` at the next heartbeat or completion, as after a rescued lease, so no completion
    /// is lost or recorded twice; it halves the flushes per claim + complete cycle.
    pub durable_claims: bool,
}

impl Default for StoreOptions {
    fn default() -> Self {
        StoreOptions {
            max_connections: 16,
            acquire_timeout: Duration::from_secs(30),
            durable_commits: true,
            durable_claims: true,
        }
    }
}

/// Handle to the job store (cheap to clone: it shares one connection pool).
#[derive(Debug, Clone)]
pub struct JobStore {
    pool: Pool,
    /// PostgreSQL: claims commit without waiting for the WAL flush (`StoreOptions::durable_claims`).
    async_claims: bool,
}

/// Runs `$body` with `$p` bound to the backend's pool.
macro_rules! with_pool {
    ($self:ident, $p:ident => $body:expr) => {
        match &$self.pool {
            Pool::Sqlite($p) => $body,
            Pool::Postgres($p) => $body,
        }
    };
}

/// Runs `$body` inside a write transaction `$tx` and commits it; an early return (`?`,
/// `return Err(..)`) drops the transaction, which rolls it back.
macro_rules! with_tx {
    ($self:ident, $tx:ident => $body:expr) => {
        match &$self.pool {
            Pool::Sqlite(p) => {
                // IMMEDIATE takes the write lock up front, so two writers never both read and then
                // fail to upgrade (SQLite's deadlock-free serialisation of writers).
                let mut $tx = p.begin_with("BEGIN IMMEDIATE").await?;
                let out = $body;
                $tx.commit().await?;
                out
            }
            Pool::Postgres(p) => {
                let mut $tx = p.begin().await?;
                let out = $body;
                $tx.commit().await?;
                out
            }
        }
    };
}

/// Columns of [`CampaignProgress`], a prefix of [`CAMPAIGN_COLS`] in content.
const PROGRESS_COLS: &str = "id, name, state, stage, iteration, iterations_planned, error";

/// A row with at least [`PROGRESS_COLS`] → [`CampaignProgress`].
macro_rules! progress_from_row {
    ($row:expr) => {{
        let r = &$row;
        let state: String = r.try_get("state")?;
        CampaignProgress {
            id: r.try_get("id")?,
            name: r.try_get("name")?,
            state: CampaignState::parse(&state)
                .ok_or_else(|| JobError::Corrupt(format!("campaign state `{state}`")))?,
            stage: r.try_get("stage")?,
            iteration: r.try_get("iteration")?,
            iterations_planned: r.try_get("iterations_planned")?,
            error: r.try_get("error")?,
        }
    }};
}

macro_rules! campaign_from_row {
    ($row:expr) => {{
        let r = &$row;
        let CampaignProgress { id, name, state, stage, iteration, iterations_planned, error } = progress_from_row!(r);
        CampaignRecord {
            id,
            name,
            state,
            stage,
            iteration,
            iterations_planned,
            spec: r.try_get::<Json<Value>, _>("spec")?.0,
            plan_state: r.try_get::<Json<Value>, _>("plan_state")?.0,
            object_prefix: r.try_get("object_prefix")?,
            error,
            queue: QueueConfig {
                max_attempts: r.try_get("max_attempts")?,
                backoff_base: ms_duration(r.try_get("backoff_base_ms")?),
                backoff_max: ms_duration(r.try_get("backoff_max_ms")?),
            },
            created_at_ms: r.try_get("created_at_ms")?,
            updated_at_ms: r.try_get("updated_at_ms")?,
            finished_at_ms: r.try_get("finished_at_ms")?,
        }
    }};
}

/// Inserts an event row.
macro_rules! event {
    ($self:ident, $tx:ident, $campaign:expr, $kind:expr, $task:expr, $msg:expr) => {{
        let q =
            $self.sql("INSERT INTO events (campaign, at_ms, kind, task_id, message) VALUES ($1, NOW_MS, $2, $3, $4)");
        sqlx::query(&q).bind($campaign).bind($kind).bind($task).bind($msg).execute(&mut *$tx).await?;
    }};
}

/// SQLite: runs the claim statement `$q` in the write transaction `$tx` and records its event.
macro_rules! lite_claim {
    ($self:ident, $tx:ident, $q:expr, $token:expr, $lease_ms:expr, $worker:expr) => {{
        let worker: &str = $worker;
        let row: Option<ClaimRow> =
            sqlx::query_as($q).bind($token).bind($lease_ms).bind(worker).fetch_optional(&mut *$tx).await?;
        if let Some(r) = &row {
            let msg = format!("{} {} attempt {} by {worker}", r.4, r.5, r.7);
            event!($self, $tx, r.1, "claimed", Some(r.0), &msg);
        }
        row
    }};
}

/// Marks a (running) campaign failed with `$msg` and cancels its open tasks.
macro_rules! fail_campaign {
    ($self:ident, $tx:ident, $campaign:expr, $msg:expr) => {{
        let msg: &str = $msg;
        let q = $self.sql(
            "UPDATE tasks SET state = 'cancelled', error = 'campaign failed', updated_at_ms = NOW_MS, \
             finished_at_ms = NOW_MS WHERE campaign = $1 AND state IN ('queued', 'leased')",
        );
        sqlx::query(&q).bind($campaign).execute(&mut *$tx).await?;
        let q = $self.sql(
            "UPDATE campaigns SET state = 'failed', error = $2, updated_at_ms = NOW_MS, finished_at_ms = NOW_MS \
             WHERE id = $1",
        );
        sqlx::query(&q).bind($campaign).bind(msg).execute(&mut *$tx).await?;
        event!($self, $tx, $campaign, "failed", None::<i64>, msg);
        warn!(campaign = %$campaign, error = msg, "campaign failed");
    }};
}

/// Enqueues the tasks of a stage.
macro_rules! insert_tasks {
    ($self:ident, $tx:ident, $campaign:expr, $spec:expr) => {{
        let spec: &StageSpec = $spec;
        let now = $self.now_sql();
        for chunk in spec.tasks.chunks(INSERT_CHUNK) {
            let mut qb = QueryBuilder::new(
                "INSERT INTO tasks (campaign, stage, iteration, kind, key, input, state, attempt, not_before_ms, \
                 created_at_ms, updated_at_ms) ",
            );
            qb.push_values(chunk, |mut b, t| {
                b.push_bind($campaign)
                    .push_bind(spec.stage.as_str())
                    .push_bind(spec.iteration)
                    .push_bind(t.kind.as_str())
                    .push_bind(t.key.as_str())
                    .push_bind(Json(&t.input))
                    .push("'queued'")
                    .push("0")
                    .push(now)
                    .push(now)
                    .push(now);
            });
            qb.build().execute(&mut *$tx).await?;
        }
    }};
}

mod barrier;
mod campaigns;
mod complete;
mod leases;
mod lifecycle;
mod queries;
mod reconcile;

use barrier::{check_unique_tasks, Barrier};
use leases::{claimed_task, pg_claim_ctes, ClaimRow, LITE_CLAIM};

impl JobStore {
    /// Opens the store and applies the migrations.
    ///
    /// `sqlite://PATH` (file created if missing; WAL; busy timeout), `sqlite::memory:` (tests),
    /// `postgres://…` / `postgresql://…`.
    pub async fn connect(url: &str) -> Result<JobStore, JobError> {
        JobStore::connect_with(url, StoreOptions::default()).await
    }

    /// [`JobStore::connect`] with explicit pool settings.
    pub async fn connect_with(url: &str, options: StoreOptions) -> Result<JobStore, JobError> {
        let bad = |reason: String| JobError::BadUrl { url: url.to_string(), reason };
        let pool = if url.starts_with("sqlite:") {
            let opts = SqliteConnectOptions::from_str(url)
                .map_err(|e| bad(e.to_string()))?
                .create_if_missing(true)
                .journal_mode(SqliteJournalMode::Wal)
                // WAL makes NORMAL durable against application crashes; only an OS crash can
                // lose the last commits.
                .synchronous(SqliteSynchronous::Normal)
                .busy_timeout(Duration::from_secs(30))
                .foreign_keys(true)
                // A small campaign's store is ~20 MB (task inputs and results); with SQLite's
                // default 2 MB page cache a run re-read it by 1.2 M `pread`s.
                .pragma("cache_size", "-65536");
            // One connection: in-process writers queue in the pool instead of spinning in SQLite's
            // busy handler (sleeps of up to 100 ms); other processes still wait via busy_timeout.
            // Never closed while idle, so `sqlite::memory:` keeps its data.
            let pool = SqlitePoolOptions::new()
                .max_connections(1)
                .min_connections(1)
                .idle_timeout(None)
                .max_lifetime(None)
                .acquire_timeout(options.acquire_timeout)
                .connect_with(opts)
                .await?;
            Embedded(migrations::SQLITE).migrator().await?.run(&pool).await?;
            Pool::Sqlite(pool)
        } else if url.starts_with("postgres://") || url.starts_with("postgresql://") {
            let mut opts = PgConnectOptions::from_str(url).map_err(|e| bad(e.to_string()))?;
            if !options.durable_commits {
                opts = opts.options([("synchronous_commit", "off")]);
            }
            let pool = PgPoolOptions::new()
                // No ping before every use (a round trip per operation): a dead connection shows
                // up as a transient error, which callers retry anyway.
                .test_before_acquire(false)
                .max_connections(options.max_connections.max(1))
                .acquire_timeout(options.acquire_timeout)
                .connect_with(opts)
                .await?;
            // sqlx takes an advisory lock, so executors starting together migrate once.
            Embedded(migrations::POSTGRES).migrator().await?.run(&pool).await?;
            Pool::Postgres(pool)
        } else {
            return Err(bad("expected `sqlite://PATH`, `sqlite::memory:` or `postgres://…`".into()));
        };
        let async_claims = matches!(pool, Pool::Postgres(_)) && options.durable_commits && !options.durable_claims;
        Ok(JobStore { pool, async_claims })
    }

    pub fn backend(&self) -> Backend {
        match self.pool {
            Pool::Sqlite(_) => Backend::Sqlite,
            Pool::Postgres(_) => Backend::Postgres,
        }
    }

    /// Closes the pool (waits for connections in use to be returned).
    pub async fn close(&self) {
        with_pool!(self, p => p.close().await)
    }

    fn now_sql(&self) -> &'static str {
        match self.pool {
            Pool::Sqlite(_) => SQLITE_NOW,
            Pool::Postgres(_) => PG_NOW,
        }
    }

    fn is_pg(&self) -> bool {
        matches!(self.pool, Pool::Postgres(_))
    }

    /// Fills in the dialect: `NOW_MS` (database clock, ms) and `FOR_LOCK` (campaign row lock).
    fn sql(&self, s: &str) -> String {
        let lock = if self.is_pg() { "FOR NO KEY UPDATE" } else { "" };
        s.replace("NOW_MS", self.now_sql()).replace("FOR_LOCK", lock)
    }

    /// The database clock in milliseconds since the epoch.
    pub async fn now_ms(&self) -> Result<i64, JobError> {
        let q = self.sql("SELECT NOW_MS");
        Ok(with_pool!(self, p => sqlx::query_scalar::<_, i64>(&q).fetch_one(p).await?))
    }
}

fn ms_duration(ms: i64) -> Duration {
    Duration::from_millis(u64::try_from(ms).unwrap_or(0))
}

#[cfg(test)]
mod tests {
    use super::*;
    use sqlx::Connection;

    /// PostgreSQL: the `synchronous_commit = off` of an asynchronous claim ends with the claim's
    /// own transaction; the completion that follows on the same connection waits for its flush.
    #[tokio::test]
    async fn async_claim_leaves_the_connection_durable() {
        let admin = std::env::var("PRECIMAP_TEST_POSTGRES")
            .unwrap_or_else(|_| "postgres://postgres@127.0.0.1:5432/postgres".into());
        let name = format!("precimap_t_{}", Uuid::new_v4().simple());
        let mut conn = sqlx::PgConnection::connect(&admin).await.expect("connect to the test PostgreSQL server");
        sqlx::query(&format!("CREATE DATABASE {name}")).execute(&mut conn).await.unwrap();
        let url = crate::with_database(&admin, &name);
        // One connection, so every statement below runs on the claim's connection.
        let opts = StoreOptions { max_connections: 1, durable_claims: false, ..StoreOptions::default() };
        let store = JobStore::connect_with(&url, opts).await.unwrap();
        assert!(store.async_claims);
        let Pool::Postgres(pool) = &store.pool else { unreachable!() };
        let setting = || async { sqlx::query_scalar::<_, String>("SHOW synchronous_commit").fetch_one(pool).await };
        let campaign = NewCampaign {
            name: "async".into(),
            spec: Value::Null,
            params: Value::Null,
            plan_state: Value::Null,
            object_prefix: "a/".into(),
            iterations_planned: 0,
            strips: vec![],
            trajectories: vec![],
            queue: QueueConfig::default(),
        };
        let stage = StageSpec {
            stage: "s".into(),
            iteration: 0,
            tasks: vec![NewTask { kind: "k".into(), key: "a".into(), input: Value::Null }],
        };
        store.create_campaign(campaign, stage).await.unwrap();
        assert_eq!(setting().await.unwrap(), "on");
        let task = store.claim("w", Duration::from_secs(60)).await.unwrap().expect("a task");
        assert_eq!(setting().await.unwrap(), "on", "the claim's setting outlived its transaction");
        assert!(store.claim("w", Duration::from_secs(60)).await.unwrap().is_none());
        assert_eq!(setting().await.unwrap(), "on");
        store.heartbeat(&task, Duration::from_secs(60)).await.unwrap();
        store.close().await;
        let durable = JobStore::connect(&url).await.unwrap();
        assert!(!durable.async_claims, "claims are durable by default");
        durable.close().await;
        sqlx::query(&format!("DROP DATABASE IF EXISTS {name} WITH (FORCE)")).execute(&mut conn).await.unwrap();
    }
}
