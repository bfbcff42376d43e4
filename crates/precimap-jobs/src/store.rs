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
/// Planned stages without tasks in a row before the planner is considered stuck.
const MAX_EMPTY_STAGES: usize = 64;

const SQLITE_NOW: &str = "CAST((julianday('now') - 2440587.5) * 86400000.0 AS INTEGER)";
const PG_NOW: &str = "(extract(epoch from clock_timestamp()) * 1000)::bigint";

/// An open (queued or leased) task of a stage, if any: `$1` campaign, `$2` stage, `$3` iteration.
/// Served by the partial index `tasks_open` whatever the statistics say (a sequential or primary-key
/// scan would have to sort or wade through the stage's done tasks, which planners underestimate),
/// newest first: completions happen roughly in id order, so the index entries of tasks that are
/// done (dead until vacuumed) pile up at the low end.
const STAGE_OPEN: &str = "SELECT id FROM tasks WHERE campaign = $1 AND stage = $2 AND iteration = $3 \
     AND state IN ('queued', 'leased') ORDER BY id DESC LIMIT 1";

/// SQLite: claims the oldest runnable task (`$1` lease token, `$2` lease in ms, `$3` worker).
const LITE_CLAIM: &str = "UPDATE tasks SET state = 'leased', attempt = attempt + 1, lease_token = $1, \
       lease_expires_at_ms = NOW_MS + $2, worker = $3, updated_at_ms = NOW_MS \
     WHERE id = (SELECT t.id FROM tasks t JOIN campaigns c ON c.id = t.campaign \
       WHERE t.state = 'queued' AND t.not_before_ms <= NOW_MS AND c.state = 'running' \
       ORDER BY t.id LIMIT 1) \
     RETURNING id, campaign, stage, iteration, kind, key, input, attempt, lease_token, lease_expires_at_ms";

/// PostgreSQL: the CTEs `next`, `claimed` and `claimed_ev` that claim the oldest runnable task
/// if `guard` holds, with the lease token in parameter `$first`, the lease in ms in the next one
/// and the worker in the one after.
fn pg_claim_ctes(first: usize, guard: &str) -> String {
    let (token, lease, worker) = (first, first + 1, first + 2);
    format!(
        "next AS ( \
           SELECT t.id FROM tasks t JOIN campaigns c ON c.id = t.campaign \
           WHERE {guard} AND t.state = 'queued' AND t.not_before_ms <= NOW_MS AND c.state = 'running' \
           ORDER BY t.id LIMIT 1 FOR UPDATE OF t SKIP LOCKED), \
         claimed AS ( \
           UPDATE tasks t SET state = 'leased', attempt = t.attempt + 1, lease_token = ${token}, \
             lease_expires_at_ms = NOW_MS + ${lease}, worker = ${worker}, updated_at_ms = NOW_MS \
           FROM next WHERE t.id = next.id \
           RETURNING t.id, t.campaign, t.stage, t.iteration, t.kind, t.key, t.input, t.attempt, \
             t.lease_token, t.lease_expires_at_ms), \
         claimed_ev AS ( \
           INSERT INTO events (campaign, at_ms, kind, task_id, message) \
           SELECT campaign, NOW_MS, 'claimed', id, kind || ' ' || key || ' attempt ' || attempt || \
             ' by ' || ${worker} FROM claimed)"
    )
}

/// PostgreSQL: the guarded completion of `complete` as CTEs `d` (the task row: `$1` id, `$2`
/// lease token, `$3` result), `outs` (`$4` the outputs as a JSON array) and `ev`.
const PG_DONE_CTES: &str = "d AS ( \
       UPDATE tasks t SET state = 'done', result = $3, updated_at_ms = NOW_MS, finished_at_ms = NOW_MS \
       FROM campaigns c \
       WHERE t.id = $1 AND t.lease_token = $2 AND t.state = 'leased' AND c.id = t.campaign \
         AND c.state = 'running' AND c.stage = t.stage AND c.iteration = t.iteration \
       RETURNING t.id, t.campaign, t.kind, t.key, t.attempt), \
     outs AS ( \
       INSERT INTO task_outputs (task_id, campaign, name, object_key) \
       SELECT d.id, d.campaign, o.name, o.object_key \
       FROM d, jsonb_to_recordset($4) AS o(name text, object_key text)), \
     ev AS ( \
       INSERT INTO events (campaign, at_ms, kind, task_id, message) \
       SELECT campaign, NOW_MS, 'done', id, kind || ' ' || key || ' done (attempt ' || attempt || ')' FROM d)";

/// SQLite: the guarded completion (`$1` id, `$2` lease token, `$3` result).
const LITE_DONE: &str =
    "UPDATE tasks SET state = 'done', result = $3, updated_at_ms = NOW_MS, finished_at_ms = NOW_MS \
     WHERE id = $1 AND lease_token = $2 AND state = 'leased' AND EXISTS (SELECT 1 FROM campaigns c \
       WHERE c.id = tasks.campaign AND c.state = 'running' AND c.stage = tasks.stage \
       AND c.iteration = tasks.iteration)";

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

/// What [`JobStore::advance_stage`] did.
#[derive(Debug, Clone, Copy)]
struct Barrier {
    /// This call closed the stage and applied the planner's transition.
    advanced: bool,
    /// The campaign's state afterwards.
    state: CampaignState,
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

    pub async fn create_campaign(&self, c: NewCampaign, first: StageSpec) -> Result<Uuid, JobError> {
        if c.queue.max_attempts < 1 {
            return Err(JobError::Invalid(format!("max_attempts must be ≥ 1, got {}", c.queue.max_attempts)));
        }
        if first.tasks.is_empty() {
            return Err(JobError::Invalid(format!("first stage `{}` has no tasks", first.stage)));
        }
        check_unique_tasks(&first).map_err(JobError::Invalid)?;
        let id = Uuid::new_v4();
        let q = self.sql(&format!(
            "INSERT INTO campaigns ({CAMPAIGN_COLS}, params) VALUES ($1, $2, 'running', $3, $4, $5, $6, $7, $8, NULL, \
             $9, $10, $11, NOW_MS, NOW_MS, NULL, $12)"
        ));
        let params = (!c.params.is_null()).then_some(Json(&c.params));
        with_tx!(self, tx => {
            sqlx::query(&q)
                .bind(id)
                .bind(&c.name)
                .bind(&first.stage)
                .bind(first.iteration)
                .bind(c.iterations_planned)
                .bind(Json(&c.spec))
                .bind(Json(&c.plan_state))
                .bind(&c.object_prefix)
                .bind(c.queue.max_attempts)
                .bind(duration_ms(c.queue.backoff_base))
                .bind(duration_ms(c.queue.backoff_max))
                .bind(params)
                .execute(&mut *tx)
                .await?;
            for chunk in c.strips.chunks(INSERT_CHUNK) {
                let mut qb = QueryBuilder::new("INSERT INTO strips (campaign, idx, id, trajectory, uri, points) ");
                qb.push_values(chunk, |mut b, s| {
                    b.push_bind(id).push_bind(s.index).push_bind(s.id.as_str()).push_bind(s.trajectory.as_str())
                        .push_bind(s.uri.as_str()).push_bind(s.points);
                });
                qb.build().execute(&mut *tx).await?;
            }
            for chunk in c.trajectories.chunks(INSERT_CHUNK) {
                let mut qb = QueryBuilder::new("INSERT INTO trajectories (campaign, idx, id, uri) ");
                qb.push_values(chunk, |mut b, t| {
                    b.push_bind(id).push_bind(t.index).push_bind(t.id.as_str()).push_bind(t.uri.as_str());
                });
                qb.build().execute(&mut *tx).await?;
            }
            insert_tasks!(self, tx, id, &first);
            let msg = format!("campaign `{}` created; stage {} iteration {}: {} tasks", c.name, first.stage,
                first.iteration, first.tasks.len());
            event!(self, tx, id, "campaign_created", None::<i64>, &msg);
        });
        if self.is_pg() {
            // Fresh statistics: a planner that believes the queue is tiny claims by sorting a bitmap
            // scan (measured 3 ms per claim instead of 0.35 ms on 5,000 new tasks).
            with_pool!(self, p => sqlx::query("ANALYZE tasks").execute(p).await.map(|_| ())?);
        }
        info!(campaign = %id, name = %c.name, stage = %first.stage, tasks = first.tasks.len(), "campaign created");
        Ok(id)
    }

