//! Completing a task: the guarded commit of its outputs, optionally with the claim of the next
//! task, then the stage barrier.

use super::*;

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

impl JobStore {
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
        let (stage_open, claimed) = match &self.pool {
            Pool::Postgres(p) => self.commit_done_postgres(p, task, &outcome, next).await?,
            Pool::Sqlite(p) => self.commit_done_sqlite(p, task, &outcome, next).await?,
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

    /// PostgreSQL: commits the completion (and the claim for `next`); returns whether the stage
    /// is still open, and the claimed task.
    ///
    /// The guarded update, the outputs (a JSON array) and the event in one statement, committed
    /// on its own (one round trip). The campaign row is read, not locked: the task row is where
    /// this races with cancelling, failing or rescuing, since each of those changes every open
    /// task of the campaign (and a stage advances only once none is open). With `next`, the same
    /// statement claims a task, only if the completion went through (`EXISTS (SELECT 1 FROM d)`):
    /// a stale token claims nothing.
    async fn commit_done_postgres(
        &self,
        p: &PgPool,
        task: &ClaimedTask,
        outcome: &TaskOutcome,
        next: Option<(&str, Duration)>,
    ) -> Result<(bool, Option<ClaimedTask>), JobError> {
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
                    .bind(Uuid::new_v4())
                    .bind(duration_ms(lease))
                    .bind(worker)
                    .fetch_one(p)
                    .await?;
                let claimed = claimed_from_row(&row, worker)?;
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
        Ok((open, claimed))
    }

    /// SQLite: commits the completion (and, if the stage stays open, the claim for `next`) in
    /// one write transaction; returns whether the stage is still open, and the claimed task.
    async fn commit_done_sqlite(
        &self,
        p: &SqlitePool,
        task: &ClaimedTask,
        outcome: &TaskOutcome,
        next: Option<(&str, Duration)>,
    ) -> Result<(bool, Option<ClaimedTask>), JobError> {
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
        // A stage that closes here advances first (in `finish`), so the claim can take the next
        // stage's first task.
        let claimed = match next {
            Some((worker, lease)) if open => {
                let q = self.sql(LITE_CLAIM);
                lite_claim!(self, tx, &q, Uuid::new_v4(), duration_ms(lease), worker).map(|r| claimed_task(r, worker))
            }
            _ => None,
        };
        tx.commit().await?;
        Ok((open, claimed))
    }
}

/// The claimed task in the row of the combined completion and claim (PostgreSQL), if any.
fn claimed_from_row(row: &sqlx::postgres::PgRow, worker: &str) -> Result<Option<ClaimedTask>, JobError> {
    let Some(id) = row.try_get::<Option<i64>, _>("id")? else {
        return Ok(None);
    };
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
    Ok(Some(claimed_task(r, worker)))
}

/// The two tasks belong to the same stage of the same campaign.
fn same_stage(a: &ClaimedTask, b: &ClaimedTask) -> bool {
    a.campaign == b.campaign && a.iteration == b.iteration && a.stage == b.stage
}
