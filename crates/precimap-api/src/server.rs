//! The REST core (axum), which also serves the dashboard's page. Reads are open (the status
//! dashboard needs no secret); every write needs `Authorization: Bearer <token>`. Request bodies
//! are bounded: manifests by `max_manifest_bytes`, uploads by `max_upload_bytes`. Uploads may only
//! create objects under `inputs/`, so a client can never overwrite a campaign's work or results.

use crate::admission::{admit, authorize, overloaded, Admission, AdmissionLimits, Auth};
use crate::errors::{json_errors, no_route, panicked, scrub, ApiError};
use crate::types::{CampaignStatus, CampaignSummary, Events, Problem, ResultEntry, Submitted, Uploaded};
use axum::body::Body;
use axum::error_handling::HandleErrorLayer;
use axum::extract::{DefaultBodyLimit, Path, Query, State};
use axum::http::{header, HeaderMap, StatusCode};
use axum::response::Response;
use axum::routing::{get, post, put};
use axum::{middleware, Json, Router};
use futures::TryStreamExt;
use precimap_formats::ManifestError;
use precimap_framework::{validate_key, CampaignLimits, Framework, FrameworkError, SubmitError};
use precimap_jobs::EventRecord;
use serde::Deserialize;
use std::sync::Arc;
use tower::limit::GlobalConcurrencyLimitLayer;
use tower::ServiceBuilder;
use tower_http::catch_panic::CatchPanicLayer;
use uuid::Uuid;

#[derive(Clone, Debug)]
pub struct ApiState {
    pub framework: Framework,
    pub auth: Auth,
    pub max_manifest_bytes: usize,
    pub max_upload_bytes: u64,
    /// `GET /metrics` renders these (404 without a recorder).
    pub metrics: Option<crate::ops::MetricsRenderer>,
    pub admission: Arc<Admission>,
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
            admission: Arc::new(Admission::new(AdmissionLimits::default())),
            metrics: None,
            limits: CampaignLimits::default(),
        }
    }

    pub fn with_admission(mut self, limits: AdmissionLimits) -> Self {
        self.admission = Arc::new(Admission::new(limits));
        self
    }
}

/// The API's router: its routes behind the admission checks (see [`crate::admission`]), every
/// error answered in the JSON error shape.
pub fn app(state: ApiState) -> Router {
    let max_in_flight = state.admission.limits.max_in_flight.max(1);
    let state = Arc::new(state);
    let shed = ServiceBuilder::new()
        .layer(HandleErrorLayer::new(overloaded))
        .load_shed()
        .layer(GlobalConcurrencyLimitLayer::new(max_in_flight));
    Router::new()
        .route("/healthz", get(healthz))
        .route("/v1/token", get(check_token))
        .route("/v1/campaigns", get(list_campaigns).post(submit_campaign))
        .route("/v1/campaigns/{id}", get(campaign_status).delete(delete_campaign))
        .route("/v1/campaigns/{id}/cancel", post(cancel_campaign))
        .route("/v1/campaigns/{id}/events", get(campaign_events))
        .route("/v1/campaigns/{id}/results", get(list_results))
        .route("/v1/campaigns/{id}/results/{*name}", get(download_result))
        // Uploads stream to the store with their own limit (checked while streaming).
        .route("/v1/objects/{*key}", put(upload_object).layer(DefaultBodyLimit::disable()))
        .merge(crate::inputs::routes())
        .merge(crate::dashboard::routes())
        .merge(crate::ops::routes())
        .fallback(no_route)
        .layer(shed)
        .layer(middleware::from_fn_with_state(state.clone(), admit))
        .layer(CatchPanicLayer::custom(panicked))
        .layer(middleware::from_fn(json_errors))
        .with_state(state)
}

fn parse_id(id: &str) -> Result<Uuid, ApiError> {
    Uuid::parse_str(id).map_err(|_| ApiError::new(StatusCode::NOT_FOUND, format!("{id:?} is not a campaign id")))
}

async fn healthz(State(state): State<Arc<ApiState>>) -> Result<Json<serde_json::Value>, ApiError> {
    state.framework.jobs.list_campaigns(1).await?;
    // Where the stores are is the operator's business: the answer names neither.
    Ok(Json(serde_json::json!({ "status": "ok" })))
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
    Ok(Json(campaigns.iter().map(|c| scrubbed(CampaignSummary::from(c))).collect()))
}