    pub async fn campaign(&self, id: Uuid) -> Result<Option<CampaignRecord>, JobError> {
        let q = format!("SELECT {CAMPAIGN_COLS} FROM campaigns WHERE id = $1");
        with_pool!(self, p => {
            match sqlx::query(&q).bind(id).fetch_optional(p).await? {
                Some(row) => Ok(Some(campaign_from_row!(row))),
                None => Ok(None),
            }
        })
    }

    /// What a progress display polls: the campaign's state and position without its spec and
    /// plan state (JSON that grows with the campaign: on medium the plan state lists every tile's
    /// chunks, and decoding it several times a second cost the embedded runner CPU its executors
    /// could have used).
    pub async fn campaign_progress(&self, id: Uuid) -> Result<Option<CampaignProgress>, JobError> {
        let q = format!("SELECT {PROGRESS_COLS} FROM campaigns WHERE id = $1");
        with_pool!(self, p => {
            match sqlx::query(&q).bind(id).fetch_optional(p).await? {
                Some(row) => Ok(Some(progress_from_row!(row))),
                None => Ok(None),
            }
        })
    }

    /// Task counts by state of one stage (served by the prefix of the unique index on
    /// `(campaign, stage, iteration, kind, key)`: no scan of the campaign's other stages, no sort).
    pub async fn stage_counts(&self, id: Uuid, stage: &str, iteration: i32) -> Result<StateCounts, JobError> {
        let q = "SELECT state, count(*) AS n FROM tasks WHERE campaign = $1 AND stage = $2 AND iteration = $3 \
                 GROUP BY state";
        let rows: Vec<(String, i64)> =
            with_pool!(self, p => sqlx::query_as(q).bind(id).bind(stage).bind(iteration).fetch_all(p).await?);
        let mut counts = StateCounts::default();
        for (state, n) in rows {
            add_count(&mut counts, &state, n)?;
        }
        Ok(counts)
    }

    /// Newest first.
    pub async fn list_campaigns(&self, limit: i64) -> Result<Vec<CampaignRecord>, JobError> {
        let q = format!("SELECT {CAMPAIGN_COLS} FROM campaigns ORDER BY created_at_ms DESC, id LIMIT $1");
        with_pool!(self, p => {
            let rows = sqlx::query(&q).bind(limit.max(0)).fetch_all(p).await?;
            let mut out = Vec::with_capacity(rows.len());
            for row in rows {
                out.push(campaign_from_row!(row));
            }
            Ok(out)
        })
    }

    /// Task counts by state, for the whole campaign and its current stage/iteration.
    pub async fn task_counts(&self, id: Uuid) -> Result<TaskCounts, JobError> {
        let q = "SELECT t.state, CAST(CASE WHEN t.stage = c.stage AND t.iteration = c.iteration THEN 1 ELSE 0 END \
                 AS BIGINT) AS cur, count(*) AS n FROM tasks t JOIN campaigns c ON c.id = t.campaign \
                 WHERE t.campaign = $1 GROUP BY 1, 2";
        let rows: Vec<(String, i64, i64)> = with_pool!(self, p => {
            if sqlx::query("SELECT 1 FROM campaigns WHERE id = $1").bind(id).fetch_optional(p).await?.is_none() {
                return Err(JobError::NotFound(format!("campaign {id}")));
            }
            sqlx::query_as(q).bind(id).fetch_all(p).await?
        });
        let (mut whole, mut stage) = (StateCounts::default(), StateCounts::default());
        for (state, cur, n) in rows {
            add_count(&mut whole, &state, n)?;
            if cur == 1 {
                add_count(&mut stage, &state, n)?;
            }
        }
        let counts = TaskCounts {
            queued: whole.queued,
            leased: whole.leased,
            done: whole.done,
            dead: whole.dead,
            cancelled: whole.cancelled,
            stage,
        };
        Ok(counts)
    }

    /// The iterations recorded after iteration `after`, in order (a poller keeps the earlier ones).
    pub async fn iterations_after(&self, id: Uuid, after: i32) -> Result<Vec<IterationRecord>, JobError> {
        let q = "SELECT iteration, stats FROM iterations WHERE campaign = $1 AND iteration > $2 ORDER BY iteration";
        let rows: Vec<(i32, Json<Value>)> =
            with_pool!(self, p => sqlx::query_as(q).bind(id).bind(after).fetch_all(p).await?);
        Ok(rows.into_iter().map(|(iteration, stats)| IterationRecord { iteration, stats: stats.0 }).collect())
    }

    pub async fn iterations(&self, id: Uuid) -> Result<Vec<IterationRecord>, JobError> {
        let q = "SELECT iteration, stats FROM iterations WHERE campaign = $1 ORDER BY iteration";
        let rows: Vec<(i32, Json<Value>)> = with_pool!(self, p => sqlx::query_as(q).bind(id).fetch_all(p).await?);
        Ok(rows.into_iter().map(|(iteration, stats)| IterationRecord { iteration, stats: stats.0 }).collect())
    }

    pub async fn strips(&self, id: Uuid) -> Result<Vec<StripRecord>, JobError> {
        let q = "SELECT idx, id, trajectory, uri, points FROM strips WHERE campaign = $1 ORDER BY idx";
        let rows: Vec<(i32, String, String, String, Option<i64>)> =
            with_pool!(self, p => sqlx::query_as(q).bind(id).fetch_all(p).await?);
        Ok(rows
            .into_iter()
            .map(|(index, id, trajectory, uri, points)| StripRecord { index, id, trajectory, uri, points })
            .collect())
    }

    pub async fn trajectories(&self, id: Uuid) -> Result<Vec<TrajectoryRecord>, JobError> {
        let q = "SELECT idx, id, uri FROM trajectories WHERE campaign = $1 ORDER BY idx";
        let rows: Vec<(i32, String, String)> = with_pool!(self, p => sqlx::query_as(q).bind(id).fetch_all(p).await?);
        Ok(rows.into_iter().map(|(index, id, uri)| TrajectoryRecord { index, id, uri }).collect())
    }

