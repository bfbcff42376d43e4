//! The REST core (axum), which also serves the dashboard's page. Reads are open (the status
//! dashboard needs no secret); every write needs `Authorization: Bearer <token>`. Request bodies
//! are bounded: manifests by `max_manifest_bytes`, uploads by `max_upload_bytes`. Uploads may only
//! create objects under `inputs/`, so a client can never overwrite a campaign's work or results.

use crate::types::{CampaignStatus, CampaignSummary, ErrorBody, Events, Problem, ResultEntry, Submitted, Uploaded};
use axum::body::Body;
use axum::extract::{DefaultBodyLimit, Path, Query, State};
use axum::http::{header, HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post, put};
use axum::{Json, Router};
use futures::TryStreamExt;
use precimap_formats::ManifestError;
use precimap_framework::{validate_key, CampaignLimits, Framework, FrameworkError, SubmitError};
use precimap_jobs::JobError;
use serde::Deserialize;
use std::sync::Arc;
use uuid::Uuid;

/// How writers prove who they are.
#[derive(Clone, Debug)]
pub enum Auth {
    /// Writes need `Authorization: Bearer <token>`.
    Token(String),
    /// No authentication (only for a server bound to loopback in tests and the embedded mode).
    Disabled,
}

#[derive(Clone, Debug)]
pub struct ApiState {
    pub framework: Framework,
    pub auth: Auth,
    pub max_manifest_bytes: usize,
    pub max_upload_bytes: u64,
    /// Bounds on a submitted campaign's size.
    pub limits: CampaignLimits,
}

impl ApiState {
    pub fn new(framework: Framework, auth: Auth) -> Self {
        Self {
            framework,
            auth,
            max_manifest_bytes: 4 << 20,
            max_upload_bytes: 64 << 30,
            limits: CampaignLimits::default(),
        }
    }
}

/// The API's router.
pub fn app(state: ApiState) -> Router {
    let manifest_limit = state.max_manifest_bytes;
    let state = Arc::new(state);
    Router::new()
        .route("/healthz", get(healthz))
        .route("/v1/token", get(check_token))
        .route("/v1/campaigns", get(list_campaigns).post(submit_campaign).layer(DefaultBodyLimit::max(manifest_limit)))
        .route("/v1/campaigns/{id}", get(campaign_status).delete(delete_campaign))
        .route("/v1/campaigns/{id}/cancel", post(cancel_campaign))
        .route("/v1/campaigns/{id}/events", get(campaign_events))
        .route("/v1/campaigns/{id}/results", get(list_results))
        .route("/v1/campaigns/{id}/results/{*name}", get(download_result))
        // Uploads stream to the store with their own limit (checked while streaming).
        .route("/v1/objects/{*key}", put(upload_object).layer(DefaultBodyLimit::disable()))
        .merge(crate::inputs::routes())
        .merge(crate::dashboard::routes())
        .with_state(state)
}

/// An error response: a status and a JSON body saying what is wrong and what to do.
#[derive(Debug)]
pub struct ApiError {
    status: StatusCode,
    body: ErrorBody,
}

impl ApiError {
    pub(crate) fn new(status: StatusCode, error: impl Into<String>) -> Self {
        Self { status, body: ErrorBody { error: error.into(), problems: Vec::new() } }
    }

    fn not_found(id: Uuid) -> Self {
        Self::new(StatusCode::NOT_FOUND, format!("no campaign {id}"))
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let mut response = (self.status, Json(self.body)).into_response();
        if self.status == StatusCode::UNAUTHORIZED {
            response.headers_mut().insert(header::WWW_AUTHENTICATE, header::HeaderValue::from_static("Bearer"));
        }
        response
    }
}

impl From<JobError> for ApiError {
    fn from(e: JobError) -> Self {
        let status = if e.is_transient() { StatusCode::SERVICE_UNAVAILABLE } else { StatusCode::INTERNAL_SERVER_ERROR };
        tracing::error!(error = %e, "job store");
        Self::new(status, format!("job store: {e}"))
    }
}

impl From<FrameworkError> for ApiError {
    fn from(e: FrameworkError) -> Self {
        match e {
            FrameworkError::Jobs(j) => j.into(),
            FrameworkError::BadKey { .. } | FrameworkError::Invalid(_) => {
                Self::new(StatusCode::BAD_REQUEST, e.to_string())
            }
            FrameworkError::TooLarge { .. } => Self::new(StatusCode::PAYLOAD_TOO_LARGE, e.to_string()),
            FrameworkError::Exists { .. } => Self::new(StatusCode::CONFLICT, e.to_string()),
            ref other if other.is_not_found() => Self::new(StatusCode::NOT_FOUND, e.to_string()),
            other => {
                tracing::error!(error = %other, "object store");
                Self::new(StatusCode::BAD_GATEWAY, format!("object store: {other}"))
            }
        }
    }
}

