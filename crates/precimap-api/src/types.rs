//! The JSON bodies of the API, shared by server and client.

use precimap_jobs::{CampaignRecord, EventRecord, IterationRecord, TaskCounts};
use serde::{Deserialize, Serialize};
use uuid::Uuid;

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Problem {
    pub path: String,
    pub message: String,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ErrorBody {
    pub error: String,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub problems: Vec<Problem>,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Submitted {
    pub id: Uuid,
    pub href: String,
}

/// `GET /v1/campaigns/{id}`: the summary's fields, then progress (one flat JSON object).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct CampaignStatus {
    #[serde(flatten)]
    pub campaign: CampaignSummary,
    pub updated_at_ms: i64,
    pub tasks: TaskCounts,
    /// One entry per finished iteration (grid, threshold, points used, residual σ, max change…).
    pub iterations: Vec<serde_json::Value>,
}

impl CampaignStatus {
    pub fn new(c: &CampaignRecord, tasks: TaskCounts, iterations: &[IterationRecord]) -> Self {
        Self {
            campaign: CampaignSummary::from(c),
            updated_at_ms: c.updated_at_ms,
            tasks,
            iterations: iterations.iter().map(|i| i.stats.clone()).collect(),
        }
    }
}

/// `GET /v1/campaigns` lists these.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct CampaignSummary {
    pub id: Uuid,
    pub name: String,
    pub state: String,
    pub stage: String,
    pub iteration: i32,
    pub iterations_planned: i32,
    pub error: Option<String>,
    pub created_at_ms: i64,
    pub finished_at_ms: Option<i64>,
}

impl From<&CampaignRecord> for CampaignSummary {
    fn from(c: &CampaignRecord) -> Self {
        Self {
            id: c.id,
            name: c.name.clone(),
            state: c.state.as_str().to_string(),
            stage: c.stage.clone(),
            iteration: c.iteration,
            iterations_planned: c.iterations_planned,
            error: c.error.clone(),
            created_at_ms: c.created_at_ms,
            finished_at_ms: c.finished_at_ms,
        }
    }
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ResultEntry {
    /// Path inside a result folder: `strips/…`, `trajectories/…`, `report.json`.
    pub name: String,
    pub href: String,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Events {
    pub events: Vec<EventRecord>,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Uploaded {
    pub key: String,
    pub bytes: u64,
}

/// `GET /v1/inputs`: uploaded input objects, sorted by key.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct InputList {
    pub inputs: Vec<InputEntry>,
    /// More inputs match than `limit` allowed to list.
    pub truncated: bool,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct InputEntry {
    pub key: String,
    pub bytes: u64,
    pub modified_at_ms: i64,
    /// The campaigns whose manifests name it (it cannot be deleted while any does).
    pub campaigns: Vec<Uuid>,
}

/// `DELETE /v1/inputs/{key}`: the input objects removed.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct InputsDeleted {
    pub deleted: Vec<String>,
}