    /// Tiles sorted by key.
    pub async fn tiles(&self, id: Uuid) -> Result<Vec<TileRecord>, JobError> {
        let q = "SELECT key, strips, points FROM tiles WHERE campaign = $1";
        let rows: Vec<(String, Json<Vec<String>>, i64)> =
            with_pool!(self, p => sqlx::query_as(q).bind(id).fetch_all(p).await?);
        let mut tiles: Vec<TileRecord> =
            rows.into_iter().map(|(key, strips, points)| TileRecord { key, strips: strips.0, points }).collect();
        // Sorted here, not in SQL: PostgreSQL's collation need not be bytewise.
        tiles.sort_by(|a, b| a.key.cmp(&b.key));
        Ok(tiles)
    }

    /// Events with id > `after_id`, oldest first.
    pub async fn events(&self, id: Uuid, after_id: i64, limit: i64) -> Result<Vec<EventRecord>, JobError> {
        let q = "SELECT id, campaign, at_ms, kind, task_id, message FROM events WHERE campaign = $1 AND id > $2 \
                 ORDER BY id LIMIT $3";
        let rows: Vec<EventRow> =
            with_pool!(self, p => sqlx::query_as(q).bind(id).bind(after_id).bind(limit.max(0)).fetch_all(p).await?);
        Ok(rows.into_iter().map(event_record).collect())
    }

    /// The campaign's newest `limit` events, oldest first (what a dashboard opens with before it
    /// follows the log with [`JobStore::events`] after the last id).
    pub async fn latest_events(&self, id: Uuid, limit: i64) -> Result<Vec<EventRecord>, JobError> {
        let q = "SELECT id, campaign, at_ms, kind, task_id, message FROM events WHERE campaign = $1 \
                 ORDER BY id DESC LIMIT $2";
        let rows: Vec<EventRow> =
            with_pool!(self, p => sqlx::query_as(q).bind(id).bind(limit.max(0)).fetch_all(p).await?);
        Ok(rows.into_iter().rev().map(event_record).collect())
    }

    /// Queued/leased tasks become `cancelled`, the campaign `cancelled`; a worker still running one
    /// gets `LeaseLost` on its next heartbeat/complete/fail. Returns false if already finished.
    pub async fn cancel_campaign(&self, id: Uuid) -> Result<bool, JobError> {
        let lock = self.sql("SELECT state FROM campaigns WHERE id = $1 FOR_LOCK");
        let tasks = self.sql(
            "UPDATE tasks SET state = 'cancelled', error = 'campaign cancelled', updated_at_ms = NOW_MS, \
             finished_at_ms = NOW_MS WHERE campaign = $1 AND state IN ('queued', 'leased')",
        );
        let camp = self.sql(
            "UPDATE campaigns SET state = 'cancelled', updated_at_ms = NOW_MS, finished_at_ms = NOW_MS WHERE id = $1",
        );
        let cancelled = with_tx!(self, tx => {
            let state: Option<String> = sqlx::query_scalar(&lock).bind(id).fetch_optional(&mut *tx).await?;
            match state.as_deref() {
                None => return Err(JobError::NotFound(format!("campaign {id}"))),
                Some("running") => {
                    let n = sqlx::query(&tasks).bind(id).execute(&mut *tx).await?.rows_affected();
                    sqlx::query(&camp).bind(id).execute(&mut *tx).await?;
                    event!(self, tx, id, "cancelled", None::<i64>, &format!("campaign cancelled; {n} open tasks cancelled"));
                    true
                }
                Some(_) => false,
            }
        });
        if cancelled {
            info!(campaign = %id, "campaign cancelled");
        }
        Ok(cancelled)
    }

    /// Removes the campaign and all its rows; returns its `object_prefix` so the caller deletes
    /// its objects. `None` if there is no such campaign.
    pub async fn delete_campaign(&self, id: Uuid) -> Result<Option<String>, JobError> {
        let lock = self.sql("SELECT object_prefix FROM campaigns WHERE id = $1 FOR_LOCK");
        let prefix = with_tx!(self, tx => {
            let prefix: Option<String> = sqlx::query_scalar(&lock).bind(id).fetch_optional(&mut *tx).await?;
            if prefix.is_some() {
                // Children first (explicit rather than relying on SQLite's foreign-key pragma).
                for table in ["task_outputs", "events", "tasks", "tiles", "iterations", "strips", "trajectories"] {
                    sqlx::query(&format!("DELETE FROM {table} WHERE campaign = $1")).bind(id).execute(&mut *tx).await?;
                }
                sqlx::query("DELETE FROM campaigns WHERE id = $1").bind(id).execute(&mut *tx).await?;
            }
            prefix
        });
        if prefix.is_some() {
            info!(campaign = %id, "campaign deleted");
        }
        Ok(prefix)
    }

    /// Claims the oldest runnable task (queued, `not_before` passed, campaign running) of any
    /// campaign, with a new lease token and `attempt + 1`.
    pub async fn claim(&self, worker: &str, lease: Duration) -> Result<Option<ClaimedTask>, JobError> {
        let token = Uuid::new_v4();
        let lease_ms = duration_ms(lease);
        let row: Option<ClaimRow> = match &self.pool {
            Pool::Postgres(p) => {
                // One statement, one round trip: SKIP LOCKED lets concurrent claimers pass each other.
                let q = self.sql(&format!("WITH {} SELECT claimed.* FROM claimed ASYNC", pg_claim_ctes(1, "TRUE")));
                // `set_config(…, true)` lasts until the end of the statement's own transaction, so
                // it applies to this claim's commit and to nothing after it.
                let q = q.replace(
                    "ASYNC",
                    if self.async_claims {
                        ", (SELECT set_config('synchronous_commit', 'off', true)) AS a"
                    } else {
                        ""
                    },
                );
                sqlx::query_as(&q).bind(token).bind(lease_ms).bind(worker).fetch_optional(p).await?
            }
            Pool::Sqlite(p) => {
                let q = self.sql(LITE_CLAIM);
                let mut tx = p.begin_with("BEGIN IMMEDIATE").await?;
                let row = lite_claim!(self, tx, &q, token, lease_ms, worker);
                tx.commit().await?;
                row
            }
        };
        Ok(row.map(|r| claimed_task(r, worker)))
    }

    /// Extends the lease to now + `lease`; `Err(LeaseLost)` if the token no longer holds the task.
    pub async fn heartbeat(&self, task: &ClaimedTask, lease: Duration) -> Result<(), JobError> {
        self.heartbeat_until(task, lease).await.map(|_| ())
    }

    /// Like [`JobStore::heartbeat`], returning the new expiry (database clock, ms).
    pub async fn heartbeat_until(&self, task: &ClaimedTask, lease: Duration) -> Result<i64, JobError> {
        let q = self.sql(
            "UPDATE tasks SET lease_expires_at_ms = NOW_MS + $1, updated_at_ms = NOW_MS \
             WHERE id = $2 AND lease_token = $3 AND state = 'leased' RETURNING lease_expires_at_ms",
        );
        let expiry: Option<i64> = with_pool!(self, p => sqlx::query_scalar(&q)
            .bind(duration_ms(lease))
            .bind(task.id)
            .bind(task.lease_token)
            .fetch_optional(p)
            .await?);
        expiry.ok_or(JobError::LeaseLost)
    }

