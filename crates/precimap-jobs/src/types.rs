//! Records and commands of the job store (the public data model).

use std::time::Duration;

use serde::{Deserialize, Serialize};
use uuid::Uuid;

/// Which database a [`crate::JobStore`] talks to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Backend {
    Sqlite,
    Postgres,
}

/// Retry policy of a campaign's tasks (stored with the campaign).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct QueueConfig {
    /// Attempts before a task is dead (≥ 1).
    pub max_attempts: i32,
    /// Back-off after the first failed attempt; doubles with every further attempt.
    pub backoff_base: Duration,
    /// Upper bound of the back-off.
    pub backoff_max: Duration,
}

impl Default for QueueConfig {
    fn default() -> Self {
        QueueConfig { max_attempts: 5, backoff_base: Duration::from_secs(2), backoff_max: Duration::from_secs(300) }
    }
}

impl QueueConfig {
    /// Back-off before the next attempt after `attempt` (1-based) failed: base·2^(attempt−1), capped.
    pub fn backoff(&self, attempt: i32) -> Duration {
        backoff_ms(duration_ms(self.backoff_base), duration_ms(self.backoff_max), attempt)
            .try_into()
            .map(Duration::from_millis)
            .unwrap_or(self.backoff_max)
    }
}

pub(crate) fn duration_ms(d: Duration) -> i64 {
    i64::try_from(d.as_millis()).unwrap_or(i64::MAX)
}

pub(crate) fn backoff_ms(base_ms: i64, max_ms: i64, attempt: i32) -> i64 {
    let doublings = attempt.saturating_sub(1).clamp(0, 62) as u32;
    base_ms.max(0).saturating_mul(1i64 << doublings).min(max_ms.max(0))
}

/// A campaign to create.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct NewCampaign {
    pub name: String,
    /// Manifest and parameters; opaque to the store.
    pub spec: serde_json::Value,
    /// The campaign's parameters, stored once for all its tasks (`JobStore::campaign_params`);
    /// `Null` stores none. Opaque to the store.
    #[serde(default)]
    pub params: serde_json::Value,
    /// The planner's state; replaced at every stage transition.
    pub plan_state: serde_json::Value,
    /// Prefix of every object the campaign writes (returned by `delete_campaign`).
    pub object_prefix: String,
    pub iterations_planned: i32,
    pub strips: Vec<StripRecord>,
    pub trajectories: Vec<TrajectoryRecord>,
    pub queue: QueueConfig,
}

#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct StripRecord {
    pub index: i32,
    pub id: String,
    pub trajectory: String,
    pub uri: String,
    pub points: Option<i64>,
}

#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct TrajectoryRecord {
    pub index: i32,
    pub id: String,
    pub uri: String,
}

#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct TileRecord {
    pub key: String,
    pub strips: Vec<String>,
    pub points: i64,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct IterationRecord {
    pub iteration: i32,
    pub stats: serde_json::Value,
}

/// Life-cycle state of a campaign.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum CampaignState {
    Running,
    Succeeded,
    Failed,
    Cancelled,
}

impl CampaignState {
    pub fn as_str(self) -> &'static str {
        match self {
            CampaignState::Running => "running",
            CampaignState::Succeeded => "succeeded",
            CampaignState::Failed => "failed",
            CampaignState::Cancelled => "cancelled",
        }
    }

    pub fn parse(s: &str) -> Option<CampaignState> {
        match s {
            "running" => Some(CampaignState::Running),
            "succeeded" => Some(CampaignState::Succeeded),
            "failed" => Some(CampaignState::Failed),
            "cancelled" => Some(CampaignState::Cancelled),
            _ => None,
        }
    }

    /// True once the campaign can no longer change.
    pub fn is_finished(self) -> bool {
        self != CampaignState::Running
    }
}

impl std::fmt::Display for CampaignState {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

impl std::str::FromStr for CampaignState {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        CampaignState::parse(s).ok_or_else(|| format!("unknown campaign state `{s}`"))
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CampaignRecord {
    pub id: Uuid,
    pub name: String,
    pub state: CampaignState,
    /// Current (or last) stage.
    pub stage: String,
    pub iteration: i32,
    pub iterations_planned: i32,
    pub spec: serde_json::Value,
    pub plan_state: serde_json::Value,
    pub object_prefix: String,
    pub error: Option<String>,
    pub queue: QueueConfig,
    pub created_at_ms: i64,
    pub updated_at_ms: i64,
    pub finished_at_ms: Option<i64>,
}

/// A campaign's state and position, without its spec and plan state ([`crate::JobStore::campaign_progress`]).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CampaignProgress {
    pub id: Uuid,
    pub name: String,
    pub state: CampaignState,
    pub stage: String,
    pub iteration: i32,
    pub iterations_planned: i32,
    pub error: Option<String>,
}

/// One task to enqueue. `(stage, iteration, kind, key)` is unique within a campaign.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NewTask {
    pub kind: String,
    pub key: String,
    pub input: serde_json::Value,
}

/// A stage to enqueue: its tasks all run before the next stage is planned.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StageSpec {
    pub stage: String,
    pub iteration: i32,
    pub tasks: Vec<NewTask>,
}

