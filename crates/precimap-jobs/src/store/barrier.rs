//! The stage barrier: closing a stage once, running the planner on its results and applying
//! the transition.

use super::*;

/// Planned stages without tasks in a row before the planner is considered stuck.
const MAX_EMPTY_STAGES: usize = 64;

/// What [`JobStore::advance_stage`] did.
#[derive(Debug, Clone, Copy)]
pub(super) struct Barrier {
    /// This call closed the stage and applied the planner's transition.
    pub(super) advanced: bool,
    /// The campaign's state afterwards.
    pub(super) state: CampaignState,
}

/// The stage's done tasks with their outputs, as the planner sees them (in `$tx`).
macro_rules! finished_stage {
    ($tx:ident, $id:expr, $stage:expr, $iteration:expr) => {{
        let (id, stage, iteration): (Uuid, &str, i32) = ($id, $stage, $iteration);
        let rows: Vec<FinishedRow> = sqlx::query_as(
            "SELECT id, kind, key, result, created_at_ms, finished_at_ms FROM tasks \
             WHERE campaign = $1 AND stage = $2 AND iteration = $3 AND state = 'done'",
        )
        .bind(id)
        .bind(stage)
        .bind(iteration)
        .fetch_all(&mut *$tx)
        .await?;
        let outs: Vec<(i64, String, String)> = sqlx::query_as(
            "SELECT o.task_id, o.name, o.object_key FROM task_outputs o JOIN tasks t ON t.id = o.task_id \
             WHERE t.campaign = $1 AND t.stage = $2 AND t.iteration = $3 AND t.state = 'done'",
        )
        .bind(id)
        .bind(stage)
        .bind(iteration)
        .fetch_all(&mut *$tx)
        .await?;
        let span_ms = stage_span(&rows);
        FinishedStage { stage: stage.to_string(), iteration, tasks: finished_tasks(rows, outs), span_ms }
    }};
}

/// Records what a transition carries besides its next step: the plan state, tiles and the
/// iteration's statistics.
macro_rules! record_transition {
    ($self:ident, $tx:ident, $id:expr, $tr:expr) => {{
        let (id, tr): (Uuid, &Transition) = ($id, $tr);
        let set_plan = $self.sql("UPDATE campaigns SET plan_state = $2, updated_at_ms = NOW_MS WHERE id = $1");
        sqlx::query(&set_plan).bind(id).bind(Json(&tr.plan_state)).execute(&mut *$tx).await?;
        for t in &tr.tiles {
            sqlx::query(
                "INSERT INTO tiles (campaign, key, strips, points) VALUES ($1, $2, $3, $4) \
                 ON CONFLICT (campaign, key) DO UPDATE SET strips = excluded.strips, points = excluded.points",
            )
            .bind(id)
            .bind(&t.key)
            .bind(Json(&t.strips))
            .bind(t.points)
            .execute(&mut *$tx)
            .await?;
        }
        if let Some(it) = &tr.iteration {
            let q = $self.sql(
                "INSERT INTO iterations (campaign, iteration, stats, recorded_at_ms) VALUES ($1, $2, $3, NOW_MS) \
                 ON CONFLICT (campaign, iteration) DO UPDATE SET stats = excluded.stats, \
                 recorded_at_ms = excluded.recorded_at_ms",
            );
            sqlx::query(&q).bind(id).bind(it.iteration).bind(Json(&it.stats)).execute(&mut *$tx).await?;
        }
    }};
}

/// Moves the campaign to the stage `$spec` and enqueues its tasks: `Err(message)` if the
/// planner's stage cannot be entered (the campaign must fail), else whether it has tasks.
macro_rules! enter_stage {
    ($self:ident, $tx:ident, $id:expr, $spec:expr) => {{
        let (id, spec): (Uuid, &StageSpec) = ($id, $spec);
        if let Err(msg) = check_unique_tasks(spec) {
            Err(format!("planner: {msg}"))
        } else {
            let existing: i64 =
                sqlx::query_scalar("SELECT count(*) FROM tasks WHERE campaign = $1 AND stage = $2 AND iteration = $3")
                    .bind(id)
                    .bind(&spec.stage)
                    .bind(spec.iteration)
                    .fetch_one(&mut *$tx)
                    .await?;
            if existing > 0 {
                Err(format!("planner: stage {} iteration {} was already run", spec.stage, spec.iteration))
            } else {
                let q = $self.sql("UPDATE campaigns SET stage = $2, iteration = $3, updated_at_ms = NOW_MS WHERE id = $1");
                sqlx::query(&q).bind(id).bind(&spec.stage).bind(spec.iteration).execute(&mut *$tx).await?;
                let msg = format!("stage {} iteration {}: {} tasks", spec.stage, spec.iteration, spec.tasks.len());
                event!($self, $tx, id, "stage", None::<i64>, &msg);
                info!(campaign = %id, stage = %spec.stage, iteration = spec.iteration,
                    tasks = spec.tasks.len(), "stage enqueued");
                if !spec.tasks.is_empty() {
                    insert_tasks!($self, $tx, id, spec);
                }
                Ok(!spec.tasks.is_empty())
            }
        }
    }};
}