    /// Records the outputs and result and marks the task done, in one transaction guarded by the
    /// lease token (and by its campaign running with the task in its current stage); then, if the
    /// stage has no open task left, closes it: [`JobStore::advance_stage`] runs the planner and
    /// applies its transition exactly once.
    ///
    /// The first transaction does not touch the campaign row, so completions of one campaign do not
    /// queue behind each other's commits. The barrier is found by looking for open tasks of the
    /// stage *after* the commit: of two completions that commit concurrently at least the later one
    /// sees the other's, so some completion always finds the stage closed (several may; the guard
    /// in `advance_stage` lets one through). A completer dying between the two transactions leaves
    /// the stage closed but not advanced, which [`JobStore::reconcile`] repairs.
    pub async fn complete(
        &self,
        task: &ClaimedTask,
        outcome: TaskOutcome,
        planner: &dyn StagePlanner,
    ) -> Result<Completion, JobError> {
        Ok(self.finish(task, outcome, planner, None).await?.0)
    }

    /// [`JobStore::complete`], and in the same transaction (one commit, one WAL flush, on
    /// PostgreSQL one statement) [`JobStore::claim`] of the next runnable task for `worker`.
    ///
    /// A stale lease token completes nothing and claims nothing (`Err(LeaseLost)`). When the
    /// completion closes its stage, the claim comes after the stage has advanced (SQLite) or, if
    /// the combined statement found nothing to claim, is repeated after it (PostgreSQL), so the
    /// next stage's first task is claimed at once.
    ///
    /// The barrier check after the commit is skipped when the claimed task belongs to the
    /// completed task's stage: the claimer holds it leased at the commit, so the stage is open
    /// and that task's own completion comes later and checks again.
    ///
    /// If the call fails with a transient error after its commit (a dropped connection), the
    /// claimed task is not returned; the caller finds it with [`JobStore::leased_by`] (else it
    /// stays leased until its lease expires and the reconciler queues it again).
    pub async fn complete_and_claim(
        &self,
        task: &ClaimedTask,
        outcome: TaskOutcome,
        planner: &dyn StagePlanner,
        worker: &str,
        lease: Duration,
    ) -> Result<(Completion, Option<ClaimedTask>), JobError> {
        let (completion, next) = self.finish(task, outcome, planner, Some((worker, lease))).await?;
        let next = match next {
            Some(next) => Some(next),
            // The stage advanced after a claim that found nothing (PostgreSQL): its tasks are new.
            None if completion.stage_finished && self.is_pg() => self.claim(worker, lease).await?,
            None => None,
        };
        Ok((completion, next))
    }

    /// `complete`, with a claim for `next` (worker, lease) in the same transaction.
    async fn finish(
        &self,
        task: &ClaimedTask,
        outcome: TaskOutcome,
        planner: &dyn StagePlanner,
        next: Option<(&str, Duration)>,
    ) -> Result<(Completion, Option<ClaimedTask>), JobError> {
        let mut names: Vec<&str> = outcome.outputs.iter().map(|o| o.name.as_str()).collect();
        names.sort_unstable();
        if let Some(w) = names.windows(2).find(|w| w[0] == w[1]) {
            return Err(JobError::Invalid(format!("output name `{}` given twice", w[0])));
        }
        let token = Uuid::new_v4();
        let (stage_open, claimed) = match &self.pool {
            Pool::Postgres(p) => {
                // The guarded update, the outputs (a JSON array) and the event in one statement,
                // committed on its own (one round trip). The campaign row is read, not locked: the
                // task row is where this races with cancelling, failing or rescuing, since each of
                // those changes every open task of the campaign (and a stage advances only once none
                // is open). With `next`, the same statement claims a task, only if the completion
                // went through (`EXISTS (SELECT 1 FROM d)`): a stale token claims nothing.
                let (updated, claimed) = match next {
                    None => {
                        let q = self.sql(&format!("WITH {PG_DONE_CTES} SELECT count(*) FROM d"));
                        let updated: i64 = sqlx::query_scalar(&q)
                            .bind(task.id)
                            .bind(task.lease_token)
                            .bind(Json(&outcome.result))
                            .bind(Json(&outcome.outputs))
                            .fetch_one(p)
                            .await?;
                        (updated, None)
                    }
                    Some((worker, lease)) => {
                        let q = self.sql(&format!(
                            "WITH {PG_DONE_CTES}, {} \
                             SELECT (SELECT count(*) FROM d) AS done, claimed.* FROM (SELECT 1) AS one \
                             LEFT JOIN claimed ON TRUE",
                            pg_claim_ctes(5, "EXISTS (SELECT 1 FROM d)")
                        ));
                        let row = sqlx::query(&q)
                            .bind(task.id)
                            .bind(task.lease_token)
                            .bind(Json(&outcome.result))
                            .bind(Json(&outcome.outputs))
                            .bind(token)
                            .bind(duration_ms(lease))
                            .bind(worker)
                            .fetch_one(p)
                            .await?;
                        let claimed = match row.try_get::<Option<i64>, _>("id")? {
                            None => None,
                            Some(id) => {
                                let r: ClaimRow = (
                                    id,
                                    row.try_get("campaign")?,
                                    row.try_get("stage")?,
                                    row.try_get("iteration")?,
                                    row.try_get("kind")?,
                                    row.try_get("key")?,
                                    row.try_get("input")?,
                                    row.try_get("attempt")?,
                                    row.try_get("lease_token")?,
                                    row.try_get("lease_expires_at_ms")?,
                                );
                                Some(claimed_task(r, worker))
                            }
                        };
                        (row.try_get::<i64, _>("done")?, claimed)
                    }
                };
                if updated == 0 {
                    return Err(JobError::LeaseLost);
                }
                let open = if claimed.as_ref().is_some_and(|c| same_stage(c, task)) {
                    true
                } else {
                    // A new statement, so a new snapshot that includes this commit.
                    sqlx::query_scalar::<_, i64>(STAGE_OPEN)
                        .bind(task.campaign)
                        .bind(&task.stage)
                        .bind(task.iteration)
                        .fetch_optional(p)
                        .await?
                        .is_some()
                };
                (open, claimed)
            }
            Pool::Sqlite(p) => {
                let done = self.sql(LITE_DONE);
                let mut tx = p.begin_with("BEGIN IMMEDIATE").await?;
                let n = sqlx::query(&done)
                    .bind(task.id)
                    .bind(task.lease_token)
                    .bind(Json(&outcome.result))
                    .execute(&mut *tx)
                    .await?
                    .rows_affected();
                if n == 0 {
                    return Err(JobError::LeaseLost);
                }
                let msg = format!("{} {} done (attempt {})", task.kind, task.key, task.attempt);
                event!(self, tx, task.campaign, "done", Some(task.id), &msg);
                if !outcome.outputs.is_empty() {
                    let mut qb = QueryBuilder::new("INSERT INTO task_outputs (task_id, campaign, name, object_key) ");
                    qb.push_values(&outcome.outputs, |mut b, o| {
                        b.push_bind(task.id)
                            .push_bind(task.campaign)
                            .push_bind(o.name.as_str())
                            .push_bind(o.object_key.as_str());
                    });
                    qb.build().execute(&mut *tx).await?;
                }
                // Writers are serialised, so this count under the write lock is exact.
                let open = sqlx::query_scalar::<_, i64>(STAGE_OPEN)
                    .bind(task.campaign)
                    .bind(&task.stage)
                    .bind(task.iteration)
                    .fetch_optional(&mut *tx)
                    .await?
                    .is_some();
                // A stage that closes here advances first (below), so the claim can take the
                // next stage's first task.
                let claimed = match next {
                    Some((worker, lease)) if open => {
                        let q = self.sql(LITE_CLAIM);
                        lite_claim!(self, tx, &q, token, duration_ms(lease), worker).map(|r| claimed_task(r, worker))
                    }
                    _ => None,
                };
                tx.commit().await?;
                (open, claimed)
            }
        };
        if stage_open {
            return Ok((Completion { stage_finished: false, campaign_state: CampaignState::Running }, claimed));
        }
        let completion = match self.advance_stage(task.campaign, &task.stage, task.iteration, planner, false).await? {
            // The campaign was deleted after this task's commit: nothing of it is left.
            None => return Err(JobError::LeaseLost),
            Some(barrier) => Completion { stage_finished: barrier.advanced, campaign_state: barrier.state },
        };
        let claimed = match (claimed, next) {
            (None, Some((worker, lease))) if !self.is_pg() => self.claim(worker, lease).await?,
            (claimed, _) => claimed,
        };
        Ok((completion, claimed))
    }

