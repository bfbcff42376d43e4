//! The storage life cycle's side of the job store: a campaign's parameters (stored once for all
//! its tasks), whether an attempt may still write, which campaigns name an input object, and the
//! look-ups the sweepers and retention need.

use std::collections::BTreeSet;
use std::time::Duration;

use serde_json::Value;
use sqlx::types::Json;
use sqlx::QueryBuilder;
use tracing::info;
use uuid::Uuid;

use super::{JobStore, Pool, INSERT_CHUNK};
use crate::error::JobError;
use crate::types::{duration_ms, DeletedCampaign, InputReference};

/// Keys under this prefix are inputs: the only objects a manifest may name, and the only ones
/// a campaign's deletion may remove besides its own prefix.
const INPUTS_PREFIX: &str = "inputs/";

/// `(uri, campaign)` of strips and trajectories whose uri is one of `$keys`, built with `push_bind`.
macro_rules! references_query {
    ($keys:expr) => {{
        let keys: &[String] = $keys;
        let mut qb = QueryBuilder::new("SELECT uri, campaign FROM strips WHERE uri IN (");
        let mut list = qb.separated(", ");
        for k in keys {
            list.push_bind(k.as_str());
        }
        qb.push(") UNION SELECT uri, campaign FROM trajectories WHERE uri IN (");
        let mut list = qb.separated(", ");
        for k in keys {
            list.push_bind(k.as_str());
        }
        qb.push(")");
        qb
    }};
}

impl JobStore {
    /// The parameters stored with the campaign (`NewCampaign::params`); `None` for a campaign
    /// that has none or does not exist.
    pub async fn campaign_params(&self, id: Uuid) -> Result<Option<Value>, JobError> {
        let q = "SELECT params FROM campaigns WHERE id = $1";
        let row: Option<Option<Json<Value>>> =
            with_pool!(self, p => sqlx::query_scalar(q).bind(id).fetch_optional(p).await?);
        Ok(row.flatten().map(|j| j.0))
    }

    /// Whether the attempt holding `task_id` with `lease_token` may still write objects: its task
    /// is leased to it and its campaign is running. False once the campaign was cancelled,
    /// failed or deleted, or the lease was lost; executors ask before every object write.
    pub async fn attempt_may_write(&self, task_id: i64, lease_token: Uuid) -> Result<bool, JobError> {
        let q = "SELECT t.id FROM tasks t JOIN campaigns c ON c.id = t.campaign \
                 WHERE t.id = $1 AND t.lease_token = $2 AND t.state = 'leased' AND c.state = 'running'";
        let row: Option<i64> =
            with_pool!(self, p => sqlx::query_scalar(q).bind(task_id).bind(lease_token).fetch_optional(p).await?);
        Ok(row.is_some())
    }

    /// Removes the campaign and all its rows, like [`JobStore::delete_campaign`], and also returns
    /// the input objects it named that no remaining campaign names (the caller deletes them).
    /// `None` if there is no such campaign.
    pub async fn delete_campaign_with_inputs(&self, id: Uuid) -> Result<Option<DeletedCampaign>, JobError> {
        let lock = self.sql("SELECT object_prefix FROM campaigns WHERE id = $1 FOR_LOCK");
        let named = "SELECT uri FROM strips WHERE campaign = $1 UNION SELECT uri FROM trajectories WHERE campaign = $1";
        let deleted = with_tx!(self, tx => {
            let prefix: Option<String> = sqlx::query_scalar(&lock).bind(id).fetch_optional(&mut *tx).await?;
            match prefix {
                None => None,
                Some(object_prefix) => {
                    let inputs: BTreeSet<String> = sqlx::query_scalar::<_, String>(named)
                        .bind(id)
                        .fetch_all(&mut *tx)
                        .await?
                        .into_iter()
                        .filter(|uri| uri.starts_with(INPUTS_PREFIX))
                        .collect();
                    for table in ["task_outputs", "events", "tasks", "tiles", "iterations", "strips", "trajectories"] {
                        sqlx::query(&format!("DELETE FROM {table} WHERE campaign = $1")).bind(id).execute(&mut *tx).await?;
                    }
                    sqlx::query("DELETE FROM campaigns WHERE id = $1").bind(id).execute(&mut *tx).await?;
                    let inputs: Vec<String> = inputs.into_iter().collect();
                    let mut still_named = BTreeSet::new();
                    for chunk in inputs.chunks(INSERT_CHUNK / 2) {
                        let rows: Vec<(String, Uuid)> =
                            references_query!(chunk).build_query_as().fetch_all(&mut *tx).await?;
                        still_named.extend(rows.into_iter().map(|(uri, _)| uri));
                    }
                    let unreferenced_inputs = inputs.into_iter().filter(|k| !still_named.contains(k)).collect();
                    Some(DeletedCampaign { object_prefix, unreferenced_inputs })
                }
            }
        });
        if let Some(d) = &deleted {
            info!(campaign = %id, inputs = d.unreferenced_inputs.len(), "campaign deleted");
        }
        Ok(deleted)
    }

    /// The campaigns that name any of `keys` as a strip or trajectory, sorted by key, then campaign.
    pub async fn input_references(&self, keys: &[String]) -> Result<Vec<InputReference>, JobError> {
        let mut out = Vec::new();
        for chunk in keys.chunks(INSERT_CHUNK / 2) {
            let rows: Vec<(String, Uuid)> =
                with_pool!(self, p => references_query!(chunk).build_query_as().fetch_all(p).await?);
            out.extend(rows.into_iter().map(|(key, campaign)| InputReference { key, campaign }));
        }
        out.sort_by(|a, b| (&a.key, a.campaign).cmp(&(&b.key, b.campaign)));
        out.dedup();
        Ok(out)
    }

    /// Every campaign's object prefix (without a trailing `/`): the sweeper removes objects under
    /// prefixes no campaign owns.
    pub async fn object_prefixes(&self) -> Result<Vec<String>, JobError> {
        let q = "SELECT object_prefix FROM campaigns";
        let rows: Vec<String> = with_pool!(self, p => sqlx::query_scalar(q).fetch_all(p).await?);
        Ok(rows.into_iter().map(|p| p.trim_end_matches('/').to_string()).collect())
    }

    /// Campaigns that finished at least `age` ago (database clock), oldest first, at most `limit`.
    pub async fn finished_before(&self, age: Duration, limit: i64) -> Result<Vec<Uuid>, JobError> {
        let q = self.sql(
            "SELECT id FROM campaigns WHERE state <> 'running' AND finished_at_ms <= NOW_MS - $1 \
             ORDER BY finished_at_ms, id LIMIT $2",
        );
        Ok(with_pool!(self, p => sqlx::query_scalar(&q).bind(duration_ms(age)).bind(limit.max(0)).fetch_all(p).await?))
    }
}

impl JobStore {
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

    /// The campaign's object prefix, `None` if there is no such campaign.
    pub async fn object_prefix(&self, id: Uuid) -> Result<Option<String>, JobError> {
        let q = "SELECT object_prefix FROM campaigns WHERE id = $1";
        Ok(with_pool!(self, p => sqlx::query_scalar(q).bind(id).fetch_optional(p).await?))
    }
}