async fn submit_campaign(
    State(state): State<Arc<ApiState>>,
    headers: HeaderMap,
    body: Body,
) -> Result<(StatusCode, Json<Submitted>), ApiError> {
    authorize(&state, &headers)?;
    let limit = state.max_manifest_bytes;
    let too_large = || {
        ApiError::new(
            StatusCode::PAYLOAD_TOO_LARGE,
            format!("the manifest exceeds {limit} bytes, the most this server accepts; split the campaign"),
        )
    };
    if content_length(&headers).is_some_and(|len| len > limit as u64) {
        return Err(too_large());
    }
    // Read up to the limit and no further: a longer body fails as soon as it passes it.
    let mut body = body.into_data_stream();
    let mut manifest_bytes = Vec::new();
    while let Some(chunk) = body.try_next().await.map_err(|e| {
        ApiError::new(StatusCode::BAD_REQUEST, format!("the manifest did not arrive whole: {}", root_cause(&e)))
    })? {
        if manifest_bytes.len() + chunk.len() > limit {
            return Err(too_large());
        }
        manifest_bytes.extend_from_slice(&chunk);
    }
    let body = manifest_bytes;
    let text = std::str::from_utf8(&body)
        .map_err(|_| ApiError::new(StatusCode::BAD_REQUEST, "the manifest must be UTF-8 JSON"))?;
    let manifest = precimap_formats::parse_manifest(text).map_err(|e| match e {
        ManifestError::Invalid { problems, .. } => ApiError::with_problems(
            StatusCode::UNPROCESSABLE_ENTITY,
            problems.into_iter().map(|p| Problem { path: p.path, message: p.message }).collect(),
        ),
        other => ApiError::new(StatusCode::UNPROCESSABLE_ENTITY, other.to_string()),
    })?;
    let id = state.framework.submit_with_limits(&manifest, &state.limits).await.map_err(|e| match e {
        SubmitError::Invalid { problems } => ApiError::with_problems(
            StatusCode::UNPROCESSABLE_ENTITY,
            problems.into_iter().map(|p| Problem { path: p.path, message: p.message }).collect(),
        ),
        SubmitError::Framework(f) => f.into(),
    })?;
    tracing::info!(%id, name = %manifest.name, "campaign submitted");
    Ok((StatusCode::CREATED, Json(Submitted { id, href: format!("/v1/campaigns/{id}") })))
}

fn content_length(headers: &HeaderMap) -> Option<u64> {
    headers.get(header::CONTENT_LENGTH)?.to_str().ok()?.parse().ok()
}

/// The innermost cause of a body error (the outer layers only say "error reading a body").
fn root_cause(e: &(dyn std::error::Error + 'static)) -> String {
    let mut inner = e;
    while let Some(next) = inner.source() {
        inner = next;
    }
    inner.to_string()
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
    let mut status = CampaignStatus::new(&campaign, counts, &iterations);
    status.campaign = scrubbed(status.campaign);
    Ok(Json(status))
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
    let events = events.into_iter().map(|e| EventRecord { message: scrub(&e.message), ..e }).collect();
    Ok(Json(Events { events }))
}

/// A campaign's error as a client may see it (task errors can quote local paths).
fn scrubbed(mut summary: CampaignSummary) -> CampaignSummary {
    summary.error = summary.error.as_deref().map(scrub);
    summary
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
    if let Some(len) = content_length(&headers) {
        if len > limit {
            return Err(ApiError::new(
                StatusCode::PAYLOAD_TOO_LARGE,
                format!("{key}: {len} bytes exceed the upload limit of {limit} bytes"),
            ));
        }
    }
    let stream = body.into_data_stream().map_err(|e| root_cause(&e));
    let bytes = state.framework.objects.put_stream(&key, stream, limit).await.map_err(|e| upload_error(&key, e))?;
    Ok((StatusCode::CREATED, Json(Uploaded { key, bytes })))
}

/// An upload that names a folder, or a file where it needs a folder, conflicts with what the
/// store holds: the client's to fix, and said without the store's own paths.
fn upload_error(key: &str, e: FrameworkError) -> ApiError {
    use std::io::ErrorKind;
    match &e {
        FrameworkError::Io { source, .. }
            if matches!(
                source.kind(),
                ErrorKind::AlreadyExists
                    | ErrorKind::NotADirectory
                    | ErrorKind::IsADirectory
                    | ErrorKind::DirectoryNotEmpty
            ) =>
        {
            tracing::info!(key, error = %e, "upload conflicts with the store's contents");
            ApiError::new(
                StatusCode::CONFLICT,
                format!(
                    "{key} conflicts with an object or folder the store holds (a key cannot be both an object and \
                     the folder of others); upload under another key"
                ),
            )
        }
        _ => e.into(),
    }
}