    /// The stage barrier: if the campaign is running at `stage`/`iteration` and that stage has no
    /// open (queued or leased) task left, runs the planner on the stage's results and applies its
    /// transition (next stage, success or failure), all under the campaign row lock. The guard on
    /// the campaign's stage makes it happen once whoever calls it (racing last completers, the
    /// reconciler). `None` if there is no such campaign.
    /// `rescue` (the reconciler) records a `stage_rescued` event before the transition's own.
    async fn advance_stage(
        &self,
        id: Uuid,
        stage: &str,
        iteration: i32,
        planner: &dyn StagePlanner,
        rescue: bool,
    ) -> Result<Option<Barrier>, JobError> {
        let lock = self.sql(&format!("SELECT {CAMPAIGN_COLS} FROM campaigns WHERE id = $1 FOR_LOCK"));
        let barrier = with_tx!(self, tx => {
            let Some(row) = sqlx::query(&lock).bind(id).fetch_optional(&mut *tx).await? else {
                return Ok(None);
            };
            let mut campaign = campaign_from_row!(row);
            let current = campaign.state == CampaignState::Running && campaign.stage == stage
                && campaign.iteration == iteration;
            // Under the lock no task of this stage can be added or reopened: a stage's tasks are
            // inserted by the transition into it, and only a leased task can be queued again.
            let open = current
                && sqlx::query_scalar::<_, i64>(STAGE_OPEN)
                    .bind(id)
                    .bind(stage)
                    .bind(iteration)
                    .fetch_optional(&mut *tx)
                    .await?
                    .is_some();
            if !current || open {
                Barrier { advanced: false, state: campaign.state }
            } else {
                let rows: Vec<FinishedRow> = sqlx::query_as(
                    "SELECT id, kind, key, result, created_at_ms, finished_at_ms FROM tasks \
                     WHERE campaign = $1 AND stage = $2 AND iteration = $3 AND state = 'done'",
                )
                .bind(id)
                .bind(stage)
                .bind(iteration)
                .fetch_all(&mut *tx)
                .await?;
                let outs: Vec<(i64, String, String)> = sqlx::query_as(
                    "SELECT o.task_id, o.name, o.object_key FROM task_outputs o JOIN tasks t ON t.id = o.task_id \
                     WHERE t.campaign = $1 AND t.stage = $2 AND t.iteration = $3 AND t.state = 'done'",
                )
                .bind(id)
                .bind(stage)
                .bind(iteration)
                .fetch_all(&mut *tx)
                .await?;
                let span_ms = stage_span(&rows);
                let mut finished =
                    FinishedStage { stage: stage.to_string(), iteration, tasks: finished_tasks(rows, outs), span_ms };
                if rescue {
                    let msg = format!("stage {stage} iteration {iteration}: all {} tasks done but the stage was not \
                        advanced (its last completer stopped before the barrier); advancing it", finished.tasks.len());
                    event!(self, tx, id, "stage_rescued", None::<i64>, &msg);
                }
                let mut planned = planner.plan(&campaign, &finished);
                let mut empty_stages = 0;
                let state = loop {
                    let tr = match planned {
                        Err(msg) => {
                            fail_campaign!(self, tx, id, &msg);
                            break CampaignState::Failed;
                        }
                        Ok(tr) => tr,
                    };
                    let set_plan = self.sql("UPDATE campaigns SET plan_state = $2, updated_at_ms = NOW_MS WHERE id = $1");
                    sqlx::query(&set_plan).bind(id).bind(Json(&tr.plan_state)).execute(&mut *tx).await?;
                    for t in &tr.tiles {
                        sqlx::query(
                            "INSERT INTO tiles (campaign, key, strips, points) VALUES ($1, $2, $3, $4) \
                             ON CONFLICT (campaign, key) DO UPDATE SET strips = excluded.strips, points = excluded.points",
                        )
                        .bind(id)
                        .bind(&t.key)
                        .bind(Json(&t.strips))
                        .bind(t.points)
                        .execute(&mut *tx)
                        .await?;
                    }
                    if let Some(it) = &tr.iteration {
                        let q = self.sql(
                            "INSERT INTO iterations (campaign, iteration, stats, recorded_at_ms) VALUES ($1, $2, $3, NOW_MS) \
                             ON CONFLICT (campaign, iteration) DO UPDATE SET stats = excluded.stats, \
                             recorded_at_ms = excluded.recorded_at_ms",
                        );
                        sqlx::query(&q).bind(id).bind(it.iteration).bind(Json(&it.stats)).execute(&mut *tx).await?;
                    }
                    campaign.plan_state = tr.plan_state;
                    match tr.next {
                        Next::Succeed => {
                            let q = self.sql(
                                "UPDATE campaigns SET state = 'succeeded', updated_at_ms = NOW_MS, finished_at_ms = NOW_MS \
                                 WHERE id = $1",
                            );
                            sqlx::query(&q).bind(id).execute(&mut *tx).await?;
                            event!(self, tx, id, "succeeded", None::<i64>, "campaign succeeded");
                            info!(campaign = %id, "campaign succeeded");
                            break CampaignState::Succeeded;
                        }
                        Next::Fail(msg) => {
                            fail_campaign!(self, tx, id, &msg);
                            break CampaignState::Failed;
                        }
                        Next::Stage(spec) => {
                            if let Err(msg) = check_unique_tasks(&spec) {
                                fail_campaign!(self, tx, id, &format!("planner: {msg}"));
                                break CampaignState::Failed;
                            }
                            let existing: i64 = sqlx::query_scalar(
                                "SELECT count(*) FROM tasks WHERE campaign = $1 AND stage = $2 AND iteration = $3",
                            )
                            .bind(id)
                            .bind(&spec.stage)
                            .bind(spec.iteration)
                            .fetch_one(&mut *tx)
                            .await?;
                            if existing > 0 {
                                let msg = format!("planner: stage {} iteration {} was already run", spec.stage, spec.iteration);
                                fail_campaign!(self, tx, id, &msg);
                                break CampaignState::Failed;
                            }
                            let q = self.sql(
                                "UPDATE campaigns SET stage = $2, iteration = $3, updated_at_ms = NOW_MS WHERE id = $1",
                            );
                            sqlx::query(&q).bind(id).bind(&spec.stage).bind(spec.iteration).execute(&mut *tx).await?;
                            let msg = format!("stage {} iteration {}: {} tasks", spec.stage, spec.iteration, spec.tasks.len());
                            event!(self, tx, id, "stage", None::<i64>, &msg);
                            info!(campaign = %id, stage = %spec.stage, iteration = spec.iteration,
                                tasks = spec.tasks.len(), "stage enqueued");
                            if !spec.tasks.is_empty() {
                                insert_tasks!(self, tx, id, &spec);
                                break CampaignState::Running;
                            }
                            // A stage without tasks is finished at once: plan again from it.
                            empty_stages += 1;
                            if empty_stages > MAX_EMPTY_STAGES {
                                let msg = format!("planner produced {MAX_EMPTY_STAGES} stages without tasks in a row");
                                fail_campaign!(self, tx, id, &msg);
                                break CampaignState::Failed;
                            }
                            campaign.stage = spec.stage.clone();
                            campaign.iteration = spec.iteration;
                            finished = FinishedStage {
                                stage: spec.stage,
                                iteration: spec.iteration,
                                tasks: Vec::new(),
                                span_ms: None,
                            };
                            planned = planner.plan(&campaign, &finished);
                        }
                    }
                };
                Barrier { advanced: true, state }
            }
        });
        Ok(Some(barrier))
    }

