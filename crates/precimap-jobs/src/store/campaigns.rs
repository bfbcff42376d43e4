//! Creating, cancelling and deleting campaigns.

use super::*;

impl JobStore {
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
}
