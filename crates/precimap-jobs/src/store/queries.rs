//! Reading campaigns, their tasks, iterations, tiles, events and outputs, and the queue.

use super::*;

impl JobStore {
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

type EventRow = (i64, Uuid, i64, String, Option<i64>, String);

fn event_record((id, campaign, at_ms, kind, task_id, message): EventRow) -> EventRecord {
    EventRecord { id, campaign, at_ms, kind, task_id, message }
}