    /// Records a failed attempt, guarded by the lease token. A `permanent` error or the last
    /// attempt makes the task dead and fails its campaign; otherwise it is queued again after a
    /// back-off.
    pub async fn fail(&self, task: &ClaimedTask, error: &str, permanent: bool) -> Result<FailOutcome, JobError> {
        let lock =
            self.sql("SELECT max_attempts, backoff_base_ms, backoff_max_ms FROM campaigns WHERE id = $1 FOR_LOCK");
        let held = "SELECT attempt FROM tasks WHERE id = $1 AND lease_token = $2 AND state = 'leased'";
        let dead = self.sql(
            "UPDATE tasks SET state = 'dead', error = $2, updated_at_ms = NOW_MS, finished_at_ms = NOW_MS WHERE id = $1",
        );
        let retry = self.sql(
            "UPDATE tasks SET state = 'queued', error = $2, lease_token = NULL, lease_expires_at_ms = NULL, \
             not_before_ms = NOW_MS + $3, updated_at_ms = NOW_MS WHERE id = $1 RETURNING not_before_ms",
        );
        let outcome = with_tx!(self, tx => {
            let Some((max_attempts, base_ms, max_ms)) = sqlx::query_as::<_, (i32, i64, i64)>(&lock)
                .bind(task.campaign)
                .fetch_optional(&mut *tx)
                .await?
            else {
                return Err(JobError::LeaseLost);
            };
            let Some(attempt) = sqlx::query_scalar::<_, i32>(held)
                .bind(task.id)
                .bind(task.lease_token)
                .fetch_optional(&mut *tx)
                .await?
            else {
                return Err(JobError::LeaseLost);
            };
            if permanent || attempt >= max_attempts {
                sqlx::query(&dead).bind(task.id).bind(error).execute(&mut *tx).await?;
                let why = if permanent { "permanent error".to_string() } else { format!("attempt {attempt} of {max_attempts}") };
                let msg = format!("{} {} dead ({why}): {error}", task.kind, task.key);
                event!(self, tx, task.campaign, "dead", Some(task.id), &msg);
                fail_campaign!(self, tx, task.campaign, &format!("`{} {}`: {error}", task.kind, task.key));
                FailOutcome::Dead
            } else {
                let not_before_ms: i64 = sqlx::query_scalar(&retry)
                    .bind(task.id)
                    .bind(error)
                    .bind(backoff_ms(base_ms, max_ms, attempt))
                    .fetch_one(&mut *tx)
                    .await?;
                let msg = format!("{} {} attempt {attempt} failed, retry at {not_before_ms}: {error}", task.kind, task.key);
                event!(self, tx, task.campaign, "retry", Some(task.id), &msg);
                FailOutcome::Retry { not_before_ms }
            }
        });
        debug!(task = task.id, ?outcome, error, "task failed");
        Ok(outcome)
    }

    /// Rescues expired leases (queued again after a back-off, or dead, failing the campaign, when
    /// the attempts are used up), then advances stuck barriers: running campaigns whose current
    /// stage has no open task left but which were not advanced, because the completer of the
    /// stage's last task died between its commit and the barrier. `planner` must be the one the
    /// completers use. Safe to run from every executor concurrently, also while tasks complete.
    pub async fn reconcile(&self, planner: &dyn StagePlanner) -> Result<ReconcileReport, JobError> {
        // The redundant `IN` lets SQLite, too, scan the partial index `tasks_open` (open tasks
        // only) rather than every task ever run.
        let q = self.sql(
            "SELECT DISTINCT campaign FROM tasks WHERE state IN ('queued', 'leased') AND state = 'leased' \
             AND lease_expires_at_ms < NOW_MS",
        );
        let campaigns: Vec<Uuid> = with_pool!(self, p => sqlx::query_scalar(&q).fetch_all(p).await?);
        let mut report = ReconcileReport::default();
        for campaign in campaigns {
            let r = self.reconcile_campaign(campaign).await?;
            report.requeued += r.requeued;
            report.dead += r.dead;
            if r.dead > 0 {
                report.finished.push(campaign);
            }
        }
        if report.requeued + report.dead > 0 {
            info!(requeued = report.requeued, dead = report.dead, "expired leases rescued");
        }
        let running = "SELECT id, stage, iteration FROM campaigns WHERE state = 'running'";
        let running: Vec<(Uuid, String, i32)> = with_pool!(self, p => sqlx::query_as(running).fetch_all(p).await?);
        let mut stuck = Vec::new();
        for (campaign, stage, iteration) in running {
            let open: Option<i64> = with_pool!(self, p => sqlx::query_scalar(STAGE_OPEN)
                .bind(campaign)
                .bind(&stage)
                .bind(iteration)
                .fetch_optional(p)
                .await?);
            if open.is_none() {
                stuck.push((campaign, stage, iteration));
            }
        }
        for (campaign, stage, iteration) in stuck {
            // Usually a completer that is about to advance the stage itself: whichever of the two
            // comes second finds the stage moved on and does nothing.
            if let Some(Barrier { advanced: true, state }) =
                self.advance_stage(campaign, &stage, iteration, planner, true).await?
            {
                report.advanced += 1;
                if state != CampaignState::Running {
                    report.finished.push(campaign);
                }
                warn!(%campaign, %stage, iteration, %state, "advanced a stage whose tasks were all done");
            }
        }
        Ok(report)
    }