pub(crate) fn authorize(state: &ApiState, headers: &HeaderMap) -> Result<(), ApiError> {
    let Auth::Token(expected) = &state.auth else { return Ok(()) };
    let given = headers
        .get(header::AUTHORIZATION)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.strip_prefix("Bearer "))
        .map(str::trim);
    match given {
        Some(token) if constant_time_eq(token.as_bytes(), expected.as_bytes()) => Ok(()),
        Some(_) => Err(ApiError::new(StatusCode::UNAUTHORIZED, "wrong bearer token")),
        None => Err(ApiError::new(
            StatusCode::UNAUTHORIZED,
            "writes need `Authorization: Bearer <token>` (the server's PRECIMAP_TOKEN)",
        )),
    }
}

/// Compares without an early exit, so response time does not reveal how much of a guess was
/// right (the length may leak; the token's entropy does not depend on it).
fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

fn parse_id(id: &str) -> Result<Uuid, ApiError> {
    Uuid::parse_str(id).map_err(|_| ApiError::new(StatusCode::NOT_FOUND, format!("{id:?} is not a campaign id")))
}

async fn healthz(State(state): State<Arc<ApiState>>) -> Result<Json<serde_json::Value>, ApiError> {
    state.framework.jobs.list_campaigns(1).await?;
    Ok(Json(serde_json::json!({ "status": "ok", "store": state.framework.objects.url() })))
}

/// Lets a client check its token before it streams gigabytes of input (a server that rejects an
/// upload mid-stream can only reset the connection).
async fn check_token(State(state): State<Arc<ApiState>>, headers: HeaderMap) -> Result<StatusCode, ApiError> {
    authorize(&state, &headers)?;
    Ok(StatusCode::NO_CONTENT)
}

#[derive(Debug, Deserialize)]
struct ListQuery {
    limit: Option<i64>,
}

async fn list_campaigns(
    State(state): State<Arc<ApiState>>,
    Query(q): Query<ListQuery>,
) -> Result<Json<Vec<CampaignSummary>>, ApiError> {
    let limit = q.limit.unwrap_or(100).clamp(1, 1000);
    let campaigns = state.framework.jobs.list_campaigns(limit).await?;
    Ok(Json(campaigns.iter().map(CampaignSummary::from).collect()))
}

async fn submit_campaign(
    State(state): State<Arc<ApiState>>,
    headers: HeaderMap,
    body: bytes::Bytes,
) -> Result<(StatusCode, Json<Submitted>), ApiError> {
    authorize(&state, &headers)?;
    let text = std::str::from_utf8(&body)
        .map_err(|_| ApiError::new(StatusCode::BAD_REQUEST, "the manifest must be UTF-8 JSON"))?;
    let manifest = precimap_formats::parse_manifest(text).map_err(|e| match e {
        ManifestError::Invalid { problems, .. } => ApiError {
            status: StatusCode::UNPROCESSABLE_ENTITY,
            body: ErrorBody {
                error: format!("the manifest has {} problem(s)", problems.len()),
                problems: problems.into_iter().map(|p| Problem { path: p.path, message: p.message }).collect(),
            },
        },
        other => ApiError::new(StatusCode::UNPROCESSABLE_ENTITY, other.to_string()),
    })?;
    let id = state.framework.submit_with_limits(&manifest, &state.limits).await.map_err(|e| match e {
        SubmitError::Invalid { problems } => ApiError {
            status: StatusCode::UNPROCESSABLE_ENTITY,
            body: ErrorBody {
                error: format!("the manifest has {} problem(s)", problems.len()),
                problems: problems.into_iter().map(|p| Problem { path: p.path, message: p.message }).collect(),
            },
        },
        SubmitError::Framework(f) => f.into(),
    })?;
    tracing::info!(%id, name = %manifest.name, "campaign submitted");
    Ok((StatusCode::CREATED, Json(Submitted { id, href: format!("/v1/campaigns/{id}") })))
}

async fn campaign_status(
    State(state): State<Arc<ApiState>>,
    Path(id): Path<String>,
) -> Result<Json<CampaignStatus>, ApiError> {
    let id = parse_id(&id)?;
    let jobs = &state.framework.jobs;
    let campaign = jobs.campaign(id).await?.ok_or_else(|| ApiError::not_found(id))?;
    let counts = jobs.task_counts(id).await?;
    let iterations = jobs.iterations(id).await?;
    Ok(Json(CampaignStatus::new(&campaign, counts, &iterations)))
}

async fn cancel_campaign(
    State(state): State<Arc<ApiState>>,
    headers: HeaderMap,
    Path(id): Path<String>,
) -> Result<Json<serde_json::Value>, ApiError> {
    authorize(&state, &headers)?;
    let id = parse_id(&id)?;
    let jobs = &state.framework.jobs;
    let campaign = jobs.campaign(id).await?.ok_or_else(|| ApiError::not_found(id))?;
    if !state.framework.cancel(id).await? {
        return Err(ApiError::new(
            StatusCode::CONFLICT,
            format!("campaign {id} has already finished ({})", campaign.state.as_str()),
        ));
    }
    Ok(Json(serde_json::json!({ "id": id, "state": "cancelled" })))
}

