//! Uploaded inputs: list them with the campaigns that name them, and delete those no campaign
//! names. Listing is open like every read; deleting needs the writer's token.

use crate::admission::authorize;
use crate::errors::ApiError;
use crate::server::ApiState;
use crate::types::{InputEntry, InputList, InputsDeleted};
use axum::extract::{Path, Query, State};
use axum::http::{HeaderMap, StatusCode};
use axum::routing::{delete, get};
use axum::{Json, Router};
use precimap_framework::lifecycle::INPUTS_PREFIX;
use precimap_framework::{is_temporary_key, validate_key};
use serde::Deserialize;
use std::collections::BTreeMap;
use std::sync::Arc;
use uuid::Uuid;

/// `GET /v1/inputs` and `DELETE /v1/inputs/{key}`.
pub(crate) fn routes() -> Router<Arc<ApiState>> {
    Router::new().route("/v1/inputs", get(list_inputs)).route("/v1/inputs/{*key}", delete(delete_inputs))
}

#[derive(Debug, Deserialize)]
struct InputsQuery {
    /// A folder under `inputs/` (e.g. `inputs/0123…`, one upload); all inputs if absent.
    prefix: Option<String>,
    limit: Option<usize>,
}

/// The folder `prefix` names, checked to lie under `inputs/`.
fn inputs_folder(prefix: Option<&str>) -> Result<String, ApiError> {
    let folder = prefix.map(|p| p.trim_end_matches('/')).unwrap_or(INPUTS_PREFIX);
    validate_key(folder).map_err(|m| ApiError::new(StatusCode::BAD_REQUEST, m))?;
    if folder != INPUTS_PREFIX && !folder.starts_with(&format!("{INPUTS_PREFIX}/")) {
        return Err(ApiError::new(
            StatusCode::BAD_REQUEST,
            format!("prefix {folder:?} is not under {INPUTS_PREFIX}/: only inputs are listed"),
        ));
    }
    Ok(folder.to_string())
}

/// Each key's campaigns, from the job store.
async fn campaigns_naming(state: &ApiState, keys: &[String]) -> Result<BTreeMap<String, Vec<Uuid>>, ApiError> {
    let mut naming: BTreeMap<String, Vec<Uuid>> = BTreeMap::new();
    for r in state.framework.jobs.input_references(keys).await? {
        naming.entry(r.key).or_default().push(r.campaign);
    }
    Ok(naming)
}

async fn list_inputs(
    State(state): State<Arc<ApiState>>,
    Query(q): Query<InputsQuery>,
) -> Result<Json<InputList>, ApiError> {
    let folder = inputs_folder(q.prefix.as_deref())?;
    let limit = q.limit.unwrap_or(1000).clamp(1, 10_000);
    let mut objects: Vec<_> =
        state.framework.objects.list_meta(&folder).await?.into_iter().filter(|o| !is_temporary_key(&o.key)).collect();
    objects.sort_by(|a, b| a.key.cmp(&b.key));
    let truncated = objects.len() > limit;
    objects.truncate(limit);
    let keys: Vec<String> = objects.iter().map(|o| o.key.clone()).collect();
    let mut naming = campaigns_naming(&state, &keys).await?;
    let inputs = objects
        .into_iter()
        .map(|o| InputEntry {
            campaigns: naming.remove(&o.key).unwrap_or_default(),
            key: o.key,
            bytes: o.bytes,
            modified_at_ms: o.modified_ms,
        })
        .collect();
    Ok(Json(InputList { inputs, truncated }))
}

/// Deletes the input `inputs/{key}`, or every input under that folder; refused (409, nothing
/// deleted) while any campaign names one of them.
async fn delete_inputs(
    State(state): State<Arc<ApiState>>,
    headers: HeaderMap,
    Path(key): Path<String>,
) -> Result<Json<InputsDeleted>, ApiError> {
    authorize(&state, &headers)?;
    let key = format!("{INPUTS_PREFIX}/{}", key.trim_end_matches('/'));
    validate_key(&key).map_err(|m| ApiError::new(StatusCode::BAD_REQUEST, m))?;
    let objects = &state.framework.objects;
    let keys: Vec<String> = match objects.size(&key).await? {
        Some(_) => vec![key.clone()],
        None => objects.list(&key).await?.into_iter().filter(|k| !is_temporary_key(k)).collect(),
    };
    if keys.is_empty() {
        return Err(ApiError::new(StatusCode::NOT_FOUND, format!("no input {key:?}")));
    }
    let naming = campaigns_naming(&state, &keys).await?;
    if !naming.is_empty() {
        let named: Vec<String> = naming
            .iter()
            .take(5)
            .map(|(k, ids)| {
                format!("{k} (campaign {})", ids.iter().map(Uuid::to_string).collect::<Vec<_>>().join(", "))
            })
            .collect();
        return Err(ApiError::new(
            StatusCode::CONFLICT,
            format!(
                "{} of these inputs are named by campaigns and were not deleted: {}; delete those campaigns first",
                naming.len(),
                named.join("; ")
            ),
        ));
    }
    for k in &keys {
        objects.delete(k).await?;
    }
    tracing::info!(key, deleted = keys.len(), "inputs deleted");
    Ok(Json(InputsDeleted { deleted: keys }))
}