/// A task held by one worker until its lease expires.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ClaimedTask {
    pub id: i64,
    pub campaign: Uuid,
    pub stage: String,
    pub iteration: i32,
    pub kind: String,
    pub key: String,
    pub input: serde_json::Value,
    /// 1 for the first attempt.
    pub attempt: i32,
    pub lease_token: Uuid,
    pub lease_expires_at_ms: i64,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TaskOutcome {
    pub result: serde_json::Value,
    pub outputs: Vec<OutputKey>,
}

#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct OutputKey {
    pub name: String,
    pub object_key: String,
}

#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct RecordedOutput {
    pub task_key: String,
    pub kind: String,
    pub name: String,
    pub object_key: String,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FinishedTask {
    pub kind: String,
    pub key: String,
    pub result: serde_json::Value,
    /// Sorted by name.
    pub outputs: Vec<OutputKey>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FinishedStage {
    pub stage: String,
    pub iteration: i32,
    /// Sorted by (kind, key).
    pub tasks: Vec<FinishedTask>,
    /// Wall-clock span of the stage on the database's clock: from its tasks' enqueueing to the
    /// last one's completion (`None` for a stage without tasks).
    #[serde(default)]
    pub span_ms: Option<StageSpan>,
}

/// When a stage's tasks were enqueued and when its last task finished, in milliseconds since the
/// Unix epoch on the database's clock (one clock, whichever executors ran the tasks).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct StageSpan {
    pub enqueued_at_ms: i64,
    pub finished_at_ms: i64,
}

impl StageSpan {
    /// The stage's wall-clock seconds.
    pub fn seconds(&self) -> f64 {
        (self.finished_at_ms - self.enqueued_at_ms).max(0) as f64 / 1000.0
    }
}

/// What follows a finished stage.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum Next {
    Stage(StageSpec),
    Succeed,
    Fail(String),
}

/// The planner's decision at a stage barrier, applied in the barrier's transaction.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Transition {
    pub plan_state: serde_json::Value,
    /// Tiles to record (upserted by key).
    pub tiles: Vec<TileRecord>,
    /// Iteration statistics to record (upserted by iteration).
    pub iteration: Option<IterationRecord>,
    pub next: Next,
}

/// Plans the next stage from a finished one. Pure and synchronous: it runs inside the barrier's
/// transaction, under the campaign row lock, so it must not do I/O.
pub trait StagePlanner: Send + Sync {
    fn plan(&self, campaign: &CampaignRecord, finished: &FinishedStage) -> Result<Transition, String>;
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Completion {
    /// True if this completion closed the stage (and the planner ran). Of last completions racing
    /// each other (and the reconciler), exactly one closes it.
    pub stage_finished: bool,
    pub campaign_state: CampaignState,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum FailOutcome {
    /// Queued again, claimable from `not_before_ms` (database clock).
    Retry { not_before_ms: i64 },
    /// No attempts left or a permanent error: the task is dead and its campaign failed.
    Dead,
}

#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct ReconcileReport {
    /// Expired leases queued again.
    pub requeued: u64,
    /// Expired leases on their last attempt (their campaigns failed).
    pub dead: u64,
    /// Stages whose tasks were all done but whose campaign had not advanced (their last
    /// completer died between its commit and the barrier), advanced now.
    pub advanced: u64,
    /// Campaigns this pass ended (failed by a dead task, or finished by an advanced stage): no
    /// executor's completion saw them end, so the caller cleans up their orphaned objects.
    #[serde(default)]
    pub finished: Vec<Uuid>,
}

/// Task counts by state.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct StateCounts {
    pub queued: i64,
    pub leased: i64,
    pub done: i64,
    pub dead: i64,
    pub cancelled: i64,
}

impl StateCounts {
    pub fn total(&self) -> i64 {
        self.queued + self.leased + self.done + self.dead + self.cancelled
    }
}

/// Task counts of a campaign: the whole campaign (flat fields) and its current stage/iteration.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct TaskCounts {
    pub queued: i64,
    pub leased: i64,
    pub done: i64,
    pub dead: i64,
    pub cancelled: i64,
    pub stage: StateCounts,
}

/// One line of a campaign's progress log.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct EventRecord {
    pub id: i64,
    pub campaign: Uuid,
    pub at_ms: i64,
    /// `campaign_created`, `claimed`, `done`, `retry`, `dead`, `lease_expired`, `released`, `stage_rescued`,
    /// `stage`, `succeeded`, `failed`, `cancelled`.
    pub kind: String,
    pub task_id: Option<i64>,
    pub message: String,
}

/// The queue across campaigns ([`crate::JobStore::queue_depth`]).
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct QueueDepth {
    /// (task kind, state, count) for the open states `queued` and `leased`.
    pub open: Vec<(String, String, i64)>,
    /// Executor loops holding at least one lease.
    pub busy_executors: i64,
}

/// What [`crate::JobStore::delete_campaign_with_inputs`] removed from the database; the caller
/// removes the objects.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct DeletedCampaign {
    /// Prefix of every object the campaign wrote.
    pub object_prefix: String,
    /// Input objects (keys under `inputs/`) the campaign named and no other campaign names.
    pub unreferenced_inputs: Vec<String>,
}

/// A campaign that names an input object ([`crate::JobStore::input_references`]).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct InputReference {
    pub key: String,
    pub campaign: Uuid,
}