    async fn reconcile_campaign(&self, campaign: Uuid) -> Result<ReconcileReport, JobError> {
        let lock = self
            .sql("SELECT state, max_attempts, backoff_base_ms, backoff_max_ms FROM campaigns WHERE id = $1 FOR_LOCK");
        let expired = self.sql(
            "SELECT id, kind, key, attempt, worker FROM tasks WHERE campaign = $1 AND state IN ('queued', 'leased') \
             AND state = 'leased' AND lease_expires_at_ms < NOW_MS ORDER BY id",
        );
        // Re-checks the expiry: a heartbeat that committed meanwhile keeps its lease.
        let dead = self.sql(
            "UPDATE tasks SET state = 'dead', error = $2, updated_at_ms = NOW_MS, finished_at_ms = NOW_MS \
             WHERE id = $1 AND state = 'leased' AND lease_expires_at_ms < NOW_MS",
        );
        let requeue = self.sql(
            "UPDATE tasks SET state = 'queued', error = $2, lease_token = NULL, lease_expires_at_ms = NULL, \
             not_before_ms = NOW_MS + $3, updated_at_ms = NOW_MS \
             WHERE id = $1 AND state = 'leased' AND lease_expires_at_ms < NOW_MS",
        );
        let report = with_tx!(self, tx => {
            let mut report = ReconcileReport::default();
            let row: Option<(String, i32, i64, i64)> = sqlx::query_as(&lock).bind(campaign).fetch_optional(&mut *tx).await?;
            // A finished campaign has no leased tasks left (finishing cancels them).
            if let Some((_, max_attempts, base_ms, max_ms)) = row.filter(|r| r.0 == "running") {
                let tasks: Vec<(i64, String, String, i32, Option<String>)> =
                    sqlx::query_as(&expired).bind(campaign).fetch_all(&mut *tx).await?;
                for (id, kind, key, attempt, worker) in tasks {
                    let worker = worker.unwrap_or_default();
                    let error = format!("lease expired (attempt {attempt}, worker {worker})");
                    if attempt >= max_attempts {
                        if sqlx::query(&dead).bind(id).bind(&error).execute(&mut *tx).await?.rows_affected() == 0 {
                            continue;
                        }
                        report.dead += 1;
                        event!(self, tx, campaign, "dead", Some(id), &format!("{kind} {key} dead: {error}"));
                        fail_campaign!(self, tx, campaign, &format!("`{kind} {key}`: {error}"));
                        // The campaign is over; its other tasks were cancelled with it.
                        break;
                    }
                    let n = sqlx::query(&requeue)
                        .bind(id)
                        .bind(&error)
                        .bind(backoff_ms(base_ms, max_ms, attempt))
                        .execute(&mut *tx)
                        .await?
                        .rows_affected();
                    if n > 0 {
                        report.requeued += 1;
                        event!(self, tx, campaign, "lease_expired", Some(id), &format!("{kind} {key} requeued: {error}"));
                    }
                }
            }
            report
        });
        Ok(report)
    }

    /// Recorded outputs of one stage, sorted by (kind, task key, name). Only committed completions
    /// are ever visible.
    pub async fn outputs(&self, campaign: Uuid, stage: &str, iteration: i32) -> Result<Vec<RecordedOutput>, JobError> {
        let q = "SELECT t.key, t.kind, o.name, o.object_key FROM task_outputs o JOIN tasks t ON t.id = o.task_id \
                 WHERE t.campaign = $1 AND t.stage = $2 AND t.iteration = $3 AND t.state = 'done'";
        let rows: Vec<(String, String, String, String)> =
            with_pool!(self, p => sqlx::query_as(q).bind(campaign).bind(stage).bind(iteration).fetch_all(p).await?);
        let mut out: Vec<RecordedOutput> = rows
            .into_iter()
            .map(|(task_key, kind, name, object_key)| RecordedOutput { task_key, kind, name, object_key })
            .collect();
        out.sort_by(|a, b| (&a.kind, &a.task_key, &a.name).cmp(&(&b.kind, &b.task_key, &b.name)));
        Ok(out)
    }

    /// Every object key recorded for the campaign, sorted, each once however many tasks recorded
    /// it (the report task records the latent map's tiles again as results), for orphan
    /// clean-up by the caller.
    pub async fn recorded_keys(&self, campaign: Uuid) -> Result<Vec<String>, JobError> {
        let q = "SELECT DISTINCT object_key FROM task_outputs WHERE campaign = $1";
        let mut keys: Vec<String> = with_pool!(self, p => sqlx::query_scalar(q).bind(campaign).fetch_all(p).await?);
        keys.sort();
        Ok(keys)
    }

    /// Claims the sweep of one finished campaign (succeeded, failed or cancelled at least `grace`
    /// ago) whose objects of lost attempts have not been swept yet, oldest first, for `lease`:
    /// no other executor gets it meanwhile. With `grace` ≥ the task lease, every attempt that was
    /// running when the campaign finished has lost its lease (its heartbeat fails and it stops)
    /// before the sweep lists the store. `None` when nothing is due.
    pub async fn claim_sweep(&self, grace: Duration, lease: Duration) -> Result<Option<Uuid>, JobError> {
        // The outer conditions are checked again on the row itself: of two racing claimers the
        // second finds the lease taken (PostgreSQL re-evaluates them after the first commits).
        let q = self.sql(
            "UPDATE campaigns SET sweep_lease_until_ms = NOW_MS + $2 WHERE id = (\
                SELECT id FROM campaigns WHERE state <> 'running' AND swept_at_ms IS NULL \
                AND finished_at_ms <= NOW_MS - $1 \
                AND (sweep_lease_until_ms IS NULL OR sweep_lease_until_ms < NOW_MS) \
                ORDER BY finished_at_ms, id LIMIT 1) \
             AND swept_at_ms IS NULL AND (sweep_lease_until_ms IS NULL OR sweep_lease_until_ms < NOW_MS) \
             RETURNING id",
        );
        let ms = |d: Duration| i64::try_from(d.as_millis()).unwrap_or(i64::MAX / 4);
        Ok(with_pool!(self, p => sqlx::query_scalar(&q).bind(ms(grace)).bind(ms(lease)).fetch_optional(p).await?))
    }

    /// Records that a finished campaign's objects of lost attempts were swept. Called after the
    /// sweep, so that an executor dying mid-sweep leaves the campaign to the next one once its
    /// sweep lease has expired.
    pub async fn mark_swept(&self, campaign: Uuid) -> Result<(), JobError> {
        let q = self.sql("UPDATE campaigns SET swept_at_ms = NOW_MS WHERE id = $1 AND state <> 'running'");
        with_pool!(self, p => sqlx::query(&q).bind(campaign).execute(p).await.map(|_| ())?);
        Ok(())
    }