async fn delete_campaign(
    State(state): State<Arc<ApiState>>,
    headers: HeaderMap,
    Path(id): Path<String>,
) -> Result<StatusCode, ApiError> {
    authorize(&state, &headers)?;
    let id = parse_id(&id)?;
    if let Some(c) = state.framework.jobs.campaign(id).await? {
        if c.state == precimap_jobs::CampaignState::Running {
            return Err(ApiError::new(StatusCode::CONFLICT, format!("campaign {id} is running; cancel it first")));
        }
    }
    if state.framework.delete(id).await? {
        Ok(StatusCode::NO_CONTENT)
    } else {
        Err(ApiError::not_found(id))
    }
}

#[derive(Debug, Deserialize)]
struct EventsQuery {
    after: Option<i64>,
    limit: Option<i64>,
    tail: Option<i64>,
}

/// `after` pages forward through the log; `tail=N` returns its newest N events (oldest first),
/// from which a client follows with `after`.
async fn campaign_events(
    State(state): State<Arc<ApiState>>,
    Path(id): Path<String>,
    Query(q): Query<EventsQuery>,
) -> Result<Json<Events>, ApiError> {
    let id = parse_id(&id)?;
    let jobs = &state.framework.jobs;
    let events = match (q.tail, q.after, q.limit) {
        (Some(tail), None, None) => jobs.latest_events(id, tail.clamp(1, 1000)).await?,
        (None, after, limit) => jobs.events(id, after.unwrap_or(0), limit.unwrap_or(200).clamp(1, 1000)).await?,
        (Some(_), _, _) => {
            return Err(ApiError::new(
                StatusCode::BAD_REQUEST,
                "`tail` returns the newest events and takes neither `after` nor `limit`; follow it with `after`",
            ))
        }
    };
    Ok(Json(Events { events }))
}

async fn list_results(
    State(state): State<Arc<ApiState>>,
    Path(id): Path<String>,
) -> Result<Json<Vec<ResultEntry>>, ApiError> {
    let id = parse_id(&id)?;
    let campaign = state.framework.jobs.campaign(id).await?.ok_or_else(|| ApiError::not_found(id))?;
    if campaign.state != precimap_jobs::CampaignState::Succeeded {
        return Err(ApiError::new(
            StatusCode::CONFLICT,
            format!("campaign {id} is {}; results exist once it has succeeded", campaign.state.as_str()),
        ));
    }
    let results = state.framework.results(id).await?;
    Ok(Json(
        results
            .into_iter()
            .map(|(name, _)| ResultEntry { href: format!("/v1/campaigns/{id}/results/{name}"), name })
            .collect(),
    ))
}

async fn download_result(
    State(state): State<Arc<ApiState>>,
    Path((id, name)): Path<(String, String)>,
) -> Result<Response, ApiError> {
    let id = parse_id(&id)?;
    let results = state.framework.results(id).await?;
    let key = results
        .into_iter()
        .find(|(n, _)| *n == name)
        .map(|(_, k)| k)
        .ok_or_else(|| ApiError::new(StatusCode::NOT_FOUND, format!("campaign {id} has no result {name:?}")))?;
    let (size, stream) = state.framework.objects.stream(&key).await?;
    let content_type = if name.ends_with(".json") {
        "application/json"
    } else if name.ends_with(".csv") {
        "text/csv"
    } else if name.ends_with(".svg") {
        // The QC plots: a browser shows them in place.
        "image/svg+xml"
    } else {
        "application/octet-stream"
    };
    Response::builder()
        .header(header::CONTENT_TYPE, content_type)
        // Results are data, never active content: no sniffing, and an SVG opened directly runs
        // no script and loads nothing but its own embedded images (its styles are attributes).
        .header(header::X_CONTENT_TYPE_OPTIONS, "nosniff")
        .header(header::CONTENT_SECURITY_POLICY, "default-src 'none'; img-src data:; sandbox")
        .header(header::CONTENT_LENGTH, size)
        .body(Body::from_stream(stream))
        .map_err(|e| ApiError::new(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()))
}

async fn upload_object(
    State(state): State<Arc<ApiState>>,
    headers: HeaderMap,
    Path(key): Path<String>,
    body: Body,
) -> Result<(StatusCode, Json<Uploaded>), ApiError> {
    authorize(&state, &headers)?;
    validate_key(&key).map_err(|m| ApiError::new(StatusCode::BAD_REQUEST, m))?;
    if !key.starts_with("inputs/") {
        return Err(ApiError::new(
            StatusCode::FORBIDDEN,
            format!("uploads may only create objects under inputs/, not {key:?}"),
        ));
    }
    let limit = state.max_upload_bytes;
    if let Some(len) =
        headers.get(header::CONTENT_LENGTH).and_then(|v| v.to_str().ok()).and_then(|v| v.parse::<u64>().ok())
    {
        if len > limit {
            return Err(ApiError::new(
                StatusCode::PAYLOAD_TOO_LARGE,
                format!("{key}: {len} bytes exceed the upload limit of {limit} bytes"),
            ));
        }
    }
    let stream = body.into_data_stream().map_err(|e| e.to_string());
    let bytes = state.framework.objects.put_stream(&key, stream, limit).await?;
    Ok((StatusCode::CREATED, Json(Uploaded { key, bytes })))
}
