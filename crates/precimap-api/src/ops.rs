//! What an operator's tooling reads: `GET /readyz` (can this server do its work: the job store
//! and the object store answer) and `GET /metrics` (Prometheus text format: this process's
//! series, and the queue and running campaigns read from the job store at each scrape).

use crate::server::ApiState;
use axum::extract::State;
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::{Json, Router};
use precimap_framework::metrics::observe_job_store;
use std::sync::Arc;
use std::time::Duration;

/// Renders the process's metrics in the Prometheus text format (the binary's recorder).
#[derive(Clone)]
pub struct MetricsRenderer(pub Arc<dyn Fn() -> String + Send + Sync>);

impl std::fmt::Debug for MetricsRenderer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("MetricsRenderer")
    }
}

pub(crate) fn routes() -> Router<Arc<ApiState>> {
    Router::new().route("/readyz", get(readyz)).route("/metrics", get(metrics))
}

/// Each check gets this long; a probe that hangs is a failed probe.
const CHECK_TIMEOUT: Duration = Duration::from_secs(3);

/// 200 when the job store and the object store both answer, else 503 naming which does not
/// (never where it is: the logs say that).
async fn readyz(State(state): State<Arc<ApiState>>) -> Response {
    let jobs = tokio::time::timeout(CHECK_TIMEOUT, state.framework.jobs.now_ms());
    let store = tokio::time::timeout(CHECK_TIMEOUT, state.framework.objects.exists("readyz-probe"));
    let (jobs, store) = tokio::join!(jobs, store);
    let failing: Vec<&str> = [("job store", answered(jobs)), ("object store", answered(store))]
        .into_iter()
        .filter_map(|(name, answer)| {
            answer.err().map(|why| {
                tracing::warn!(error = %why, "readiness: {name}");
                name
            })
        })
        .collect();
    if failing.is_empty() {
        (StatusCode::OK, Json(serde_json::json!({ "status": "ready" }))).into_response()
    } else {
        let body = serde_json::json!({ "status": "not ready", "failing": failing });
        (StatusCode::SERVICE_UNAVAILABLE, Json(body)).into_response()
    }
}

/// A check's result within its timeout, or why not.
fn answered<T, E: std::fmt::Display>(result: Result<Result<T, E>, tokio::time::error::Elapsed>) -> Result<(), String> {
    match result {
        Ok(Ok(_)) => Ok(()),
        Ok(Err(e)) => Err(e.to_string()),
        Err(_) => Err(format!("no answer within {CHECK_TIMEOUT:?}")),
    }
}

async fn metrics(State(state): State<Arc<ApiState>>) -> Response {
    let Some(render) = &state.metrics else {
        let body = serde_json::json!({ "error": "this server records no metrics" });
        return (StatusCode::NOT_FOUND, Json(body)).into_response();
    };
    // The queue and the campaigns as the job store has them now; a database that does not
    // answer leaves the last values (and says so in the log), the process's own series stand.
    let observed = tokio::time::timeout(CHECK_TIMEOUT, observe_job_store(&state.framework.jobs)).await;
    if let Err(why) = answered(observed) {
        tracing::warn!(error = %why, "metrics: reading the job store");
    }
    ([(header::CONTENT_TYPE, "text/plain; version=0.0.4; charset=utf-8")], (render.0)()).into_response()
}