    /// Tasks leased to `worker` (oldest first), with their lease tokens. An executor loop whose
    /// `complete_and_claim` failed with a transient error after its commit finds here the task
    /// that call claimed, instead of leaving it leased until its lease expires (worker ids must
    /// be unique among running executors, as `hostname-pid-loop` is).
    pub async fn leased_by(&self, worker: &str) -> Result<Vec<ClaimedTask>, JobError> {
        // The redundant `IN` lets both backends scan `tasks_open` only.
        let q = "SELECT id, campaign, stage, iteration, kind, key, input, attempt, lease_token, lease_expires_at_ms \
                 FROM tasks WHERE state IN ('queued', 'leased') AND state = 'leased' AND worker = $1 ORDER BY id";
        let rows: Vec<ClaimRow> = with_pool!(self, p => sqlx::query_as(q).bind(worker).fetch_all(p).await?);
        Ok(rows.into_iter().map(|r| claimed_task(r, worker)).collect())
    }

    /// Hands a leased task back to the queue at once (an executor shutting down before the task
    /// is done): runnable again now, by any executor, without waiting for the lease to expire.
    /// The attempt still counts towards the campaign's maximum, as an expired lease does, so the
    /// next attempt writes under keys of its own. `Ok(false)` if the token no longer holds it.
    pub async fn release(&self, task: &ClaimedTask) -> Result<bool, JobError> {
        let q = self.sql(
            "UPDATE tasks SET state = 'queued', lease_token = NULL, lease_expires_at_ms = NULL, \
             not_before_ms = NOW_MS, updated_at_ms = NOW_MS WHERE id = $1 AND lease_token = $2 AND state = 'leased'",
        );
        let released = with_tx!(self, tx => {
            let n = sqlx::query(&q).bind(task.id).bind(task.lease_token).execute(&mut *tx).await?.rows_affected();
            if n > 0 {
                let msg = format!("{} {} attempt {} handed back by its executor", task.kind, task.key, task.attempt);
                event!(self, tx, task.campaign, "released", Some(task.id), &msg);
            }
            n > 0
        });
        debug!(task = task.id, released, "lease handed back");
        Ok(released)
    }

    /// The queue across campaigns, for monitoring: open tasks per kind and state (`queued`,
    /// `leased`) and how many executors hold a lease. Reads the open tasks' partial index only.
    pub async fn queue_depth(&self) -> Result<QueueDepth, JobError> {
        let per_kind =
            "SELECT kind, state, count(*) FROM tasks WHERE state IN ('queued', 'leased') GROUP BY kind, state";
        let busy = "SELECT count(DISTINCT worker) FROM tasks WHERE state IN ('queued', 'leased') AND state = 'leased'";
        let open: Vec<(String, String, i64)> = with_pool!(self, p => sqlx::query_as(per_kind).fetch_all(p).await?);
        let busy_executors: i64 = with_pool!(self, p => sqlx::query_scalar(busy).fetch_one(p).await?);
        Ok(QueueDepth { open, busy_executors })
    }

    /// Lease tokens of the campaign's running attempts (their objects must not be cleaned up).
    pub async fn live_lease_tokens(&self, campaign: Uuid) -> Result<Vec<Uuid>, JobError> {
        let q = "SELECT lease_token FROM tasks WHERE campaign = $1 AND state = 'leased' AND lease_token IS NOT NULL";
        Ok(with_pool!(self, p => sqlx::query_scalar(q).bind(campaign).fetch_all(p).await?))
    }
}

mod lifecycle;

/// The columns a claim returns: id, campaign, stage, iteration, kind, key, input, attempt,
/// lease token, lease expiry.
type ClaimRow = (i64, Uuid, String, i32, String, String, Json<Value>, i32, Uuid, i64);

fn claimed_task(row: ClaimRow, worker: &str) -> ClaimedTask {
    let (id, campaign, stage, iteration, kind, key, input, attempt, lease_token, lease_expires_at_ms) = row;
    debug!(task = id, %kind, %key, attempt, worker, "claimed");
    ClaimedTask { id, campaign, stage, iteration, kind, key, input: input.0, attempt, lease_token, lease_expires_at_ms }
}

/// The two tasks belong to the same stage of the same campaign.
fn same_stage(a: &ClaimedTask, b: &ClaimedTask) -> bool {
    a.campaign == b.campaign && a.iteration == b.iteration && a.stage == b.stage
}

fn ms_duration(ms: i64) -> Duration {
    Duration::from_millis(u64::try_from(ms).unwrap_or(0))
}

fn add_count(c: &mut StateCounts, state: &str, n: i64) -> Result<(), JobError> {
    match state {
        "queued" => c.queued += n,
        "leased" => c.leased += n,
        "done" => c.done += n,
        "dead" => c.dead += n,
        "cancelled" => c.cancelled += n,
        other => return Err(JobError::Corrupt(format!("task state `{other}`"))),
    }
    Ok(())
}

/// `(kind, key)` must be unique within a stage: it names the task's objects.
fn check_unique_tasks(spec: &StageSpec) -> Result<(), String> {
    let mut seen: Vec<(&str, &str)> = spec.tasks.iter().map(|t| (t.kind.as_str(), t.key.as_str())).collect();
    seen.sort_unstable();
    match seen.windows(2).find(|w| w[0] == w[1]) {
        Some(w) => Err(format!("stage {} has task `{} {}` twice", spec.stage, w[0].0, w[0].1)),
        None => Ok(()),
    }
}

/// A finished task's row: id, kind, key, result, enqueued and finished times.
type FinishedRow = (i64, String, String, Option<Json<Value>>, i64, Option<i64>);

/// From the first task's enqueueing to the last one's completion (`None` without tasks).
fn stage_span(rows: &[FinishedRow]) -> Option<StageSpan> {
    let enqueued_at_ms = rows.iter().map(|r| r.4).min()?;
    let finished_at_ms = rows.iter().filter_map(|r| r.5).max().unwrap_or(enqueued_at_ms).max(enqueued_at_ms);
    Some(StageSpan { enqueued_at_ms, finished_at_ms })
}

/// Joins the stage's done tasks with their outputs; tasks sorted by (kind, key) bytewise,
/// outputs by name, so the planner sees the same input whatever the database's collation.
fn finished_tasks(rows: Vec<FinishedRow>, outs: Vec<(i64, String, String)>) -> Vec<FinishedTask> {
    let mut by_task: HashMap<i64, Vec<OutputKey>> = HashMap::new();
    for (task_id, name, object_key) in outs {
        by_task.entry(task_id).or_default().push(OutputKey { name, object_key });
    }
    let mut tasks: Vec<FinishedTask> = rows
        .into_iter()
        .map(|(id, kind, key, result, _, _)| {
            let mut outputs = by_task.remove(&id).unwrap_or_default();
            outputs.sort_by(|a, b| a.name.cmp(&b.name));
            FinishedTask { kind, key, result: result.map(|j| j.0).unwrap_or(Value::Null), outputs }
        })
        .collect();
    tasks.sort_by(|a, b| (&a.kind, &a.key).cmp(&(&b.kind, &b.key)));
    tasks
}

type EventRow = (i64, Uuid, i64, String, Option<i64>, String);

fn event_record((id, campaign, at_ms, kind, task_id, message): EventRow) -> EventRecord {
    EventRecord { id, campaign, at_ms, kind, task_id, message }
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
        let url = crate::bench::with_database(&admin, &name);
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
