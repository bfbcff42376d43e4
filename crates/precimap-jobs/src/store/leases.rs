//! Leases: claiming a task, heartbeats, failed attempts, and handing a task back.

use super::*;

/// SQLite: claims the oldest runnable task (`$1` lease token, `$2` lease in ms, `$3` worker).
pub(super) const LITE_CLAIM: &str = "UPDATE tasks SET state = 'leased', attempt = attempt + 1, lease_token = $1, \
       lease_expires_at_ms = NOW_MS + $2, worker = $3, updated_at_ms = NOW_MS \
     WHERE id = (SELECT t.id FROM tasks t JOIN campaigns c ON c.id = t.campaign \
       WHERE t.state = 'queued' AND t.not_before_ms <= NOW_MS AND c.state = 'running' \
       ORDER BY t.id LIMIT 1) \
     RETURNING id, campaign, stage, iteration, kind, key, input, attempt, lease_token, lease_expires_at_ms";

/// PostgreSQL: the CTEs `next`, `claimed` and `claimed_ev` that claim the oldest runnable task
/// if `guard` holds, with the lease token in parameter `$first`, the lease in ms in the next one
/// and the worker in the one after.
pub(super) fn pg_claim_ctes(first: usize, guard: &str) -> String {
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

impl JobStore {
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
}

/// The columns a claim returns: id, campaign, stage, iteration, kind, key, input, attempt,
/// lease token, lease expiry.
pub(super) type ClaimRow = (i64, Uuid, String, i32, String, String, Json<Value>, i32, Uuid, i64);

pub(super) fn claimed_task(row: ClaimRow, worker: &str) -> ClaimedTask {
    let (id, campaign, stage, iteration, kind, key, input, attempt, lease_token, lease_expires_at_ms) = row;
    debug!(task = id, %kind, %key, attempt, worker, "claimed");
    ClaimedTask { id, campaign, stage, iteration, kind, key, input: input.0, attempt, lease_token, lease_expires_at_ms }
}
