//! Rescuing expired leases and stuck barriers.

use super::*;

impl JobStore {
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
}