/// Runs the planner from the finished stage `$finished` and applies its transitions until one
/// enqueues tasks or ends the campaign (stages without tasks are finished at once); evaluates to
/// the campaign's state afterwards.
macro_rules! apply_plan {
    ($self:ident, $tx:ident, $campaign:ident, $finished:expr, $planner:expr) => {{
        let id = $campaign.id;
        let planner: &dyn StagePlanner = $planner;
        let mut planned = planner.plan(&$campaign, &$finished);
        let mut empty_stages = 0;
        loop {
            let tr = match planned {
                Err(msg) => {
                    fail_campaign!($self, $tx, id, &msg);
                    break CampaignState::Failed;
                }
                Ok(tr) => tr,
            };
            record_transition!($self, $tx, id, &tr);
            $campaign.plan_state = tr.plan_state;
            let spec = match tr.next {
                Next::Succeed => {
                    let q = $self.sql(
                        "UPDATE campaigns SET state = 'succeeded', updated_at_ms = NOW_MS, finished_at_ms = NOW_MS \
                         WHERE id = $1",
                    );
                    sqlx::query(&q).bind(id).execute(&mut *$tx).await?;
                    event!($self, $tx, id, "succeeded", None::<i64>, "campaign succeeded");
                    info!(campaign = %id, "campaign succeeded");
                    break CampaignState::Succeeded;
                }
                Next::Fail(msg) => {
                    fail_campaign!($self, $tx, id, &msg);
                    break CampaignState::Failed;
                }
                Next::Stage(spec) => spec,
            };
            match enter_stage!($self, $tx, id, &spec) {
                Err(msg) => {
                    fail_campaign!($self, $tx, id, &msg);
                    break CampaignState::Failed;
                }
                Ok(true) => break CampaignState::Running,
                Ok(false) => {}
            }
            // A stage without tasks is finished at once: plan again from it.
            empty_stages += 1;
            if empty_stages > MAX_EMPTY_STAGES {
                let msg = format!("planner produced {MAX_EMPTY_STAGES} stages without tasks in a row");
                fail_campaign!($self, $tx, id, &msg);
                break CampaignState::Failed;
            }
            $campaign.stage = spec.stage.clone();
            $campaign.iteration = spec.iteration;
            let finished = FinishedStage { stage: spec.stage, iteration: spec.iteration, tasks: Vec::new(), span_ms: None };
            planned = planner.plan(&$campaign, &finished);
        }
    }};
}

impl JobStore {
    /// The stage barrier: if the campaign is running at `stage`/`iteration` and that stage has no
    /// open (queued or leased) task left, runs the planner on the stage's results and applies its
    /// transition (next stage, success or failure), all under the campaign row lock. The guard on
    /// the campaign's stage makes it happen once whoever calls it (racing last completers, the
    /// reconciler). `None` if there is no such campaign.
    /// `rescue` (the reconciler) records a `stage_rescued` event before the transition's own.
    pub(super) async fn advance_stage(
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
                let finished = finished_stage!(tx, id, stage, iteration);
                if rescue {
                    let msg = format!("stage {stage} iteration {iteration}: all {} tasks done but the stage was not \
                        advanced (its last completer stopped before the barrier); advancing it", finished.tasks.len());
                    event!(self, tx, id, "stage_rescued", None::<i64>, &msg);
                }
                let state = apply_plan!(self, tx, campaign, finished, planner);
                Barrier { advanced: true, state }
            }
        });
        Ok(Some(barrier))
    }
}

/// `(kind, key)` must be unique within a stage: it names the task's objects.
pub(super) fn check_unique_tasks(spec: &StageSpec) -> Result<(), String> {
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
